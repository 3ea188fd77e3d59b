"""Options of the interior-point method (method ``"ipm"``); defaults are IPOPT's (FATROP uses the same)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ...riccati.range_space import check_terminal_rows


@dataclass
class IPOptions:
    """Options of :func:`solve_interior_point`; defaults are IPOPT's (FATROP uses the same)."""

    #: Converged when the unscaled-barrier error ``E_0`` is below this (``tol``); ``None``: 1e-8 in float64,
    #: 1e-6 in float32 (the test is absolute: at 1e-5 the pendulum, whose multipliers are below 5e-4, stops
    #: 1.6e-3 above its optimum in float32 and float64 alike; at 1e-6, 1.4e-4).
    tolerance: Optional[float] = None
    #: Maximum iterations (steps taken or attempted; ``max_iter``).
    iterations: int = 1000
    #: Where the iterations run out, expand the last iterate and test it for convergence. ``False``: its objective
    #: and violation alone are evaluated (no derivatives), and an instance still running reports
    #: ``MAX_ITERATIONS`` even where that iterate would pass the test (``NON_FINITE`` and ``DIVERGED`` are still
    #: told): a control step's real-time iteration, which applies its plan whatever the status, saves an expansion.
    test_last_iterate: bool = True
    #: A control step's adaptive budget (with ``test_last_iterate`` off): from its ``stop_feasible_after``-th
    #: iteration on, an instance whose iterate violates its constraints (the largest violation: defects, equality
    #: rows, inequality rows' excess, as :attr:`~torchtraj.Solution.max_violation`) by at most
    #: ``stop_feasible_violation`` stops there, its values alone evaluated, and reports ``MAX_ITERATIONS``; the
    #: others go on, up to ``iterations``. ``0``: off. The violation's default is IPOPT's
    #: ``acceptable_constr_viol_tol``: its level of a point acceptable to stop at. :meth:`IPM.step_defaults` stops
    #: after one iteration, so that a controller's step whose plan is feasible costs one iteration and one whose plan
    #: is not takes more (``docs/benchmarks.md``, MPC).
    stop_feasible_after: int = 0
    stop_feasible_violation: float = 1e-2
    #: Initial barrier parameter ``μ_0`` (``mu_init``).
    barrier_initial: float = 0.1
    #: ``κ_μ`` and ``θ_μ`` of the barrier update (``mu_linear_decrease_factor``, ``mu_superlinear_decrease_power``).
    barrier_decrease: float = 0.2
    barrier_power: float = 1.5
    #: The barrier problem is solved when ``E_μ ≤ κ_ε μ`` (``barrier_tol_factor``).
    barrier_tolerance_factor: float = 10.0
    #: ``τ_min`` of the fraction-to-boundary rule (``tau_min``).
    fraction_to_boundary: float = 0.99
    #: ``s_max`` of the error scaling (IPOPT eq. 5).
    scaling_threshold: float = 100.0
    #: Slack push from zero ``κ_1`` (``bound_push``) and initial inequality multipliers (``bound_mult_init_val``).
    bound_push: float = 1e-2
    dual_initial: float = 1.0
    #: ``κ_Σ``: the multipliers stay within ``[μ/(κ_Σ s), κ_Σ μ/s]`` (``kappa_sigma``).
    dual_safeguard: float = 1e10
    #: Filter margins ``γ_θ``, ``γ_φ``, Armijo ``η_φ``, switching ``δ, s_θ, s_φ``, limits ``θ_max``, ``θ_min`` as
    #: factors of ``max(1, θ_0)``.
    filter_theta: float = 1e-5
    filter_phi: float = 1e-8
    armijo: float = 1e-8
    switching: float = 1.0
    switching_theta_power: float = 1.1
    switching_phi_power: float = 2.3
    theta_max_factor: float = 1e4
    theta_min_factor: float = 1e-4
    #: Entries kept per instance in the filter.
    filter_size: int = 64
    #: Backtracking factor, the number of step sizes tried and how many are evaluated together per round.
    line_search_decrease: float = 0.5
    line_search_steps: int = 20
    line_search_parallel: int = 4
    #: How many the first round evaluates: ``None`` decides once a solve, the full step alone in a compiled solve
    #: (``compile``) on a CPU of at least ``line_search.FULL_STEP_ALONE_FROM`` instances, whose trial points'
    #: evaluation is computation (the full step is usually taken, and the other candidates would be evaluated for
    #: every instance for the few that need them), else ``line_search_parallel`` (eager, or in a small batch, a
    #: further round costs about as much as a round of more candidates). The answer is the same either way: the same
    #: candidates, tried in the same order.
    line_search_first: Optional[int] = None
    #: Inertia correction ``δ_w``: first value, bounds and factors (``first_hessian_perturbation``,
    #: ``min/max_hessian_perturbation``, ``perturb_inc_fact_first``, ``perturb_inc_fact``, ``perturb_dec_fact``).
    regularization_first: float = 1e-4
    regularization_min: float = 1e-20
    regularization_max: float = 1e40
    regularization_increase_first: float = 100.0
    regularization_increase: float = 8.0
    regularization_decrease: float = 1.0 / 3.0
    #: Factorisation attempts per iteration before the instance gives up.
    regularization_attempts: int = 40
    #: Divergence limit on ``|x|`` (``diverging_iterates_tol``: 1e20 in IPOPT; ``max_state`` of the other methods).
    max_state: float = 1e8
    #: ``torch.compile`` the per-iteration kernels (:mod:`torchtraj.core.compiled`).
    compile: bool = False
    #: Replay the expansion and the line search's values from operator graphs recorded once per batch size
    #: (:mod:`torchtraj.core.recorded`): the same numbers with fewer, cheaper calls, after a trace of a fraction of a
    #: second per shape. ``None`` (default): a shape is recorded once it has been evaluated about as often as its
    #: trace costs (a long solve, repeated solves); ``True``: early (a controller's steps); ``False``: never.
    record: Optional[bool] = None
    #: On a GPU, replay the per-iteration kernels, the crossover's candidates and the implicit layer's Newton step
    #: and adjoint solve from CUDA graphs (:mod:`torchtraj.core.graphs`); no effect on a CPU or with ``compile``.
    cuda_graphs: bool = False
    #: Once the running instances are at most this share of the batch being iterated, the next iterations run
    #: on them alone (:mod:`torchtraj.solvers.ipm.compaction`); ``0`` never. Off with CUDA graphs, whose kernels
    #: are specialised to the batch size; with ``compile``, down to two instances (the kernels' batch dimension is
    #: dynamic from two on).
    compact_below: float = 0.75
    #: ``"monotone"``: the Fiacco-McCormick update with the filter line search (IPOPT's and FATROP's default).
    #: ``"mehrotra"``: Mehrotra's predictor-corrector (IPOPT's ``mehrotra_algorithm``: the probing barrier parameter,
    #: the affine corrector, no line search, the steps to the boundary taken whole). For convex problems (linear
    #: dynamics and constraints, convex costs), where it takes fewer iterations; without a globalisation, it may
    #: fail on others. Not with ``compile`` or ``cuda_graphs``.
    barrier_strategy: str = "monotone"
    #: Of a linear-quadratic problem (``Problem.linear_quadratic``) with inequality rows: once an instance's KKT
    #: error ``E_0`` is below ``crossover_from``, try at every iteration the exact solve with its proposed active set
    #: held (:mod:`torchtraj.solvers.ipm.crossover`); where the result passes the convergence test the instance ends
    #: there, at its KKT point to round-off.
    crossover: bool = True
    crossover_from: float = 1e-3
    #: Active sets tried per crossover: the proposed one, then the primal-dual active-set updates of its result.
    #: Each round solves one Newton system and counts as an iteration.
    crossover_rounds: int = 2
    #: Where every inequality row is a control bound: active sets tried before the first iteration, from none held
    #: (the unconstrained optimum) — the primal-dual active-set method; the instances it settles never iterate.
    #: ``0`` skips it.
    crossover_start_rounds: int = 8
    #: ``σ_max`` of the probing update (``sigma_max``), and the factor of the initial average complementarity that
    #: bounds its ``μ`` (``mu_max_fact``).
    mehrotra_sigma_max: float = 100.0
    mehrotra_mu_max_factor: float = 1e3
    #: Start the costates and the equality and inequality-row multipliers at their least-squares estimate
    #: (W&B 2006 §3.6, :mod:`~torchtraj.solvers.ipm.initialization`), kept where its largest entry is at most
    #: ``multiplier_init_max`` (``constr_mult_init_max``), else zero.
    least_squares_multipliers: bool = True
    multiplier_init_max: float = 1000.0
    #: A start from given multipliers (``tt.solve``'s ``duals``, :mod:`~torchtraj.solvers.ipm.warm_start`): the
    #: inequality multipliers at least ``warm_start_mult_bound_push`` (IPOPT's), and the given barrier at least
    #: ``warm_start_barrier_min`` (at most ``barrier_initial``).
    warm_start_mult_bound_push: float = 1e-3
    warm_start_barrier_min: float = 1e-3
    #: Second-order corrections of a rejected full step (W&B 2006 §2.3, :mod:`~torchtraj.solvers.ipm.soc`): at most
    #: this many (``max_soc``; 0: none), stopped when ``θ`` does not fall by ``soc_decrease`` (``kappa_soc``).
    second_order_corrections: int = 4
    soc_decrease: float = 0.99
    #: Feasibility restoration (Wächter & Biegler 2006 §3.3, :mod:`~torchtraj.solvers.ipm.restoration`): where the
    #: filter line search finds no step, minimise the ℓ1 infeasibility from there, ``ρ Σ (p + n) + ζ/2 ‖D_R (w −
    #: w_R)‖²`` (``resto_penalty_parameter`` ρ; ``ζ = restoration_proximity √μ_R``, ``resto_proximity_weight``), and
    #: return once the point is acceptable to the filter and ``θ ≤ κ_resto θ_R`` (``required_infeasibility_reduction``).
    #: Off, or with ``barrier_strategy="mehrotra"`` (no filter): such an instance retries with a larger ``δ_w`` until
    #: ``regularization_max``. ``ρ`` is 10, not IPOPT's
    #: 1000: a violated relaxed row's multiplier goes to ``ρ``, and on the circles of ``car_3obs`` (``∇²g = −2I``)
    #: that is a curvature of ``−2ρ`` that the inertia correction has to cover; with 1000 the restoration phase
    #: there creeps (steps of 1e-3) and ends ``MAX_REGULARIZATION`` (measured without the second-order corrections
    #: and the least-squares start); with 10 the solve converges in 143 iterations.
    restoration: bool = True
    restoration_penalty: float = 10.0
    restoration_proximity: float = 1.0
    restoration_reduction: float = 0.9
    #: After a restoration phase, inequality multipliers above this are reset to 1 (``bound_mult_reset_threshold``);
    #: the costates and equality multipliers restart at zero (``constr_mult_reset_threshold`` = 0).
    restoration_multiplier_reset: float = 1000.0
    #: The watchdog (W&B 2006 §3.2, :mod:`~torchtraj.solvers.ipm.watchdog`): started after this many successive
    #: iterations whose first trial point the line search rejected (``watchdog_shortened_iter_trigger``; 0: never),
    #: it takes up to ``watchdog_trials`` full steps without a line search (``watchdog_trial_iter_max``).
    watchdog_trigger: int = 10
    watchdog_trials: int = 3
    #: The filter reset heuristic (:mod:`~torchtraj.solvers.ipm.watchdog`): the filter is emptied after this many
    #: successive iterations whose last rejected trial point the filter alone refused (``filter_reset_trigger``),
    #: at most ``filter_resets`` times per instance (``max_filter_resets``; 0: never).
    filter_reset_trigger: int = 5
    filter_resets: int = 5
    #: Very small search directions (W&B 2006 §3.9, :mod:`~torchtraj.solvers.ipm.barrier`): after two successive
    #: primal steps at round-off with a multiplier step below this (``tiny_step_y_tol``), ``μ`` is decreased, or,
    #: at its floor, the instance stops ``STALLED``.
    tiny_step_dual: float = 1e-2  # 0: never
    #: Automatic scaling of the objective (W&B 2006 §3.8, :mod:`~torchtraj.solvers.ipm.scaling`):
    #: ``"gradient-based"`` solves ``min s_f J`` with ``s_f = min(1, g_max / ‖∇J(w_0)‖_∞)`` per instance
    #: (``nlp_scaling_method``), at least ``scaling_min_value`` (``nlp_scaling_min_value``), ``g_max`` =
    #: ``scaling_max_gradient`` (``nlp_scaling_max_gradient``); ``"none"``: the problem as given.
    scaling: str = "gradient-based"
    scaling_max_gradient: float = 100.0
    scaling_min_value: float = 1e-8
    #: Log one line per iteration through the ``torchtraj`` logger.
    verbose: bool = False
    #: The Riccati sweep of the Newton steps (:func:`~torchtraj.riccati.factorize`): ``"sequential"``,
    #: ``"parallel"`` (the associative-scan sweep, O(log N) deep; for problems without stage equality rows, whose
    #: back-propagation is sequential, and terminal rows with ``terminal_rows="range-space"``) or ``"auto"`` (parallel
    #: where it applies and pays for the batch, by :func:`~torchtraj.riccati.sweep_for_batch`, decided once a solve).
    #: Both take the sequential sweep's inertia test: an instance whose stage control Hessian the parallel sweep
    #: refuses is factorised by the sequential one (:func:`~torchtraj.riccati.factorize`). On well-conditioned
    #: systems they solve the same Newton system to round-off, but the associative scan is not backward stable where
    #: the barrier's ``Σ`` makes the system ill conditioned: with some stages' ``Q`` and ``R`` scaled by 1e10 (as
    #: bounds active at a small ``μ`` do) its value function is 1e-5 from the sequential sweep's and its steps meet
    #: the stationarity rows to a residual as large as their terms (relative 1.0; the sequential sweep's 2e-6). Paths
    #: that run through such systems then differ (the Mehrotra run of ``tests/test_interior_point.py`` with an
    #: unreachable goal: 1000 iterations instead of ending ``MAX_REGULARIZATION`` after 255), hence the default.
    sweep: str = "sequential"
    #: How the Newton steps hold terminal equality rows (:func:`~torchtraj.riccati.factorize`):
    #: ``"range-space"``, the unconstrained ``sweep`` and the rows' Schur complement
    #: (:mod:`~torchtraj.riccati.range_space`: a few calls a stage, and the parallel sweep applies), where the
    #: problem has no stage equality rows; ``"back-propagation"``, the constraint back-propagation (two SVDs a
    #: stage) always. Both solve the same Newton system; the range-space method asks the inertia test for a
    #: positive definite ``Q_uu`` at every stage, where the back-propagation asks it on the controls the rows leave
    #: free, so its ``δ_w`` can differ on a nonconvex problem.
    terminal_rows: str = "range-space"

    def __post_init__(self):
        if self.sweep not in ("sequential", "parallel", "auto"):
            raise ValueError(f"sweep must be 'sequential', 'parallel' or 'auto', not {self.sweep!r}")
        check_terminal_rows(self.terminal_rows)
        if self.scaling not in ("gradient-based", "none"):
            raise ValueError(f"scaling must be 'gradient-based' or 'none', not {self.scaling!r}")
        if self.barrier_strategy not in ("monotone", "mehrotra"):
            raise ValueError(f"barrier_strategy must be 'monotone' or 'mehrotra', not {self.barrier_strategy!r}")
        if self.line_search_first is not None and self.line_search_first < 1:
            raise ValueError(f"line_search_first must be None or >= 1, got {self.line_search_first}")
        if self.crossover_rounds < 0 or self.crossover_start_rounds < 0:
            raise ValueError(f"crossover_rounds and crossover_start_rounds must be >= 0, got {self.crossover_rounds} "
                             f"and {self.crossover_start_rounds}")
        if self.stop_feasible_after < 0 or not self.stop_feasible_violation > 0:
            raise ValueError(f"stop_feasible_after must be >= 0 and stop_feasible_violation > 0, got "
                             f"{self.stop_feasible_after} and {self.stop_feasible_violation}")
        if self.stop_feasible_after > 0 and self.test_last_iterate:
            raise ValueError("stop_feasible_after stops an instance on its iterate's values alone, untested: it goes "
                             "with test_last_iterate=False (a control step's options, IPM.step_defaults)")
        if self.barrier_strategy == "mehrotra" and (self.compile or self.cuda_graphs):
            raise ValueError("barrier_strategy='mehrotra' runs eager: set compile=False and cuda_graphs=False")

    def tolerance_for(self, dtype: torch.dtype) -> float:
        if self.tolerance is not None:
            return self.tolerance
        return 1e-8 if dtype == torch.float64 else 1e-6
