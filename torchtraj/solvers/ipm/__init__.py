r"""The interior-point method (method ``"ipm"``) as a :class:`~torchtraj.solvers.base.Solver` object; the algorithm
is :mod:`torchtraj.solvers.ipm.solver`.

It handles the constraints and takes a state guess ``X0`` (multiple shooting starts from the defects
``f(x_k, u_k) − x_{k+1}``); without one it starts at the problem's own state guess ``Problem.X_init`` where there
is one (car_escape's waypoints, IPOPT's start too), else at the rollout of the controls. Its multipliers start
from the barrier's initial values (``bound_push``, ``dual_initial``) and their least-squares estimate, or from
``tt.solve``'s ``duals`` (``"multipliers"``, ``"costate"``, ``"barrier"``: :mod:`~torchtraj.solvers.ipm.warm_start`).
A control step with a budget of ``n`` iterations runs at most ``n`` interior-point iterations; it starts from the
previous step's controls and states, shifted by one knot, with the measured state at the first
(:attr:`~torchtraj.solvers.base.Solver.starts_from_shifted_states`): multiple shooting takes the defects of that
start (at the first stage where the plant moved otherwise than the model, at the last where the repeated control
leaves the repeated state) and needs no rollout; and from the previous step's multipliers and costates, shifted, and
its last barrier parameter (:meth:`IPM.carried_duals`). A cold instance starts as a solve without ``X0`` and
``duals`` does: at the problem's ``X_init`` with its own controls, else at the rollout of the controls, and with
the cold multipliers and barrier.
"""

from __future__ import annotations

from torch import Tensor

from ...core.batch import Batch
from ...core.constraints import Constraints
from ...core.problem import Problem
from ...core.solution import Solution
from ..base import Solver
from .options import IPOptions
from .solver import solve_interior_point, start_states


class IPM(Solver):
    """Method ``"ipm"``: :func:`~torchtraj.solvers.ipm.solver.solve_interior_point`."""

    name = "ipm"
    options_class = IPOptions
    handles_constraints = True
    records = True
    compiles = True
    takes_state_guess = True
    takes_duals = True
    dual_entries = ("multipliers", "costate", "barrier")
    starts_from_shifted_states = True

    def solve(self, problem: Problem, batch: Batch, options: IPOptions) -> Solution:
        return solve_interior_point(problem, batch, options, method=self.name)

    def start_states(self, problem: Problem, batch: Batch, options: IPOptions) -> Tensor:
        return start_states(problem, batch, options)

    def step_defaults(self) -> IPOptions:
        """A control step's options: the defaults with recorded kernels (``IPOptions.record``) on the whole batch
        (``compact_below=0``), so that a controller's steps repeat the same shapes, and with the multipliers started
        at zero instead of at their least-squares estimate (``least_squares_multipliers=False``, IPOPT's
        ``constr_mult_init_max = 0``): a step starts from the previous solution, shifted, whose first Newton step
        gives the multipliers, and the estimate would cost each step an expansion and a factorisation more (the
        controllers measured both ways: ``docs/benchmarks.md``, section MPC); and with the last iterate evaluated
        untested (``test_last_iterate=False``): the controller applies the plan whatever its status, so a step
        whose budget runs out reports ``MAX_ITERATIONS`` without the expansion that would test it; and with an
        adaptive budget (``stop_feasible_after=1``): a step whose plan is feasible after one iteration (to IPOPT's
        ``acceptable_constr_viol_tol``) ends there, and one whose plan is not takes more, up to the controller's
        ``iterations``."""
        return IPOptions(record=True, compact_below=0.0, least_squares_multipliers=False, test_last_iterate=False,
                         stop_feasible_after=1)

    def carried_duals(self, constraints: Constraints, solution: Solution, options: IPOptions) -> dict:
        """The multipliers and costates of ``solution``, and its last barrier parameter (the history's, in the
        problem's units); where no iteration was made (every instance converged at its start), the tolerance:
        the next step's start raises it to ``warm_start_barrier_min``. Always positive: a zero marks a cold
        instance (:mod:`~torchtraj.solvers.ipm.warm_start`)."""
        barrier = solution.history.extra.get("barrier")
        if barrier is None or barrier.shape[-1] == 0:
            last = solution.cost.new_full(solution.cost.shape, options.tolerance_for(solution.cost.dtype))
        else:
            last = barrier[:, -1]
        return {"multipliers": dict(solution.multipliers), "costate": solution.costate, "barrier": last}


__all__ = ["IPM"]
