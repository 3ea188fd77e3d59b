"""Options of ALTRO (methods ``"altro"`` and ``"al-ilqr"``); defaults are Altro.jl's ``SolverOptions`` but for the
stopping tolerances, which reach the optimum (:meth:`ALTROOptions.fast` has Altro.jl's), and the infeasible start's
slack cost (``slack_cost``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from ...iterations.ilqr import ILQROptions
from .projection import ProjectionOptions

#: The AL stage's default ``constraint_tolerance`` where the projection follows (Altro.jl's ``constraint_tolerance``
#: is 1e-6 too).
PROJECTED_TOLERANCE = 1e-6


@dataclass
class ALTROOptions:
    """Options of :func:`solve_altro`; defaults are Altro.jl's ``SolverOptions`` except the stopping tolerances and
    the slack cost of an infeasible start (``slack_cost``, the field's comment).

    Altro.jl's (``cost_tolerance = cost_tolerance_intermediate = 1e-4``, the inner ``gradient_tolerance = 10``;
    :meth:`fast`) stop the pendulum 31 % above its optimum, the cart-pole 0.1 %. The defaults here (1e-12, 1e-6
    and the inner iLQR's own, :class:`ILQROptions`) stop where the KKT certificate of :func:`torchtraj.solve`
    (stationarity 1e-6) holds, at 1.3 to 2 times the iterations of a cost change of 1e-8 and a scaled step of
    1e-3 (which stop the pendulum at stationarity 6e-6)."""

    #: Options of the inner iLQR (its ``iterations`` is unused: see ``iterations_inner``; its ``cost_tolerance``
    #: neither: the two below replace it).
    ilqr: ILQROptions = field(default_factory=ILQROptions)
    #: The AL stage stops once the largest violation, and the complementarity ``|λ c|`` of the multiplier estimate,
    #: are below this (``constraint_tolerance``), or below ten rounding errors of the trajectory where that is larger
    #: (:func:`~torchtraj.solvers.altro.augmented_lagrangian.resolution_floor`). ``None``: 1e-6 where the projection
    #: follows (it takes the violations to its own tolerance), the projection's tolerance (1e-8; in float32 the
    #: resolution floor, 1.2e-6 of the trajectory's magnitude) where none does (AL-iLQR, whose AL stage's point is
    #: the answer): :meth:`stage_tolerance`.
    constraint_tolerance: Optional[float] = None
    #: Inner convergence on the cost change while the constraints are not met (``cost_tolerance_intermediate``;
    #: Altro.jl: 1e-4),
    cost_tolerance_intermediate: float = 1e-6
    #: ... and once they are (``cost_tolerance``; Altro.jl: 1e-4).
    cost_tolerance: float = 1e-12
    #: Initial penalty ``μ`` (``penalty_initial``), its scaling ``φ`` (``penalty_scaling``) and cap (in float32 the
    #: cap is 840: :func:`~torchtraj.solvers.altro.augmented_lagrangian.penalty_limit`).
    penalty_initial: float = 1.0
    penalty_scaling: float = 10.0
    penalty_max: float = 1e8
    #: Multipliers are clipped to ``±dual_max``.
    dual_max: float = 1e8
    #: The AL stage stops only where the inequality rows ``L_A`` holds (eq. 7's ``I_μ``) pull with nonnegative
    #: multipliers ``λ + μ c`` (:meth:`~torchtraj.solvers.altro.augmented_lagrangian.AugmentedLagrangian.sign_mismatch`
    #: within the constraint tolerance), else it updates the duals and goes on: eq. (17)'s estimate clamps such a
    #: multiplier to zero, so the point is stationary for ``L_A`` but not a KKT point (parallel_park's sample starts
    #: 26, 35 and 40: rows at ``c ≈ −1e-9`` with ``λ = 4e-3`` and ``μ = 1e7``, stationarity 1e-4). Not in the paper:
    #: :meth:`fast` (and so a control step) leaves it out, as Altro.jl does.
    multiplier_signs: bool = True
    #: AL-iLQR (no projection): where eq. (17)'s multiplier estimate misses the certificate's stationarity, take the
    #: held rows' least-squares multipliers if they do better (at ``μ = 1e7`` the estimate carries the inner solve's
    #: error times the penalty: stationarity 5e-6 to 1.1e-5 on parallel_park's sample starts 26, 35 and 40, 1e-9
    #: with the least-squares ones). Not in the paper: :meth:`fast` (and so a control step, where the check would
    #: evaluate the certificate at every step) leaves it out.
    multiplier_refinement: bool = True
    #: AL-iLQR (``projection=False``) only: where its AL stage would finish (inner solve converged, rows met) at a
    #: stationarity residual above the KKT certificate's (1e-6; float32 its own), the inner iLQR goes on while its
    #: steps at least halve that residual, within ``iterations_inner``. Its answer is the AL stage's point, and the
    #: inner test (cost change, scaled step) stopped quadrotor2d's sample starts 6 and 29 at 3.7e-6 and 3.5e-6
    #: with the residual falling fivefold an iteration at ``μ = 1e8`` (``STALLED``). Not in the paper; off in
    #: :meth:`fast`.
    stationary_finish: bool = True
    #: Outer (dual update) iterations and iLQR iterations per outer iteration.
    iterations_outer: int = 30
    iterations_inner: int = 300
    #: Square-root backward pass (§III-A) instead of the standard one.
    square_root: bool = False
    #: Run the projection stage (``False`` gives plain AL-iLQR, method ``"al-ilqr"``).
    projection: bool = True
    projection_options: ProjectionOptions = field(default_factory=ProjectionOptions)
    #: Cost ``½ R_s |s|²`` on the slack controls of an infeasible start (§III-B, eq. 32); it acts on nothing else. 0.1,
    #: the ALTRO sources' value for their escape benchmark, where Altro.jl's default ``R_inf`` is 1. Measured on
    #: ``car_escape`` from its waypoint guess (the only problem of the set that starts infeasibly by default): the
    #: walls' rows are inactive there (every knot 0.14 or more outside a circle, ``λ = 0``: eq. 3 leaves them out of
    #: the first LQR model), the model's step only removes slack, and the line search on ``L_A`` (walls at ``μ = 1``)
    #: takes ``α = 1`` of it with ``R_s = 1`` (``α = 0.5`` at 0.15 to 0.3): the route cuts through a wall (rows at
    #: 0.25), the first inner solve ends there (slacks 0.22, walls 0.21, cost 0.047 against the optimum's 0.33) and
    #: from ``μ = 100`` on the AL stage stalls (slacks 0.36 to 0.37, walls 0.18, up to ``μ = 1e8``), until iLQR's
    #: regularisation passes its cap (``MAX_REGULARIZATION``, 2519 iterations; 0.3 stalls at the same point, followed
    #: to ``μ = 1e5``). From 0.001 to 0.12 the first step is cut to 1/16 (walls at 0.088); with 0.1 and 0.03 the
    #: slacks then fall about tenfold per dual update to a local optimum that IPOPT keeps (0.3316056; 234 and 240
    #: iterations). The margin is narrow (0.12 to 0.15): a line-search outcome, not a property of the problem.
    slack_cost: float = 0.1
    #: Without an ``X0``, start from the problem's own state guess (``Problem.X_init``) where it carries one, by the
    #: infeasible start (§III-B), as from an ``X0``; ``False``: from the rollout of ``U0`` (module docstring of
    #: :mod:`torchtraj.solvers.altro.solver`). A control step never does (:meth:`ALTRO.step_options`).
    problem_state_guess: bool = True
    #: Log one line per iteration through the ``torchtraj`` logger.
    verbose: bool = False

    def stage_tolerance(self) -> float:
        """The AL stage's ``constraint_tolerance``, its default resolved (the field's comment)."""
        if self.constraint_tolerance is not None:
            return self.constraint_tolerance
        return PROJECTED_TOLERANCE if self.projection else self.projection_options.tolerance

    @classmethod
    def fast(cls, **changes) -> "ALTROOptions":
        """Altro.jl's own stopping tolerances (cost change 1e-4 inside and out, the inner scaled step 10, the
        constraints 1e-6 with or without the projection, no test of the held rows' multiplier signs, no refinement
        of AL-iLQR's estimate and no stationarity test at its finish): fewer
        iterations, a point short of the optimum that ``tt.solve`` reports ``STALLED`` unless it is a KKT point.
        ``changes`` replace fields (``ilqr`` among them)."""
        fields = {"cost_tolerance": 1e-4, "cost_tolerance_intermediate": 1e-4,
                  "constraint_tolerance": PROJECTED_TOLERANCE, "ilqr": ILQROptions.fast(), "multiplier_signs": False,
                  "multiplier_refinement": False, "stationary_finish": False, **changes}
        return cls(**fields)
