r"""HM-iLQR (method ``"hm-ilqr"``) as a :class:`~torchtraj.solvers.base.Solver` object; the algorithm is
:mod:`torchtraj.solvers.hm_ilqr.solver`.

It handles the constraints (AL stage, then the relaxed log barrier), takes a state guess ``X0`` (multiple shooting:
any, dynamically inconsistent guess) and no warm-started duals (its multipliers and barrier start afresh at every
solve). A control step (``tt.MPC``) starts in the RLB stage (``al_iterations=0``): its warm-started controls are near
a solution, and an AL stage that restarts its multipliers at every step never gets far enough to hold the bounds
(on the contract's pendulum swing-up it does not come up within 70 steps; started in the RLB stage it is upright
from about step 45). A converged solution is a KKT point up to the barrier's final weight, which the implicit layer
refines.
"""

from __future__ import annotations

from torch import Tensor

from ...core.batch import Batch
from ...core.problem import Problem
from ...core.solution import Solution
from ..base import Solver
from .options import HMILQROptions
from .solver import solve_hm_ilqr, start_states


class HMILQR(Solver):
    """Method ``"hm-ilqr"``: :func:`~torchtraj.solvers.hm_ilqr.solver.solve_hm_ilqr`."""

    name = "hm-ilqr"
    options_class = HMILQROptions
    handles_constraints = True
    records = True
    takes_state_guess = True
    takes_duals = False
    compiles = True
    starts_from_shifted_states = True

    def solve(self, problem: Problem, batch: Batch, options: HMILQROptions) -> Solution:
        return solve_hm_ilqr(problem, batch, options, method=self.name)

    def start_states(self, problem: Problem, batch: Batch, options: HMILQROptions) -> Tensor:
        return start_states(problem, batch)

    def step_defaults(self) -> HMILQROptions:
        """A control step's options: :meth:`HMILQROptions.fast` without AL updates, the expansions replayed from
        their recorded graphs (``record``: a controller's steps repeat the same shapes)."""
        return HMILQROptions.fast(al_iterations=0, record=True)


__all__ = ["HMILQR", "HMILQROptions"]
