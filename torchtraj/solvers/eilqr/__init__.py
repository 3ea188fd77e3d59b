"""eILQR (method ``"eilqr"``) as a :class:`~torchtraj.solvers.base.Solver` object; the algorithm is
:mod:`torchtraj.solvers.eilqr.solver`.

Horizon's equality-constrained iLQR (Laurenzi, Ruscelli & Tsagarakis): Newton's method on the KKT conditions with
multipliers, constraint back-propagation, an optional free initial state and an exact ℓ1 merit. Its equalities are
exact; its inequalities and bounds are soft barriers on the cost (:mod:`~torchtraj.solvers.eilqr.barrier`), so a
converged solution is a KKT point of :meth:`EILQR.kkt_problem` (the barrier-augmented, equality-constrained
problem), not of the hard-inequality one: the contract test and the implicit layer check and differentiate that
problem. It takes a state guess ``X0`` (multiple shooting) and no warm-started duals.
"""

from __future__ import annotations

from ...core.batch import Batch
from ...core.problem import Problem
from ...core.solution import Solution
from ..base import Solver
from .barrier import soft_problem
from .options import EILQROptions
from .solver import solve_eilqr


class EILQR(Solver):
    """Method ``"eilqr"``: :func:`~torchtraj.solvers.eilqr.solver.solve_eilqr`."""

    name = "eilqr"
    options_class = EILQROptions
    handles_constraints = True
    takes_state_guess = True
    takes_duals = False

    def solve(self, problem: Problem, batch: Batch, options: EILQROptions) -> Solution:
        return solve_eilqr(problem, batch, options, method=self.name)

    def step_defaults(self) -> EILQROptions:
        """A control step's options: a barrier ten times stiffer than a solve's (``w = 1e-3``, ``δ = 1e-4``). A few
        warm-started iterations a step then track the moving optimum; with the solve's ``w = 1e-4`` three iterations
        a step did not swing the contract test's pendulum up."""
        return EILQROptions(barrier_weight=1e-3, barrier_relaxation=1e-4)

    def kkt_problem(self, problem: Problem, options) -> Problem:
        """``problem`` with its inequalities as the soft barriers of ``options``: what a converged solution is a KKT
        point of (a fixed initial state; with ``free_initial_state`` the start's stationarity holds as well)."""
        opts = self.options(options)
        return soft_problem(problem, opts.barrier_weight, opts.barrier_relaxation)

    def fixes_initial_state(self, options) -> bool:
        return self.options(options).free_initial_state is False


__all__ = ["EILQR", "EILQROptions"]
