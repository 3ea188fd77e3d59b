"""Options of eILQR (Laurenzi, Ruscelli & Tsagarakis, "A Constrained Iterative LQR Solver for the Trajectory
Optimization Framework Horizon"): the Newton-KKT step, its ℓ1-merit line search and regularisation, the soft
barrier of the inequalities and the initial-state optimisation.

The paper gives no numbers for its globalisation; those below are the textbook's it cites (Nocedal & Wright 2006
§3.1, §15.4, §18.3: Armijo constant 1e-4, halving the step) and IPOPT's inertia-correction schedule
(Wächter & Biegler 2006 §3.1: ``δ_w^0 = 1e-4``, ``κ_w^- = 1/3``, ``κ_w^+ = 8``, ``κ̄_w^+ = 100``).
``short_step``, the merit's margin and the barrier's weight are this implementation's choices, measured on the
problem set (their attributes say how).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import torch

from ...riccati.range_space import check_terminal_rows


@dataclass
class EILQROptions:
    """Options of :func:`~torchtraj.solvers.eilqr.solver.solve_eilqr`.

    Attributes:
        iterations: most Newton iterations (300: the pendulum's default solve takes 47; 152 with the monotone line
            search, 176 before the fraction to the boundary, most of them in its continuation's stage at
            ``w = 3.2e-5`` with steps cut to ``α ≈ 1/16``).
        tolerance: the KKT error at which an instance has converged, the largest of the Lagrangian's gradient,
            the dynamics defects, the equality rows and the initial-state rows (``∞``-norms, unscaled);
            ``None``: 1e-9 in float64, 1e-5 in float32.
        barrier_weight: ``w`` of the soft barrier ``w Σ β(−g)`` of every inequality row and bound
            (:mod:`~torchtraj.solvers.eilqr.barrier`) without ``barrier_continuation`` (the paper's fixed weight);
            with it, ``barrier_weight_initial`` is the first stage's. A fixed weight's solution costs more than the
            hard-constrained optimum by a gap about linear in ``w`` (the pendulum: +44 % at 1e-3, +6.2 % at 1e-4, +0.8 %
            at 1e-5, with more iterations as ``w`` falls).
        barrier_relaxation: ``δ`` of the relaxed log barrier: ``−log t`` for ``t ≥ δ``, its C² quadratic
            extension below (an infeasible start stays finite); with continuation ``δ`` follows ``w`` in the
            ratio ``barrier_relaxation / barrier_weight`` (1/10).
        barrier_continuation: decrease the weight between Newton stages down to ``barrier_weight_final``, so that
            a converged point is the hard-constrained problem's KKT point (an extension beyond the paper:
            :mod:`~torchtraj.solvers.eilqr.continuation`); ``False``: the paper's fixed weight, whose converged
            point is the KKT point of :meth:`EILQR.kkt_problem` (the soft problem).
        barrier_weight_initial: the continuation's first weight (IPOPT starts its ``μ`` at 1e-1). Measured on the
            cart-pole with ``short_step`` 0: from 1e-4 its first stage crawled (263 iterations in all, steps of 0.002
            to 0.03 against its stiff barrier), from 1e-3 85, from 1e-2 68, from 1e-1 107; the pendulum took 110,
            223, 232 from 1e-4, 1e-3, 1e-2 (176 from 1e-2 with the default ``short_step``).
        barrier_weight_final: the last stage's weight ``w_min``; ``None``: ``tol / 10`` of the dtype's tolerance in
            float64 (1e-10), ``tol / 100`` in float32 (1e-7;
            :func:`~torchtraj.solvers.eilqr.continuation.final_weight`).
        barrier_decrease, barrier_superlinear: ``κ_w``, ``θ_w`` of ``w ← max(w_min, min(κ_w w, w^θ_w))``
            (IPOPT's ``κ_μ = 0.2``, ``θ_μ = 1.5``, Wächter & Biegler 2006 eq. (7)).
        barrier_error_factor: ``κ_ε``: a stage ends where the KKT error of its weight is below ``κ_ε w`` (IPOPT's
            ``κ_ε = 10``).
        merit_factor, merit_floor: the ℓ1 merit's weight ``γ = merit_factor · max|y⁺| + merit_floor`` from the
            Newton step's multiplier estimates ``y⁺`` (Horizon eq. 9 with a margin of 50 %; the floor keeps ``γ > 0``
            where every multiplier vanishes). It is exact above ``max|y*|`` and the step is a descent direction of
            the merit for any ``γ > max|y⁺|`` (:mod:`~torchtraj.solvers.eilqr.merit`).
        merit_monotone: never lower ``γ`` during a solve (Nocedal & Wright's safeguard against cycling between
            merit functions). Off by default: the paper sets a "reasonable" weight from the current estimates,
            and a weight fixed by the first iterations' large multipliers slowed the pendulum from 57 iterations
            to more than 100.
        armijo: the sufficient-decrease constant ``η`` of ``m(α) ≤ m(0) + η α D m``.
        backtracking: the step-size factor ``β``: trials ``α = β^j``, ``j < line_search_steps``.
        line_search_steps: how many step sizes are tried; ``per_round``: how many are evaluated in one batched
            call.
        regularization_first, regularization_min, regularization_max, regularization_decrease,
            regularization_increase_first, regularization_increase: the ``ε_reg I`` added to the Lagrangian
            Hessian (the paper's Fig. 5), with IPOPT's inertia-correction numbers (``δ_w^0``, ``δ_w^{min}``,
            ``δ_w^{max}``, ``κ_w^-``, ``κ̄_w^+``, ``κ_w^+``). Within an iteration it rises where a reduced Hessian is
            not positive definite (refactorised, at most ``regularization_attempts`` times; where they run out below
            ``regularization_max`` the iterate stays and the next iteration starts above the largest ``ε`` tried:
            from the carried ``ε ≈ 1e-20`` twelve attempts reach about 1e-9, and quadrotor2d's start 47 of
            ``sample_x0`` had ended ``MAX_REGULARIZATION`` so, issue 23). Between iterations it is carried:
            ``×κ_w^+`` (at least ``δ_w^0``) after a step the merit refused or cut below ``short_step``, ``×κ_w^-``
            after a full step (zero below ``regularization_min``), kept otherwise (``regularization_partial``:
            ``×min(1/α, κ_w^+)`` after a step cut to ``α ≥ short_step``); past ``regularization_max`` the status is
            ``MAX_REGULARIZATION``.
        short_step: the step size below which the next iteration is regularised more (a shorter, more
            gradient-like step where the Newton model was poor). At 0.1 the regularisation that an early cut step
            raised was carried by every later partial step: the cart-pole without bounds took 219 iterations at
            ``α = 0.125`` and ``ε = 2.7e-4`` (33 at 0.05 or 0); at 0 the pendulum without bounds never got the
            regularisation it needs (more than 300 iterations; 57 at 0.1, 62 at 0.05).
        boundary_fraction: ``τ_min`` of the fraction-to-the-boundary rule ``τ = max(τ_min, 1 − w)`` that truncates
            each step to the barrier's domain before the line search (IPOPT's ``τ_min = 0.99``;
            :mod:`~torchtraj.solvers.eilqr.globalization`), with ``barrier_continuation`` (with the paper's fixed
            weight the relaxed barrier is the problem itself and no step is truncated). ``None``: no truncation
            (before issue 23's change: cart-pole's ``sample_x0`` batch 48/64 against 54/64 with it, but the
            pendulum's and car_3obs's median iterations there 130.5 and 83.5 against 196.5 and 183.5;
            ``docs/benchmarks.md``, eILQR).
        regularization_partial: after a step cut to ``α ≥ short_step``, multiply the next ``ε`` by ``min(1/α, κ_w^+)``
            (a trust region's radius from the accepted step: where ``ε`` dominates the reduced Hessian's smallest
            eigenvalue the step's length goes as ``1/ε``). Off by default: on ``sample_x0("cartpole_unconstrained",
            64, 0)`` with ``second_order_trials=4`` it shortened the crawls (``α = 1/16`` at a fixed ``ε = 7e-4``) but
            slowed the problem's own start (33 iterations with the defaults; 179 with both, 150 with the trials only).
        second_order_trials: how many trial step sizes ``α = 1, β, …`` of the line search get the second-order
            correction where the merit refuses them (1: the first only, IPOPT's; ``docs/benchmarks.md``, eILQR, has
            the measurements with 4).
        second_order_correction: correct a refused full step once before backtracking
            (:mod:`~torchtraj.solvers.eilqr.globalization`).
        nonmonotone_memory: ``M``: the Armijo test compares a trial point's merit with the largest of the last ``M``
            iterates' (Grippo, Lampariello & Lucidi 1986, their ``M = 10``; :mod:`~torchtraj.solvers.eilqr.merit`),
            so that the merit may rise for a few iterations where the ℓ1 penalty of the second-order defects (the
            Maratos effect) refuses steps the Newton model accepts; 1: the monotone test (before issue 23).
            Measured with ``sample_x0(name, 64, 0)`` (``docs/benchmarks.md``, eILQR): with 1, cartpole 54/64 and
            cartpole_unconstrained 42/64 converged, the others crawling at ``α = 1/16`` along valleys of negative
            curvature; with 10, 64/64 each, at IPOPT's optima or lower ones, and the problems' own starts no slower
            (the pendulum 152 → 47 iterations, the cart-pole 72 → 40).
        terminal_rows: how the Newton step holds the terminal equality rows (:func:`~torchtraj.riccati.factorize`):
            ``"range-space"``, the unconstrained sweep and the rows' Schur complement
            (:mod:`~torchtraj.riccati.range_space`, the interior point's default), where the problem has no stage
            equality rows and the initial state is fixed; ``"back-propagation"``, Horizon's constraint
            back-propagation (§II-B/C) always. Both solve the same Newton system; they differ in round-off. With a
            goal the controls must reach, the back-propagation fixes the last few controls by the terminal rows
            (on quadrotor2d, all six rows by the last three controls, singular values down to ``1.5e-5``), so the
            value function's Hessians there grow as their inverse squares and the step's multipliers lose their
            accuracy: on ``sample_x0("quadrotor2d", 64, 0)`` start 17, iteration 2, its terminal multipliers were
            ``1.2e7`` and its costates ``4.9e9`` where a dense solve of the same system and the range-space method
            give ``675``; moved into the iterate, they made the Lagrangian's Hessian indefinite by ``1e6`` (the
            regularisation's 140 iterations of crawl) and ended the solve ``MAX_REGULARIZATION`` (issue 23). The
            range-space method asks the inertia test for a positive definite ``Q_uu`` at every stage (with the
            rows' projector added to ``Q_N``), the back-propagation on the controls the rows leave free, so ``ε``
            can differ on a nonconvex problem.
        globalization: ``False`` takes the full Newton step with no line search and no regularisation (the
            paper's "crucial" ingredients left out; for experiments).
        free_initial_state: optimise ``x_0`` (Horizon §II-D): ``True`` for every component, a sequence of the
            free components' indices (the others stay at the given ``x_0``), ``False`` for none.
        initial_eq: ``h_0(x_0, p) -> (m_0,)`` equality rows on a free ``x_0`` (a line it starts on, ...).
        problem_state_guess: without an ``X0``, start the states from the problem's own guess ``Problem.X_init``
            where it carries one (multiple shooting from it, as from an ``X0``; IPOPT's reference starts there too),
            ``False``: from the rollout of ``U0``. Measured on ``car_escape``, the one problem of the set with a state
            guess: from the rollout (its own ``x0`` inside the walls) 300 iterations, ``MAX_ITERATIONS``; from its
            ``X_init`` IPOPT's optimum in 219. A control step never takes it (:meth:`EILQR.step_options`).
        max_state: ``|x|`` above which an instance is ``DIVERGED``.
        test_last_iterate: where the iterations run out, expand the last iterate and test it for convergence.
            ``False``: its barrier multipliers are taken from the rows' values alone (no derivatives), and an
            instance still running reports ``MAX_ITERATIONS`` even where that iterate would pass the test
            (``NON_FINITE`` where its cost or violation is not finite, ``DIVERGED``): a control step, whose plan
            is applied whatever the status, saves an expansion.
        compile: ``torch.compile`` the per-iteration kernels (:mod:`torchtraj.core.compiled`): the expansion, the
            Newton step, the step's bound and slope, the trial points and their merit, the second-order correction's
            step, the choice of a step, the move and the initial rollout (the loop, its masks and the
            regularisation's attempts stay eager, as in the other methods). The first solve of a problem compiles
            them (minutes on a CPU); a compiled step keeps no factorisation, so a correction factorises its system
            again.
        record: replay the expansion from its operator graph recorded once per batch size
            (:mod:`torchtraj.core.recorded`): the same numbers with fewer, cheaper calls, after a trace of a fraction
            of a second per shape. ``None`` (default): a shape is recorded once it has been evaluated about as often
            as its trace costs; ``True``: early (a controller's steps); ``False``: never.
        verbose: log one line per iteration.
    """

    iterations: int = 300
    tolerance: Optional[float] = None
    barrier_weight: float = 1e-4
    barrier_relaxation: float = 1e-5
    barrier_continuation: bool = True
    barrier_weight_initial: float = 1e-2
    barrier_weight_final: Optional[float] = None
    barrier_decrease: float = 0.2
    barrier_superlinear: float = 1.5
    barrier_error_factor: float = 10.0
    merit_factor: float = 1.5
    merit_floor: float = 1e-6
    merit_monotone: bool = False
    armijo: float = 1e-4
    backtracking: float = 0.5
    line_search_steps: int = 16
    per_round: int = 4
    regularization_first: float = 1e-4
    regularization_min: float = 1e-20
    regularization_max: float = 1e10
    regularization_decrease: float = 1.0 / 3.0
    regularization_increase_first: float = 100.0
    regularization_increase: float = 8.0
    regularization_attempts: int = 12
    short_step: float = 0.05
    boundary_fraction: Optional[float] = 0.99
    regularization_partial: bool = False
    second_order_trials: int = 1
    second_order_correction: bool = True
    nonmonotone_memory: int = 10
    terminal_rows: str = "range-space"
    globalization: bool = True
    free_initial_state: Union[bool, Sequence[int]] = False
    initial_eq: Optional[Callable] = None
    problem_state_guess: bool = True
    max_state: float = 1e8
    test_last_iterate: bool = True
    compile: bool = False
    record: Optional[bool] = None
    verbose: bool = False

    def __post_init__(self):
        if self.barrier_weight <= 0 or self.barrier_relaxation <= 0:
            raise ValueError(f"barrier_weight and barrier_relaxation must be positive, got {self.barrier_weight} "
                             f"and {self.barrier_relaxation}")
        if self.barrier_weight_initial <= 0:
            raise ValueError(f"barrier_weight_initial must be positive, got {self.barrier_weight_initial}")
        if self.barrier_weight_final is not None and self.barrier_weight_final <= 0:
            raise ValueError(f"barrier_weight_final must be positive, got {self.barrier_weight_final}")
        if not 0 < self.barrier_decrease < 1 or self.barrier_superlinear <= 1 or self.barrier_error_factor <= 0:
            raise ValueError("barrier_decrease must lie in (0, 1), barrier_superlinear exceed 1 and "
                             "barrier_error_factor be positive")
        if self.nonmonotone_memory < 1:
            raise ValueError(f"nonmonotone_memory must be at least 1 (1: the monotone test), "
                             f"got {self.nonmonotone_memory}")
        check_terminal_rows(self.terminal_rows)
        if not 0 < self.backtracking < 1:
            raise ValueError(f"backtracking must lie in (0, 1), got {self.backtracking}")
        if self.initial_eq is not None and self.free_initial_state is False:
            raise ValueError("initial_eq constrains a free initial state: set free_initial_state as well")

    def tolerance_for(self, dtype: torch.dtype) -> float:
        if self.tolerance is not None:
            return self.tolerance
        return 1e-9 if dtype == torch.float64 else 1e-5
