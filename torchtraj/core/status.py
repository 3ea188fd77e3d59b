"""Per-instance solver status.

Every solver returns ``Solution.status``, an integer tensor ``(B,)`` whose values are
members of :class:`Status`, so ``sol.status == tt.Status.CONVERGED`` is a boolean mask.
A failing instance is reported here; it never raises and never changes another
instance's answer.
"""

from __future__ import annotations

import enum

import torch


class Status(enum.IntEnum):
    """Outcome of one instance of a batched solve."""

    #: Still iterating (only seen inside solvers and in truncated histories).
    RUNNING = -1
    #: Met the method's convergence tolerances at a KKT point (:mod:`torchtraj.kkt.certificate`).
    CONVERGED = 0
    #: Hit the iteration limit before meeting the tolerances.
    MAX_ITERATIONS = 1
    #: Cost, state or control grew beyond the divergence limits.
    DIVERGED = 2
    #: A non-finite value (NaN / inf) appeared, e.g. from a NaN initial state.
    NON_FINITE = 3
    #: The regularisation reached its maximum without a successful step.
    MAX_REGULARIZATION = 4
    #: The initial guess could not be used (e.g. non-finite rollout of the initial controls).
    INFEASIBLE_START = 5
    #: The method's own stopping test passed at a point that is not a KKT point to the certificate's tolerances
    #: (:mod:`torchtraj.kkt.certificate`; ``Solution.kkt`` holds the residuals): tighten the method's tolerances.
    STALLED = 6
    #: Converged to a stationary point of the constraint violation that is not feasible: the instance is
    #: (locally) infeasible (the interior-point method's restoration phase, Wächter & Biegler 2006 §3.3).
    LOCALLY_INFEASIBLE = 7

    @classmethod
    def describe(cls, status: torch.Tensor) -> list:
        """Names of the statuses of a ``(B,)`` tensor, for printing."""
        return [cls(int(s)).name.lower() for s in status.reshape(-1).tolist()]

    @classmethod
    def counts(cls, status: torch.Tensor) -> dict:
        """``{name: count}`` of the statuses present in ``status``."""
        out = {}
        for name in cls.describe(status):
            out[name] = out.get(name, 0) + 1
        return out
