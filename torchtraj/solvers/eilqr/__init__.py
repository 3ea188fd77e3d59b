"""eILQR (method ``"eilqr"``) as a :class:`~torchtraj.solvers.base.Solver` object; the algorithm is
:mod:`torchtraj.solvers.eilqr.solver`.

Horizon's equality-constrained iLQR (Laurenzi, Ruscelli & Tsagarakis): Newton's method on the KKT conditions with
multipliers, constraint back-propagation, an optional free initial state and an exact ℓ1 merit. Its equalities are
exact; its inequalities and bounds are soft barriers on the cost (:mod:`~torchtraj.solvers.eilqr.barrier`). By
default their weight decreases between Newton stages down to a tolerance-sized one, with primal-dual steps (an
extension beyond the paper, :mod:`~torchtraj.solvers.eilqr.continuation`), so that a converged solution is a KKT
point of the problem with hard inequalities. With ``barrier_continuation=False`` (the paper's fixed weight) it is a
KKT point of :meth:`EILQR.kkt_problem` (the barrier-augmented, equality-constrained problem): the certificate, the
contract test and the implicit layer then check and differentiate that problem. It takes a state guess ``X0``
(multiple shooting; without one, the problem's own ``X_init`` where it has one, outside a control step) and no
warm-started duals.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

from torch import Tensor

from ...core.batch import Batch
from ...core.problem import Problem
from ...core.solution import Solution
from ..base import Solver
from .barrier import soft_problem
from .options import EILQROptions
from .solver import solve_eilqr, start_states


class EILQR(Solver):
    """Method ``"eilqr"``: :func:`~torchtraj.solvers.eilqr.solver.solve_eilqr`."""

    name = "eilqr"
    options_class = EILQROptions
    handles_constraints = True
    records = True
    takes_state_guess = True
    takes_duals = False
    starts_from_shifted_states = True
    compiles = True

    def solve(self, problem: Problem, batch: Batch, options: EILQROptions) -> Solution:
        return solve_eilqr(problem, batch, options, method=self.name)

    def start_states(self, problem: Problem, batch: Batch, options: EILQROptions) -> Tensor:
        return start_states(problem, batch, options)

    def step_defaults(self) -> EILQROptions:
        """A control step's options: the paper's fixed weight (a few warm-started iterations a step track the moving
        optimum, no continuation), ten times stiffer than a solve's first (``w = 1e-3``, ``δ = 1e-4``); with
        ``w = 1e-4`` three iterations a step did not swing the contract test's pendulum up. The expansion is
        replayed from its recorded graph (``record``): a controller's steps repeat the same shapes. The last
        iterate is left untested (``test_last_iterate=False``): the controller applies the plan whatever its
        status, so a step whose budget runs out reports ``MAX_ITERATIONS`` without the expansion that would test
        it."""
        return EILQROptions(barrier_weight=1e-3, barrier_relaxation=1e-4, barrier_continuation=False, record=True,
                            test_last_iterate=False)

    def step_options(self, options, iterations, compile=False) -> EILQROptions:
        """The base's, never from the problem's state guess: a control step starts from the shifted controls of
        the last one, and ``X_init`` belongs to the problem's own ``x0``."""
        return dataclasses.replace(super().step_options(options, iterations, compile), problem_state_guess=False)

    def kkt_problem(self, problem: Problem, options) -> Optional[Problem]:
        """With a fixed weight (``barrier_continuation=False``), ``problem`` with its inequalities as the soft
        barriers of ``options``: what a converged solution is a KKT point of (a fixed initial state; with
        ``free_initial_state`` the start's stationarity holds as well). With continuation ``None``: the problem
        itself, inequalities hard."""
        opts = self.options(options)
        if opts.barrier_continuation:
            return None
        return soft_problem(problem, opts.barrier_weight, opts.barrier_relaxation)

    def fixes_initial_state(self, options) -> bool:
        return self.options(options).free_initial_state is False


__all__ = ["EILQR", "EILQROptions"]
