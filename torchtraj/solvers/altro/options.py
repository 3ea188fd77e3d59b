"""Options of ALTRO (methods ``"altro"`` and ``"al-ilqr"``); defaults are Altro.jl's ``SolverOptions`` but for the
stopping tolerances, which reach the optimum (:meth:`ALTROOptions.fast` has Altro.jl's)."""

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
    """Options of :func:`solve_altro`; defaults are Altro.jl's ``SolverOptions`` except the stopping tolerances.

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
    #: Outer (dual update) iterations and iLQR iterations per outer iteration.
    iterations_outer: int = 30
    iterations_inner: int = 300
    #: Square-root backward pass (§III-A) instead of the standard one.
    square_root: bool = False
    #: Run the projection stage (``False`` gives plain AL-iLQR, method ``"al-ilqr"``).
    projection: bool = True
    projection_options: ProjectionOptions = field(default_factory=ProjectionOptions)
    #: Cost ``½ R_s |s|²`` on the slack controls of an infeasible start (§III-B, eq. 32).
    slack_cost: float = 1.0
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
        constraints 1e-6 with or without the projection): fewer iterations, a point short of the optimum that
        ``tt.solve`` reports ``STALLED`` unless it is a KKT point. ``changes`` replace fields (``ilqr`` among
        them)."""
        fields = {"cost_tolerance": 1e-4, "cost_tolerance_intermediate": 1e-4,
                  "constraint_tolerance": PROJECTED_TOLERANCE, "ilqr": ILQROptions.fast(), **changes}
        return cls(**fields)
