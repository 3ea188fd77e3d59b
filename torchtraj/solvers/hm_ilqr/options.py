r"""Options of HM-iLQR (method ``"hm-ilqr"``; Tang, Chu, Jin & Au, "Inequality Constrained Trajectory Optimization
with A Hybrid Multiple-shooting iLQR").

The paper fixes the exit criteria (§IV-C): ``ε_v = 1e-3`` on the objective reduction, ``c_min^rlb = 1e-7`` on the
constraint violation and ``MaxIter = 100`` (:meth:`HMILQROptions.fast`); the defaults ask ``c_min^rlb = 1e-8``, the
violation every constrained method of the library meets. Its ``ε_v`` ends the double integrator
at a point whose stationarity is 9e-3, no KKT point. No reduction of the objective tells a KKT point either: near
the end the active rows' curvature ``ψ / z²`` (``1e8`` at ``ψ = 1e-8``) makes the last Newton steps change the
objective by ``|r|² z² / ψ`` for a stationarity residual ``r``, below the rounding of the objective in float64 with
``r = 4e-6`` (16 of 32 double integrators stopped there by ``ε_v = 1e-12``). So the defaults stop on the KKT
residual itself, within 1000 iterations: ``ε_v = 0`` (off) and an RLB instance at ``ψ_min`` and ``c_min^rlb`` has
converged where the stationarity residual with the multipliers ``z⁺`` (:mod:`~torchtraj.solvers.hm_ilqr.
multipliers`) is below ``stationarity_tolerance``.

**Resolution of the dtype** (:meth:`HMILQROptions.tolerances`). Tolerances below what the dtype resolves are met
at its resolution: ``c_min^rlb`` at ``100 ε`` (the defects of a float32 rollout are about ``1e-7``), ``ψ_min`` and
``δ_min`` at ``ε``. An active row's slack is ``z = ψ / λ``; below ``ψ = ε`` it falls under the resolution ``ε |g|``
of a row of unit scale, and the barrier's point and its multipliers are rounding noise (float32, ``ψ_min = 1e-8``:
one of the 32 double integrators of ``tests/test_hm_ilqr.py`` stalls; at ``ε`` all 32 are KKT points, with costs
within 3e-7 of float64's). A larger ``ψ_min`` moves the cost off the optimum by about ``ψ`` per active row
(``ε^{3/4}``: 2.2e-5 relative on the pendulum). It leaves the other constants open; the defaults below were chosen
on the problem set (``tests/test_hm_ilqr.py`` and ``docs/benchmarks.md``), see each field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ...riccati.range_space import check_terminal_rows


@dataclass
class HMILQROptions:
    """Options of :func:`~torchtraj.solvers.hm_ilqr.solver.solve_hm_ilqr` (module docstring)."""

    #: ``MaxIter``: iterations of both stages together (paper §IV-C: 100). The Gauss-Newton model of iLQR converges
    #: linearly on the cart-pole (its dynamics' curvature is what the model leaves out): from the line between x0
    #: and the goal ``cartpole_unconstrained`` converges after 811 iterations (measured; ALTRO and AL-iLQR take 825
    #: from the rollout of the control guess), hence 1000.
    iterations: int = 1000
    #: ``ε_v``: an RLB iteration ends the solve once it changes the objective by less than this and the other exit
    #: tests hold (paper §IV-C: 1e-3; 0: off, the solve ends on the KKT residual, module docstring).
    cost_tolerance: float = 0.0
    #: ``c_min^rlb``: the largest constraint violation and defect of a converged solve; at least ``100 ε`` of the
    #: dtype. The paper's 1e-7 (§IV-C, :meth:`fast`) left defects and violations of 2e-8 to 6e-8 on four problems
    #: of the set (the pendulum, the park, car_escape, the pendulum without bounds), above the 1e-8 that every
    #: constrained method meets by default (the interior point's and AL-iLQR's tolerance).
    constraint_tolerance: float = 1e-8
    #: The largest stationarity residual of the objective's Lagrangian in the controls (``|∂L/∂u|∞`` with the
    #: costates of its stationarity in the states, as the KKT certificate measures it) at which an RLB instance at
    #: ``ψ_min`` has converged; ``None``: a tenth of the certificate's tolerance of the dtype (1e-7 in float64).
    stationarity_tolerance: Optional[float] = None
    #: ``c_min^al``: the AL stage hands over to the RLB stage below this violation (Algorithm 2).
    constraint_tolerance_al: float = 1e-2
    #: The AL stage hands over after this many iterations even above ``c_min^al`` (the relaxed barrier accepts
    #: an infeasible start); 0 starts in the RLB stage (a control step's default, whose warm start is near).
    al_iterations: int = 60
    #: The "if update" of Algorithm 2: the multipliers (15) and the penalty (16) move after an iteration that changed
    #: ``J_1`` by less than this, relative to ``1 + |J_1|`` (the inner M-iLQR nearly converged). ``inf`` updates after
    #: every iteration (one inner iteration per update): on the cart-pole the multipliers then run away (violation
    #: 8e2 after 34 iterations from the interpolated guess, measured).
    al_update_tolerance: float = 1e-3
    #: ``M``: shooting segments (``M = N``: full multiple shooting, ``M = 1``: single shooting). Capped at N.
    segments: int = 10
    #: ``μ_0``: initial AL penalty: ``ψ_0 / δ_0²``, the curvature of the relaxed barrier's quadratic extension at
    #: the start of the RLB stage, so that the AL stage starts as stiff as the barrier would. Measured on car_escape
    #: from its waypoint guess: with ``μ_0 = 1`` the first five AL iterations cut the path through a wall of circles
    #: (cost 0.13, below the optimum's 0.33, violation 0.24), and neither stage gets it out again (violation 0.250
    #: after 300 iterations; 0.249 with ``μ_0 = 10``); with 100 it converges to IPOPT's optimum (162 iterations).
    #: With 100 every problem of the set converges from its own guess (docs/benchmarks.md, "Default options"; the
    #: cart-pole at a local optimum IPOPT keeps, 1.789, where ``μ_0 = 1`` crawled toward IPOPT's 1.486); its price:
    #: from a guess far outside the bounds (the paper's coarse cart-pole guess, controls 3 beyond them) the AL stage
    #: stalls and the solve takes 486 iterations instead of 84 (N = 50), or ends ``MAX_REGULARIZATION`` from a guess
    #: that differs by 2e-10: pass ``penalty_initial=1`` from a start far outside the bounds.
    penalty_initial: float = 100.0
    #: ``φ``: the penalty scaling of eq. (16), applied after every iteration (one inner iteration per update).
    penalty_scaling: float = 10.0
    #: The "if update" of Algorithm 2 for the penalty: eq. (16) is applied after an iteration whose violation of the
    #: penalised rows is above this fraction of the previous one's (the multipliers are updated every iteration).
    penalty_trigger: float = 0.5
    #: Largest AL penalty (the AL stage's ill-conditioning is what the RLB stage avoids).
    penalty_max: float = 1e3
    #: Multipliers are clipped to ``±dual_max``.
    dual_max: float = 1e8
    #: ``ψ_0``: barrier weight at the start of the RLB stage.
    barrier_initial: float = 1e-2
    #: ``ω_1``: barrier decrease of eq. (18a).
    barrier_decrease: float = 0.2
    #: ``κ``: the "if update" of Algorithm 3: ψ and δ move after an accepted step whose predicted decrease of the
    #: merit was below ``κ ψ`` (the barrier problem of that ψ nearly solved; IPOPT's rule in the iLQR model's terms).
    barrier_update: float = 1.0
    #: ``ψ_min``: the barrier weight stops decreasing here; a converged solve has reached it (the complementarity
    #: of its log-branch rows is ``ψ``). At least ``ε`` of the dtype (module docstring).
    barrier_min: float = 1e-8
    #: ``δ_0``: relaxation at the start of the RLB stage.
    relaxation_initial: float = 1e-2
    #: ``ω_2``: relaxation decrease of eq. (18b).
    relaxation_decrease: float = 0.1
    #: ``δ_min`` of eq. (18b); at least ``ε`` of the dtype.
    relaxation_min: float = 1e-12
    #: ``μ_V^0``: state-value regularisation at the start of each CRLS iteration (eq. 21).
    regularization_initial: float = 1e-6
    #: ``σ``: CRLS's regularisation increase, eq. (22).
    regularization_increase: float = 10.0
    #: ``μ_V^max``.
    regularization_max: float = 1e8
    #: Use CRLS (Algorithm 5) in the RLB stage; ``False``: a failed line search ends the iteration (plain LS).
    crls: bool = True
    #: Plain LS of the RLB stage (``crls=False``) as the paper's pure LS (§III-C-3, Fig. 5): a failed line search
    #: ends the solve (``STALLED``). ``False``: it raises ``μ_V`` for the next iteration (Tassa's schedule).
    failed_search_stops: bool = False
    #: ``γ``: line-search step decrease, eq. (20).
    line_search_decrease: float = 0.5
    #: Step sizes tried, ``α ∈ {1, γ, …, γ^(steps−1)}`` (``α_min`` is the last).
    line_search_steps: int = 12
    #: Accepted interval of the ratio of actual to expected change (§III-C-1).
    line_search_lower: float = 1e-4
    line_search_upper: float = 10.0
    #: The RLB stage's model adds the dynamics' curvature ``Σ λ_{k+1,i} ∇²f_i`` where it stays convex (an extension
    #: beyond the paper, :mod:`~torchtraj.solvers.hm_ilqr.objective`, "Dynamics curvature"): Newton's model of the
    #: barrier problem instead of Gauss-Newton's. Measured on ``sample_x0("cartpole_unconstrained", 64, 0)``: of the
    #: six of the first 16 starts that ended ``MAX_ITERATIONS`` or ``STALLED`` without it, all converge (68 to 915
    #: iterations, stationarity at most 1e-10). ``False``: the paper's Gauss-Newton model.
    dynamics_curvature: bool = True
    #: With ``dynamics_curvature``: the shortest step of the curvature's model that the line search accepts; below it
    #: CRLS raises ``μ_V`` instead (:mod:`~torchtraj.solvers.hm_ilqr.crls`, "Newton steps"). Measured on
    #: ``cartpole_unconstrained`` start 8: without it the search took ``α = 2e-3`` from iteration 130 on and the
    #: solve ended ``MAX_ITERATIONS``; with 0.1 it converges after 915 iterations.
    curvature_step_min: float = 0.1
    #: With ``dynamics_curvature``: where the backward pass at ``μ_V^0`` fails with the curvature (the model is not
    #: convex), the stage Hessians are shifted by ``δ I``, the smallest ``δ = s δ*`` for ``s`` in these factors with
    #: which it succeeds, ``δ*`` the most negative eigenvalue of the curvature blocks in magnitude (the inertia
    #: correction of Wächter & Biegler 2006, §3.1, on a short ladder), instead of dropping to the Gauss-Newton model,
    #: which stays the fallback where none succeeds. ``()``: no shift. Measured on ``sample_x0("cartpole", 64, 0)``
    #: start 36: the curvature failed in 478 of 935 RLB iterations and the Gauss-Newton steps there took ``α`` of
    #: 2e-3 to 8e-3 (``MAX_ITERATIONS``); with the shifts starts 18, 19, 36 converge (338, 293, 255 iterations).
    #: Small factors only: a shift near ``δ*`` damps every direction like a large ``μ_V``, and
    #: ``cartpole_unconstrained`` start 19 then took full steps of a model shifted by about 47 for 1000 iterations
    #: (stationarity 2.4; up to ``s = 0.1`` the same), where with ``s ≤ 1e-2`` it converges (386 iterations).
    curvature_shifts: tuple = (1e-3, 1e-2)
    #: A second-order correction of a refused full step (an extension beyond the paper, Wächter & Biegler 2006 §2.4;
    #: :mod:`~torchtraj.solvers.hm_ilqr.crls`, "Second-order correction"): against the Maratos effect of the
    #: defects' merit term. ``False``: the paper's line search.
    second_order_correction: bool = True
    #: ``w``: weight of the defect term ``w Σ dᵀd`` of the expected change (§III-C-1); raised per iteration where
    #: the model would otherwise predict no decrease (module :mod:`~torchtraj.solvers.hm_ilqr.shooting`).
    defect_weight: float = 1.0
    #: The raised defect weight never decreases within a stage (per instance; it restarts at ``w`` at the hand-over):
    #: recomputed from ``w`` at every iteration, the merit changes from one iteration to the next and the iterates
    #: can cycle between merits (Nocedal & Wright 2006 §18.3's reason for a monotone penalty parameter). Measured on
    #: the cart-pole, N = 100, M = 20: without it the RLB stage repeats steps of ``α = 0.5`` at violation 9e-3 until
    #: the iteration limit; with it the solve converges (253 iterations, IPOPT's cost to 4e-8). Only the weights of
    #: steps that CRLS took at ``μ_V^0`` raise the floor: a step of a larger ``μ_V`` barely moves but closes the
    #: defects, its model predicts the objective's price of closing them, ``λᵀd``, and the weight that outweighs it,
    #: about ``‖λ‖ / ‖d‖``, grows without bound as the defects close. Kept, it refused every later step that opened
    #: second-order defects: on ``sample_x0("cartpole", 64, 0)`` starts 18, 19, 36 it reached 3.1e8, 1.5e11 and
    #: 1.6e6 (costates of at most 6) and CRLS then took ``μ_V`` of 0.1 to 1 for hundreds of iterations.
    monotone_defect_weight: bool = True
    #: How the backward pass holds the terminal equality rows of the RLB stage (the goal; :func:`~torchtraj.riccati.
    #: factorize`): ``"range-space"``, the unconstrained sweep and the rows' Schur complement
    #: (:mod:`~torchtraj.riccati.range_space`, the interior point's and eILQR's default), where the problem has no
    #: stage equality rows; ``"back-propagation"``, the constraint back-propagation (Laurenzi et al. §II-B/C, two
    #: SVDs a stage) always. Both solve the same LQR problem and give the same constrained gains; they differ in
    #: round-off and in the inertia test: the range-space method asks for a positive definite ``Q_uu`` at every
    #: stage (with the rows' projector added to ``Q_N``), the back-propagation on the controls the rows leave free.
    terminal_rows: str = "range-space"
    #: Converged (no step needed) when the predicted decrease is below this.
    expected_decrease_tolerance: float = 1e-16
    #: Divergence limits on the objective and on |x|.
    max_cost: float = 1e8
    max_state: float = 1e8
    #: ``torch.compile`` the per-iteration kernels (:mod:`torchtraj.core.compiled`): the expansion, the dynamics'
    #: curvature, the backward pass, the solve of each right-hand side and the line search's batched rollouts (the
    #: loop, CRLS's rounds and the masks stay eager). The first solve of a problem compiles them (minutes on a CPU).
    compile: bool = False
    #: Replay the expansions (the model's and the dynamics' curvature) and the rollouts' steps from their operator
    #: graphs recorded once per batch size (:mod:`torchtraj.core.recorded`): the same numbers with fewer, cheaper
    #: calls, after a trace of a fraction of a second per shape. ``None`` (default): a shape is recorded once it has
    #: been evaluated about as often as its trace costs; ``True``: early (a controller's steps); ``False``: never.
    record: Optional[bool] = None
    #: Log one line per iteration through the ``torchtraj`` logger.
    verbose: bool = False

    def __post_init__(self):
        check_terminal_rows(self.terminal_rows)

    @classmethod
    def fast(cls, **changes) -> "HMILQROptions":
        """The paper's exit criteria (``ε_v = 1e-3``, ``c_min^rlb = 1e-7``, ``MaxIter = 100``) and its model (no
        dynamics curvature, no second-order correction, which cost an expansion, a factorisation and a rollout more
        an iteration): fewer, cheaper iterations (a control step's), a point short of the optimum that ``tt.solve``
        reports ``STALLED`` unless it is a KKT point."""
        return cls(**{"cost_tolerance": 1e-3, "constraint_tolerance": 1e-7, "iterations": 100,
                      "dynamics_curvature": False, "second_order_correction": False, **changes})

    def tolerances(self, dtype: torch.dtype) -> "Tolerances":
        """The exit tolerances and the barrier's floors in ``dtype`` (:class:`Tolerances`)."""
        eps = torch.finfo(dtype).eps
        stationarity = self.stationarity_tolerance
        if stationarity is None:
            stationarity = 0.5 * (1e-6 if dtype == torch.float64 else 1e-3)
        return Tolerances(constraint=max(self.constraint_tolerance, 100 * eps), stationarity=stationarity,
                          barrier=max(self.barrier_min, eps), relaxation=max(self.relaxation_min, eps))


@dataclass(frozen=True)
class Tolerances:
    """The tolerances of a solve in its dtype: ``c_min^rlb``, the stationarity residual, ``ψ_min`` and ``δ_min``
    (:meth:`HMILQROptions.tolerances`)."""

    constraint: float
    stationarity: float
    barrier: float
    relaxation: float
