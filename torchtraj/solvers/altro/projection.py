r"""ALTRO's active-set projection (Howell et al. 2019 §III-D, Algorithms 2-3), in sequential form.

The coarse AL-iLQR solution ``Y = (X, U)`` is projected onto the manifold of the active constraints
``d(Y) = 0`` — the dynamics ``f(x_k, u_k) − x_{k+1}``, the initial condition, every equality and the
inequalities held active — in the norm of the objective's Hessian ``H``:

.. math::  \delta Y = -H^{-1} D^T (D H^{-1} D^T)^{-1} d
           = \arg\min_{\delta Y} \tfrac12 \delta Y^T H \delta Y \ \text{s.t.}\ D\,\delta Y + d = 0.

Instead of building ``D H^{-1} D^T`` (Algorithm 2's ``S``), the minimisation is solved as an
equality-constrained LQR by the shared Riccati core (the "sequential" form the paper points to,
its ref. [16]): ``Q, R, S, Q_N`` from the cost Hessian, the linearised dynamics with the defects as
affine terms, the active rows as stagewise equality constraints. The factorisation plays the part of
``S``: it is computed when the constraints are linearised and reused for further Newton steps with
new right-hand sides while the convergence rate ``r = log v⁺ / log v`` stays above
``convergence_rate`` (Algorithm 2, line 8); then the constraints are linearised again.

Each step is a line search on ``v = ‖d‖_∞`` (Algorithm 3): ``α ∈ {1, γ, γ², …}``, all candidates
evaluated in one batched call, the largest ``α`` with ``v(α) < v`` taken.

The LQR is the held-rows KKT system of :mod:`torchtraj.kkt.newton` with the cost Hessian and no gradient. An
inequality row is held when it is violated or nearly so (``g > −active_tolerance``) or its multiplier is positive
(:func:`torchtraj.kkt.activity.by_value_or_multiplier`). The multipliers of the projected point are then the
least-squares solution of stationarity, ``∇ℓ + Dᵀ ν = 0``, from one more solve with the cost gradient. Last,
Newton steps on the KKT conditions of the held rows with the Lagrangian Hessian make the feasible point stationary
too (:mod:`torchtraj.solvers.altro.polish`): the steps above, made without the cost gradient, leave a stationarity
error that the least-squares multipliers do not remove.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage
from ...core.compiled import kernel, unplanned_single
from ...core.derivatives import quadratize_cost, stage_jacobian
from ...core.masks import where_rows
from ...globalization.line_search import Accepted, backtrack
from ...kkt import activity
from ...kkt.newton import held_lqr, newton_rhs, newton_step
from ...riccati import factorize
from .augmented_lagrangian import AugmentedLagrangian, resolution_floor
from .polish import ROUND_OFF, KKTPoint, kkt_error, newton_kkt_step


@dataclass
class ProjectionOptions:
    """Options of :func:`project` (Altro.jl ``SolverOptions`` where it has them)."""

    #: Target largest violation of the active constraints and the dynamics; met at the dtype's resolution where it
    #: lies below it (:func:`resolution_floor`).
    tolerance: float = 1e-8
    #: Inequalities with ``g > −active_tolerance`` (or a positive multiplier) are held as equalities.
    active_tolerance: float = 1e-6
    #: Re-linearise when ``log v⁺ / log v`` falls below this (Altro.jl ``r_threshold``).
    convergence_rate: float = 1.1
    #: Linearisations (outer loop of Algorithm 2).
    iterations: int = 10
    #: Newton steps per linearisation.
    inner_iterations: int = 10
    #: Line-search step shrink ``γ`` and number of step sizes.
    line_search_decrease: float = 0.5
    line_search_steps: int = 10
    #: Added to ``Q_uu`` so the objective Hessian is definite on the controls.
    regularization: float = 1e-8
    #: Relative singular value below which an active row counts as dependent on the others (``None``:
    #: ``√eps``). Near-degenerate active sets (a car pinned in a corner of its box, where the
    #: linearised rows differ by ``dt·v ≈ 0``) would otherwise get steps of size ``1/σ``.
    rank_tolerance: Optional[float] = None
    #: Multiplier solves: after each, active inequalities with a negative multiplier are released.
    multiplier_passes: int = 4
    #: Newton steps on the KKT conditions of the held rows after the projection, each kept where it lowers the KKT
    #: error (:mod:`torchtraj.solvers.altro.polish`; not in the paper, 0 turns them off). An update of the held set
    #: takes one of them: from parallel_park's sample starts 26 and 40 the set changed four times before the Newton
    #: steps converged (in five and six more), and with 4 both ended ``STALLED`` at stationarity 1e-4. An instance
    #: stops as soon as its step is at round-off, so the count costs only where it is needed.
    polish_iterations: int = 16


@dataclass
class Projected:
    """Projected trajectories and the multipliers of the projected point.

    ``violation (B,)`` is the largest violation of the active set and dynamics; ``costate (B, N+1, nx)``,
    ``stage (B, N, m)`` and ``terminal (B, mN)`` are multipliers in the stacked layout of
    :class:`~torchtraj.solvers.altro.augmented_lagrangian.AugmentedLagrangian` (zero on inactive rows).
    """

    X: Tensor
    U: Tensor
    violation: Tensor
    converged: Tensor
    costate: Tensor
    stage: Tensor
    terminal: Tensor
    K: Tensor


def _residuals(al: AugmentedLagrangian, dynamics, params, x0, X, U, stage_active, terminal_active):
    """Defects ``(B, *E, N, nx)``, initial defect, active stage/terminal values, and ``v = ‖d‖_∞`` ``(B, *E)``."""
    defect = map_stage(dynamics, X[..., :-1, :], U, params) - X[..., 1:, :]
    init = x0.reshape(x0.shape[0], *([1] * (X.dim() - 3)), -1) - X[..., 0, :]
    c = al.stage_values(X, U, params)
    cN = al.terminal_values(X, params)
    extra = X.dim() - 3
    sa = stage_active.reshape(stage_active.shape[0], *([1] * extra), *stage_active.shape[1:])
    ta = terminal_active.reshape(terminal_active.shape[0], *([1] * extra), *terminal_active.shape[1:])
    c, cN = c * sa, cN * ta
    parts = [defect.abs().flatten(-2), init.abs(), c.abs().flatten(-2), cN.abs()]
    v = torch.cat(parts, -1).amax(-1)
    return defect, init, c, cN, v


def _active_rows(al: AugmentedLagrangian, X, U, params, opts: ProjectionOptions):
    d = al.duals
    c = al.stage_values(X, U, params)
    cN = al.terminal_values(X, params)
    # equality rows are always held; an inequality row by ALTRO's rule
    stage = (~al.is_ineq | activity.by_value_or_multiplier(c, d.stage, opts.active_tolerance)) & (al.knot_mask > 0)
    terminal = ~al.is_ineqN | activity.by_value_or_multiplier(cN, d.terminal, opts.active_tolerance)
    return stage.to(X.dtype), terminal.to(X.dtype)


def _held_lqr(al: AugmentedLagrangian, params, X, U, stage_active, terminal_active):
    """The held-rows KKT system's matrices at ``(X, U)`` with the cost Hessian (the projection's metric ``H``),
    and the cost gradient ``(B, N, nz)``, ``(B, nx)`` for the multiplier solve."""
    problem = al.problem
    _, fz = stage_jacobian(problem.dynamics, X, U, params)
    cost = quadratize_cost(problem.stage_cost, problem.terminal_cost, X, U, params)
    # a block of zero rows is kept as one: the Riccati core's constrained sweep, as the projection always took
    _, Cz, _, CN = al.row_jacobians(X, U, params)
    lqr = held_lqr(fz, cost.hessian, cost.terminal_hessian, rows=Cz, mask=stage_active, rowsN=CN,
                   maskN=terminal_active, lower_only=True)
    return lqr, cost.gradient, cost.terminal_gradient


def project(al: AugmentedLagrangian, params, x0: Tensor, X: Tensor, U: Tensor, mask: Tensor,
            opts: ProjectionOptions, compile: bool = False) -> Projected:
    """Project the instances in ``mask (B,)`` of ``(X, U)``; the others are returned unchanged. ``compile``: the
    feasibility steps, the multiplier solves, the Newton steps on the KKT conditions and their KKT errors run as
    compiled kernels (:func:`~torchtraj.core.compiled.kernel`)."""
    B = U.shape[0]
    reg = X.new_full((B,), opts.regularization)
    eps = torch.finfo(X.dtype).eps
    rank_tol = eps ** 0.5 if opts.rank_tolerance is None else opts.rank_tolerance
    tolerance = resolution_floor(X, U).clamp_min(opts.tolerance)
    X, U = _feasibility_steps(al, params, x0, X, U, mask, opts, reg, rank_tol, tolerance, compile=compile)
    stage_active, terminal_active = _active_rows(al, X, U, params, opts)
    _, _, _, _, v = _residuals(al, al.problem.dynamics, params, x0, X, U, stage_active, terminal_active)
    held = multipliers(al, params, X, U, opts, stage_active, terminal_active, compile)
    point = KKTPoint(X, U, held.costate, held.stage, held.terminal, held.K)
    # the feasible point made stationary as well, with the rows held whose multipliers have the right sign; where it
    # moved, its violation is that of every row and the dynamics (the held set may have changed on the way)
    point, moved, violation = _polished(al, params, x0, point, mask & (v <= tolerance),
                                        (held.stage_active, held.terminal_active), opts, reg, rank_tol, tolerance,
                                        compile)
    v = torch.where(moved, violation, v)
    converged = mask & (v <= tolerance)
    return Projected(X=point.X, U=point.U, violation=v, converged=converged, costate=point.costate,
                     stage=point.stage, terminal=point.terminal, K=point.K)


def _feasibility_steps(al: AugmentedLagrangian, params, x0: Tensor, X: Tensor, U: Tensor, mask: Tensor,
                       opts: ProjectionOptions, reg: Tensor, rank_tol: float, tolerance: Tensor,
                       held: Optional[tuple] = None, compile: bool = False):
    """Algorithms 2-3 on the instances in ``mask (B,)``: ``(X, U)`` with ``v ≤ tolerance (B,)`` where the steps
    reach it. The rows held are ALTRO's (:func:`_active_rows`, at each linearisation), or ``held = (stage (B, N, m),
    terminal (B, mN))``. ``compile``: each step one compiled kernel (:func:`_linearised_step`), which factorises
    again at the linearisation point, since a kernel hands on no factorisation; the same factor, bit for bit."""
    alphas = opts.line_search_decrease ** torch.arange(opts.line_search_steps, dtype=X.dtype, device=X.device)
    residuals_k, step_k = kernel(_residuals, compile), kernel(_linearised_step, compile)
    for _ in range(opts.iterations):
        stage_active, terminal_active = _active_rows(al, X, U, params, opts) if held is None else held
        defect, init, c, cN, v = residuals_k(al, al.problem.dynamics, params, x0, X, U, stage_active, terminal_active)
        pending = mask & (v > tolerance)
        if not bool(pending.any()):
            break
        rows, point = (stage_active, terminal_active), (X, U, defect, init, c, cN, v)
        if compile:  # the kernel factorises at (X, U), which stay the linearisation point until the loop ends
            stepping = pending
        else:
            factor = _factorised(al, params, X, U, *rows, reg, rank_tol)
            stepping = pending & factor.ok
        for _ in range(opts.inner_iterations):
            if not bool(stepping.any()):
                break
            if compile:
                take, point = step_k(al, params, x0, X, U, reg, rank_tol, rows, point, stepping, alphas)
            else:
                take, point = _step(al, params, x0, factor, rows, point, stepping, alphas)
            v_new = point[-1]
            rate = torch.log(v_new) / torch.log(v)
            v = v_new
            # reuse the factorisation only while convergence stays fast (Algorithm 2, line 8)
            stepping = take & (v > tolerance) & (rate > opts.convergence_rate)
        X, U = point[:2]
    return X, U


def _factorised(al: AugmentedLagrangian, params, X: Tensor, U: Tensor, stage_active: Tensor, terminal_active: Tensor,
                reg: Tensor, rank_tol: float):
    """The held-rows system at ``(X, U)`` with the cost Hessian, factorised: the ``S`` of Algorithm 2."""
    lqr, _, _ = _held_lqr(al, params, X, U, stage_active, terminal_active)
    return factorize(lqr, reg, rank_tolerance=rank_tol)


def _step(al: AugmentedLagrangian, params, x0: Tensor, factor, rows: tuple, point: tuple, stepping: Tensor,
          alphas: Tensor):
    """One step of Algorithm 2's inner loop for the ``stepping (B,)`` instances: the least-``H``-norm step onto the
    linearised rows (no gradient, the violations ``point[2:6]`` as offsets), then Algorithm 3, the largest ``α``
    with ``v(α) < v``, all step sizes in one round. ``point = (X, U, defect, init, c, cN, v)``; returns ``(take
    (B,), point)``, the other instances' point unchanged."""
    X, U, defect, init, c, cN, v = point
    B, N, nx = U.shape[0], U.shape[1], X.shape[-1]
    step = factor.solve(newton_rhs(X.new_zeros(B, N, nx + U.shape[-1]), X.new_zeros(B, nx), defect, init, c, cN))

    def decrease(alphas):
        """Algorithm 3's test, ``v(α) < v``, at every step size at once, and the candidates' values."""
        a = alphas.reshape(1, -1, 1, 1)
        Xc, Uc = X.unsqueeze(1) + a * step.dx.unsqueeze(1), U.unsqueeze(1) + a * step.du.unsqueeze(1)
        dc, ic, cc, cNc, vc = _residuals(al, al.problem.dynamics, params, x0, Xc, Uc, *rows)
        return torch.isfinite(vc) & (vc < v.unsqueeze(1)), (Xc, Uc, dc, ic, cc, cNc, vc)

    start = Accepted(found=~stepping, alpha=torch.zeros_like(v), values=point)
    accepted = backtrack(alphas, alphas.numel(), decrease, stepping, start)
    return stepping & accepted.found, accepted.values


@unplanned_single
def _linearised_step(al: AugmentedLagrangian, params, x0: Tensor, X: Tensor, U: Tensor, reg: Tensor,
                     rank_tol: float, rows: tuple, point: tuple, stepping: Tensor, alphas: Tensor):
    """:func:`_step` with the factorisation at the linearisation point ``(X, U)`` formed here (a compiled solve's
    kernel), for the instances of ``stepping`` whose system factorised."""
    factor = _factorised(al, params, X, U, *rows, reg, rank_tol)
    return _step(al, params, x0, factor, rows, point, stepping & factor.ok, alphas)


def _polished(al: AugmentedLagrangian, params, x0: Tensor, point: KKTPoint, mask: Tensor, held: tuple,
              opts: ProjectionOptions, reg: Tensor, rank_tol: float, tolerance: Tensor, compile: bool = False):
    """At most ``polish_iterations`` Newton steps on the KKT conditions of the ``held`` rows
    (:mod:`torchtraj.solvers.altro.polish`) for the feasible instances in ``mask (B,)``: ``(point, moved (B,),
    violation (B,))``, ``violation`` the largest of every row and the dynamics at ``point`` where it ``moved``.

    Where a step would violate a free inequality or leave a held one with a negative multiplier, the set is updated
    instead (Hintermüller, Ito & Kunisch's primal-dual rule, :func:`_updated_rows`) and the step computed again.
    Otherwise the step is followed by the feasibility steps back onto the rows (a second-order correction: a Newton
    step from afar leaves violations of the size of its square) and kept where the KKT error goes down and the
    violation stays within ``max(tolerance, its value before)``. The other instances are returned unchanged."""
    step_k, error_k = kernel(newton_kkt_step, compile), kernel(kkt_error, compile)
    error, violation = error_k(al, params, x0, point)
    eps = torch.finfo(point.X.dtype).eps
    moving = mask.clone()
    moved_at_all = torch.zeros_like(mask)
    for _ in range(opts.polish_iterations):
        if not bool(moving.any()):
            break
        moved, size, ok = step_k(al, params, x0, point, held[0], held[1], reg, rank_tol)
        following, changed = _updated_rows(al, params, moved, held, tolerance)
        changed = moving & ok & changed
        held = tuple(where_rows(changed, new, old) for new, old in zip(following, held))
        stepping = moving & ok & ~changed
        Xr, Ur = _feasibility_steps(al, params, x0, moved.X, moved.U, stepping, opts, reg, rank_tol, tolerance,
                                    held, compile)
        moved = dataclasses.replace(moved, X=Xr, U=Ur)
        moved_error, moved_violation = error_k(al, params, x0, moved)
        take = stepping & (moved_error < error) & (moved_violation <= torch.maximum(tolerance, violation))
        point = moved.where(take, point)
        error = torch.where(take, moved_error, error)
        violation = torch.where(take, moved_violation, violation)
        moved_at_all = moved_at_all | take
        scale = 1 + torch.maximum(point.X.abs().flatten(1).amax(-1), point.U.abs().flatten(1).amax(-1))
        moving = (take & (size > ROUND_OFF * eps * scale)) | changed
    return point, moved_at_all, violation


def _updated_rows(al: AugmentedLagrangian, params, moved: KKTPoint, held: tuple, tolerance: Tensor):
    """``((stage (B, N, m), terminal (B, mN)), changed (B,))``: the rows held after a Newton step to ``moved``: a held
    inequality stays where its multiplier is not negative, a free one joins where ``moved`` violates it by more than
    ``tolerance (B,)`` (round-off on a weakly active row is no reason to hold it); equality rows stay held."""
    stage, terminal = held
    c = al.stage_values(moved.X, moved.U, params) - tolerance.reshape(-1, 1, 1)
    cN = al.terminal_values(moved.X, params) - tolerance.reshape(-1, 1)
    applies = (al.knot_mask > 0) & al.is_ineq
    new_stage = torch.where(applies, torch.where(stage > 0, moved.stage >= 0, c > 0), stage > 0).to(stage.dtype)
    new_terminal = torch.where(al.is_ineqN, torch.where(terminal > 0, moved.terminal >= 0, cN > 0),
                               terminal > 0).to(terminal.dtype)
    changed = (new_stage != stage).flatten(1).any(-1) | (new_terminal != terminal).any(-1)
    return (new_stage, new_terminal), changed


@dataclass
class HeldMultipliers:
    """:func:`multipliers`' result: ``costate (B, N+1, nx)``, ``stage (B, N, m)``, ``terminal (B, mN)`` (zero off
    the held rows), the gains ``K`` of the held-rows system and the rows held in the end, ``stage_active (B, N, m)``
    and ``terminal_active (B, mN)`` (those of a negative multiplier released)."""

    costate: Tensor
    stage: Tensor
    terminal: Tensor
    K: Tensor
    stage_active: Tensor
    terminal_active: Tensor


def multipliers(al: AugmentedLagrangian, params, X: Tensor, U: Tensor, opts: ProjectionOptions,
                stage_active: Optional[Tensor] = None, terminal_active: Optional[Tensor] = None,
                compile: bool = False) -> HeldMultipliers:
    """The least-squares multipliers of the held rows at ``(X, U)``, the rows held by ALTRO's rule (or
    ``stage_active``, ``terminal_active``), the others zero, and the gains of the held-rows system; ``compile``:
    each solve a compiled kernel."""
    B = U.shape[0]
    reg = X.new_full((B,), opts.regularization)
    eps = torch.finfo(X.dtype).eps
    rank_tol = eps ** 0.5 if opts.rank_tolerance is None else opts.rank_tolerance
    if stage_active is None:
        stage_active, terminal_active = _active_rows(al, X, U, params, opts)
    solve = kernel(_least_squares_multipliers, compile)
    for _ in range(opts.multiplier_passes):
        costate, nu, nuN, K = solve(al, params, X, U, stage_active, terminal_active, reg, rank_tol)
        # Dependent active rows (a car parked in a corner of its box) leave the multipliers non-unique
        # and the least-squares ones may be negative; such rows are released and the others take over.
        wrong = al.is_ineq & (nu * stage_active < 0)
        wrongN = al.is_ineqN & (nuN * terminal_active < 0)
        if not bool(wrong.any() | wrongN.any()):
            break
        stage_active = stage_active * (~wrong).to(X.dtype)
        terminal_active = terminal_active * (~wrongN).to(X.dtype)
    return HeldMultipliers(costate, nu * stage_active, nuN * terminal_active, K, stage_active, terminal_active)


@unplanned_single
def _least_squares_multipliers(al: AugmentedLagrangian, params, X: Tensor, U: Tensor, stage_active: Tensor,
                               terminal_active: Tensor, reg: Tensor, rank_tol: float):
    """One solve of :func:`multipliers`: ``(costate, nu, nuN, K)`` of the held-rows system at ``(X, U)`` with the
    cost gradient, stationarity ``∇ℓ + Dᵀν = 0`` at the projected point (no offsets)."""
    B, N, nx = U.shape[0], U.shape[1], X.shape[-1]
    lqr, lz, lNx = _held_lqr(al, params, X, U, stage_active, terminal_active)
    rhs = newton_rhs(lz, lNx, X.new_zeros(B, N, nx), X.new_zeros(B, nx), torch.zeros_like(stage_active),
                     torch.zeros_like(terminal_active))
    solved = newton_step(lqr, rhs, reg, rank_tol)
    return solved.step.costate, solved.step.nu, solved.step.nuN, solved.factor.K
