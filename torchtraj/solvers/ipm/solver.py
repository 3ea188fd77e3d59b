r"""A primal-dual interior-point method on multiple shooting, batched (FATROP, papers/fatrop.md).

FATROP (§II-B, §III) is IPOPT's algorithm applied to the multiple-shooting problem, with the
reduced primal-dual system solved by a Riccati recursion generalised to stagewise equality
constraints. Here the inequality rows ``g(z) ≤ 0`` of the problem (the stacked blocks of
:class:`~torchtraj.core.constraints.Constraints`: path and terminal inequalities and finite bounds) get
slacks ``s ≥ 0`` and the barrier problem (FATROP eq. 3, with this library's sign of ``g``) is

.. math::

    \min_{w, s}\; J(w) - μ \sum_i \log s_i \quad \text{s.t.}\quad
    x_{k+1} = f(x_k, u_k),\; h(w) = 0,\; g(w) + s = 0,

``w = (X, U)`` with ``x_0`` fixed. Its primal-dual Newton step (eq. 6) with the inequality multipliers
``z`` (the multiplier of ``g + s = 0`` is the bound multiplier of ``s`` at stationarity in ``s``),
after eliminating ``Δs`` and ``Δz`` (eqs. 7-8), is the equality-constrained LQR problem (eq. 9)

.. math::

    H_k = ∇^2_{z_k z_k} \mathcal L + G_k^T Σ_k G_k + δ_w I,\quad
    \begin{bmatrix} q_k \\ r_k \end{bmatrix} = ∇_{z_k} \mathcal L + G_k^T S_k^{-1} (μ e + Z_k g_k),\quad
    Σ_k = S_k^{-1} Z_k,

with the dynamics linearised around the (possibly defective) trajectory — the defects
``f(x_k, u_k) − x_{k+1}`` are the affine terms ``c_k`` — and the equality rows ``h`` as stagewise
constraints of the shared Riccati core (:mod:`torchtraj.riccati`). Because the linear terms are the
*whole* Lagrangian gradient ``∇\mathcal L`` (costates ``λ``, equality multipliers ``ν``, ``z``), the
core's costates and constraint multipliers are the steps ``Δλ``, ``Δν``. Then (eq. 8)

.. math::  Δs = −(g + s) − G Δw, \qquad Δz = S^{-1} (μ e + Z g + Z G Δw).

The rest is IPOPT's (Wächter & Biegler 2006; FATROP §III defers to it), with its defaults in
:class:`IPOptions`:

* **Barrier update** (monotone Fiacco-McCormick): when the barrier problem's error ``E_μ ≤ κ_ε μ``,
  ``μ ← max(tol/10, min(κ_μ μ, μ^{θ_μ}))`` (repeatedly within one iteration) and the filter is reset.
  Converged when ``E_0 ≤ tol``; ``E_μ`` is the scaled maximum of the Lagrangian gradient, the
  constraint violation (defects, equalities, ``g + s``) and ``S z − μ`` (IPOPT eq. 5).
* **Fraction to boundary**: ``τ = max(τ_min, 1 − μ)``; ``s`` and ``z`` keep a fraction ``1 − τ`` of their
  distance to zero, ``z`` with its own step ``α_z``, then ``z`` is clipped to ``[μ/(κ_Σ s), κ_Σ μ/s]``.
* **Filter line search** on ``θ = ‖c‖₁`` and the barrier objective ``φ``: switching condition,
  Armijo condition for f-type steps, sufficient decrease in ``θ`` or ``φ`` otherwise, filter
  augmentation after h-type steps. The backtracking step sizes ``α_max β^j`` are evaluated in rounds of
  ``line_search_parallel``, every instance and step size of a round in one batched evaluation (multiple
  shooting needs no rollout); the full step is usually accepted in the first round.
* **Inertia correction** (FATROP §III "Hessian regularization"): the Riccati recursion reports
  whether every reduced Hessian is positive definite (``RiccatiFactor.ok``); if not, ``δ_w`` grows by
  IPOPT's rule (first ``δ_w^0``, or ``κ_w^- δ_w^{last}``, then ``κ_w^+`` or ``κ̄_w^+`` per attempt) and the
  batch is factorised again, instances that already succeeded keeping their factor.

* **Mehrotra's predictor-corrector** (``barrier_strategy="mehrotra"``, opt-in; IPOPT's ``mehrotra_algorithm``, for
  LPs and convex QPs): each iteration solves the factorised system twice, first for the affine-scaling step
  (``S z = 0``), whose largest steps to the boundary give ``μ_aff``; then ``μ = σ μ̄`` with
  ``σ = min((μ_aff / μ̄)³, σ_max)`` and the average complementarity ``μ̄`` (within ``[tol/10, 10³ μ̄_0]``), and the
  corrector step for ``S z = μ − ΔS_aff Δz_aff``. No line search: the fraction-to-boundary steps are taken whole (a
  step the boundary cuts to round-off counts as a failed one). On the bench's box-constrained linear system
  (B = 256) it takes 6.9 iterations on average, at most 11, against 10.9 and 17; on the nonlinear pendulum with
  state bounds, without a globalisation, 80 against 28, and one instance ends at another local optimum: it is not
  the default.
* **Finished instances leave the batch** (``compact_below``): once the running instances are at most that
  share of the batch being iterated, their rows are gathered (iterate, model, filter, parameters) and the
  next iterations run on them alone; the others' results are written back. The arithmetic of an instance is
  unchanged, bit for bit, and the batch's spread of iteration counts no longer costs the slowest one's
  iterations for all: the time of an iteration grows about linearly with the batch past a few dozen
  instances (one CPU core, the bench's ``linear_box``: 112 ms at B = 256, 57 at 128, 35 at 64).
* **Active-set crossover** (linear-quadratic problems, ``crossover``; :mod:`torchtraj.solvers.ipm.crossover`): once an
  instance's ``E_0 ≤ crossover_from``, the rows with ``z > s`` are held as equalities and one Riccati solve gives
  the KKT point of that set exactly; it ends the instance where it passes the convergence test, else up to
  ``crossover_rounds`` primal-dual active-set updates are tried. Where every row is a control bound, up to
  ``crossover_start_rounds`` sets are tried before the first iteration, from the unconstrained optimum. On the
  bench's box-constrained linear system (B = 256) every instance ends there, after 3.8 rounds on average (at most
  6), at its KKT point to round-off (``|U − U*| ≤ 4e-10`` against ``1e-5`` at the tolerance), in 0.41 s against
  1.1 s for the iterations alone (one CPU core).

Left out, and what happens instead: there is no feasibility-restoration phase and no second-order
correction. An instance whose line search finds no acceptable step keeps its iterate and
retries with a larger ``δ_w`` (a shorter, more gradient-like step); past ``regularization_max`` its status
is ``MAX_REGULARIZATION``. The filter holds the last ``filter_size`` entries of each instance.
Multipliers start at zero (``λ``, ``ν``, ``y``) and ``dual_initial`` (``z``), not at IPOPT's least-squares
estimate; slacks at ``max(−g, κ_1)``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, fields
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state, param_rows, rollout
from ...core.compiled import kernel
from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints, multiplier_blocks
from ...core.derivatives import (
    affine_stage_jacobian,
    multiplier_terms,
    problem_lagrangian_expansion,
    quadratic_stage_hessian,
    stage_jacobian,
    terminal_hessian,
    terminal_jacobian,
)
from ...core.graphs import graphed, graphs_used
from ...core.masks import first_true, where_rows
from ...core.problem import Problem
from ...core.solution import History, Solution
from ...core.status import Status
from ...kkt.model import total_cost
from ...riccati import LQR, LQRVectors, RiccatiFactor, all_finite, factorize
from . import crossover
from .iterate import Iterate, Model
from .options import IPOptions

logger = logging.getLogger("torchtraj")


def _pick(mask: Tensor, a, b):
    """The batch-first dataclass ``a`` where ``mask (B,)``, else ``b`` (field by field; a field that is no tensor,
    as a :class:`Direction`'s factor, is kept where ``a`` and ``b`` share it, else ``None``)."""
    def one(x, y):
        return where_rows(mask, x, y) if isinstance(x, Tensor) else (x if x is y else None)

    return type(a)(**{f.name: one(getattr(a, f.name), getattr(b, f.name)) for f in fields(a)})


def _flat_abs(*parts: Tensor) -> Tensor:
    B = parts[0].shape[0]
    return torch.cat([p.reshape(B, -1).abs() for p in parts] + [parts[0].new_zeros(B, 1)], -1)


# ----------------------------------------------------------------------------------------- expansion
def _constraint_parts(cons: Constraints, X: Tensor, U: Tensor, params, jacobians: bool, affine: bool = False):
    """Values (and Jacobians) of the stage inequalities (rows off at a knot are zero), stage equalities,
    terminal inequalities and equalities; ``affine``: rows affine in ``(x, u)``, their stage Jacobians taken once
    per instance (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`)."""
    N, nx, nu = U.shape[-2], X.shape[-1], U.shape[-1]
    lead = X.shape[:-2]
    nz = nx + nu
    Xs, xN = X[..., :-1, :], X[..., -1, :]

    def stage(fn, m):
        if not m:
            return X.new_zeros(*lead, N, 0), X.new_zeros(*lead, N, 0, nz)
        if jacobians:
            return (affine_stage_jacobian if affine else stage_jacobian)(fn, Xs, U, params)
        return map_stage(fn, Xs, U, params), None

    def terminal(fn, m):
        if not m:
            return X.new_zeros(*lead, 0), X.new_zeros(*lead, 0, nx)
        if jacobians:
            return terminal_jacobian(fn, xN, params)
        return map_state(fn, xN, params), None

    g, Gz = stage(cons.stage_ineq, cons.mi)
    knots = cons.ineq_knot_mask
    g = g * knots
    Gz = None if Gz is None else Gz * knots.unsqueeze(-1)
    h, Hz = stage(cons.stage_eq, cons.me)
    gN, GN = terminal(cons.terminal_ineq, cons.miN)
    hN, HN = terminal(cons.terminal_eq, cons.meN)
    return g, Gz, h, Hz, gN, GN, hN, HN


@dataclass
class Base:
    """The first expansion of a linear-quadratic problem (``Problem.linear_quadratic``): its point ``X``, ``U``
    and :class:`Model`, taken where every multiplier is zero, so that ``model.Lz`` is the cost gradient."""

    X: Tensor
    U: Tensor
    model: Model


def _linear_quadratic_derivatives(it: Iterate, base: Base):
    """The Lagrangian gradient at ``it`` of a linear-quadratic problem from its first expansion: the cost
    gradient moves with the constant cost Hessian, and the constant Jacobians carry the multipliers."""
    X, U, m = it.X, it.U, base.model
    dz = torch.cat([X[:, :-1] - base.X[:, :-1], U - base.U], -1)
    stage, terminal = multiplier_terms(m.fz, m.Hz, m.Gz, m.HN, m.GN, it.lam[:, 1:], it.nu, it.y, it.nuN, it.yN)
    Lz = m.Lz + _mv(m.Lzz, dz) + stage
    LNx = m.LNx + _mv(m.LNxx, X[:, -1] - base.X[:, -1]) + terminal
    return Lz, m.Lzz, LNx, m.LNxx, m.fz, m.Gz, m.Hz, m.GN, m.HN


def _linear_quadratic_expansion(problem: Problem, cons: Constraints, params, it: Iterate) -> tuple:
    """The first expansion of a linear-quadratic problem: every Jacobian and Hessian taken once per instance and
    broadcast over the stages (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`); the Lagrangian's Hessian is
    the costs' (affine rows have no curvature), its gradient the costs' and the multipliers' terms."""
    X, U = it.X, it.U
    f, fz = affine_stage_jacobian(problem.dynamics, X[:, :-1], U, params)
    _, lz, Lzz = quadratic_stage_hessian(problem.stage_cost, X[:, :-1], U, params)
    _, lNx, LNxx = terminal_hessian(problem.terminal_cost, X[:, -1], params)
    g, Gz, h, Hz, gN, GN, hN, HN = _constraint_parts(cons, X, U, params, jacobians=True, affine=True)
    # stored whole, not as broadcast views: products with a gathered copy (compact_below) then round alike
    fz, Lzz, Gz, Hz = (t.contiguous() for t in (fz, Lzz, Gz, Hz))
    stage, terminal = multiplier_terms(fz, Hz, Gz, HN, GN, it.lam[:, 1:], it.nu, it.y, it.nuN, it.yN)
    Lz, LNx = lz + stage, lNx + terminal
    return Lz, Lzz, LNx, LNxx, f, fz, g, Gz, h, Hz, gN, GN, hN, HN


def expand(problem: Problem, cons: Constraints, params, it: Iterate, opts: IPOptions,
           base: Optional[Base] = None) -> Model:
    """Everything the iteration needs at ``it``: one pass of ``torch.func`` over the batch, or, given the
    ``base`` expansion of a linear-quadratic problem, the values alone and its derivatives by products."""
    X, U = it.X, it.U
    nx = X.shape[-1]
    if base is None and problem.linear_quadratic:
        Lz, Lzz, LNx, LNxx, f, fz, g, Gz, h, Hz, gN, GN, hN, HN = _linear_quadratic_expansion(problem, cons, params, it)
    elif base is None:
        _, Lz, Lzz, _, LNx, LNxx = problem_lagrangian_expansion(problem, cons, X, U, params, it.lam, it.nu, it.y,
                                                                it.nuN, it.yN)
        f, fz = stage_jacobian(problem.dynamics, X[:, :-1], U, params)
        g, Gz, h, Hz, gN, GN, hN, HN = _constraint_parts(cons, X, U, params, jacobians=True)
    else:
        Lz, Lzz, LNx, LNxx, fz, Gz, Hz, GN, HN = _linear_quadratic_derivatives(it, base)
        f = map_stage(problem.dynamics, X[:, :-1], U, params)
        g, _, h, _, gN, _, hN, _ = _constraint_parts(cons, X, U, params, jacobians=False)
    J = total_cost(problem, X, U, params)
    defects = f - X[:, 1:]
    knots = cons.ineq_knot_mask
    residuals = _flat_abs(defects, h, hN, (g + it.s) * knots, gN + it.sN)
    theta, primal_error = residuals.sum(-1), residuals.amax(-1)
    violation = _flat_abs(defects, h, hN, g.clamp_min(0), gN.clamp_min(0)).amax(-1)
    # Lagrangian gradient: x_k also appears in the dynamics row of stage k-1 (−λ_k); x_0 is fixed
    grad_x = Lz[:, 1:, :nx] - it.lam[:, 1:-1]
    grad_N = LNx - it.lam[:, -1]
    s_max = opts.scaling_threshold
    multipliers = _flat_abs(it.lam, it.nu, it.nuN, it.y, it.yN, it.z, it.zN).sum(-1)
    count = it.lam[0].numel() + it.nu[0].numel() + it.nuN[0].numel() + 2 * (cons.mi * problem.N + cons.miN) + \
        U[0].numel() + X[0].numel()
    s_d = torch.clamp(multipliers / count, min=s_max) / s_max
    slack_grad = (it.y - it.z) * knots  # stationarity in s
    dual_error = _flat_abs(grad_x, Lz[:, :, nx:], grad_N, slack_grad, it.yN - it.zN).amax(-1) / s_d
    if base is None:
        finite = all_finite([Lz, Lzz, LNxx, fz, Gz, Hz, GN, HN, J.unsqueeze(1), theta.unsqueeze(1)])
    else:  # the constant derivatives were checked with the first expansion
        finite = base.model.finite & all_finite([Lz, LNx, J.unsqueeze(1), theta.unsqueeze(1)])
    return Model(J, Lz, Lzz, LNx, LNxx, f, fz, g, Gz, h, Hz, gN, GN, hN, HN, theta, violation, dual_error,
                 primal_error, finite, knots)


def complementarity_error(cons: Constraints, it: Iterate, mu: Tensor, opts: IPOptions) -> Tensor:
    """``‖S z − μ‖∞ / s_c`` ``(B,)`` (IPOPT eq. 5); rows off at a knot do not count."""
    knots = cons.ineq_knot_mask
    m = mu.reshape(-1, 1, 1)
    stage = (it.s * it.z - m) * knots
    terminal = it.sN * it.zN - mu.unsqueeze(-1)
    n = max(cons.mi * cons.problem.N + cons.miN, 1)
    s_max = opts.scaling_threshold
    s_c = torch.clamp(_flat_abs(it.z * knots, it.zN).sum(-1) / n, min=s_max) / s_max
    return _flat_abs(stage, terminal).amax(-1) / s_c


# ------------------------------------------------------------------------------------- Newton step
def _targets(mu: Tensor, target: Optional[tuple]):
    """The complementarity targets ``(stage (B, N|1, mi|1), terminal (B, miN|1))``: ``μ`` on every row, or ``target``."""
    return (mu.reshape(-1, 1, 1), mu.unsqueeze(-1)) if target is None else target


def newton_lqr(model: Model, it: Iterate, mu: Tensor, x0: Tensor, nx: int, target: Optional[tuple] = None):
    """The reduced primal-dual system (FATROP eq. 9) as LQR matrices (without ``δ_w``) and right-hand side
    (:func:`newton_rhs`)."""
    sigma = it.z / it.s  # rows off at a knot: z = 0
    sigmaN = it.zN / it.sN
    H = model.Lzz + model.Gz.transpose(-1, -2) @ (sigma.unsqueeze(-1) * model.Gz)
    HN = model.LNxx + model.GN.transpose(-1, -2) @ (sigmaN.unsqueeze(-1) * model.GN)
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    lqr = LQR.from_blocks(
        model.fz, H, HN,
        C=model.Hz[..., :nx] if me else None, D=model.Hz[..., nx:] if me else None,
        mask=torch.ones_like(model.h) if me else None,
        CN=model.HN if meN else None, maskN=torch.ones_like(model.hN) if meN else None,
    )
    return lqr, newton_rhs(model, it, mu, x0, nx, target)


def newton_rhs(model: Model, it: Iterate, mu: Tensor, x0: Tensor, nx: int, target: Optional[tuple] = None):
    """The right-hand side of the reduced system for the complementarity ``S z = μ`` or, given, ``S z = target``
    row by row (:func:`_targets`)."""
    m, mN = _targets(mu, target)
    barrier = (it.z - it.y + (m + it.z * model.g) / it.s) * model.knots  # zero on rows that are off
    grad = model.Lz + _mv(model.Gz.transpose(-1, -2), barrier)
    grad = torch.cat([grad[..., :nx] - it.lam[:, :-1], grad[..., nx:]], -1)
    barrierN = it.zN - it.yN + (mN + it.zN * model.gN) / it.sN
    gradN = model.LNx - it.lam[:, -1] + _mv(model.GN.transpose(-1, -2), barrierN)
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    return LQRVectors(q=grad[..., :nx], r=grad[..., nx:], qN=gradN, c=model.f - it.X[:, 1:], x0=x0 - it.X[:, 0],
                      e=model.h if me else None, eN=model.hN if meN else None)


@dataclass
class Direction:
    dX: Tensor
    dU: Tensor
    ds: Tensor
    dsN: Tensor
    dz: Tensor
    dzN: Tensor
    dy: Tensor
    dyN: Tensor
    dlam: Tensor
    dnu: Tensor
    dnuN: Tensor
    K: Tensor
    ok: Tensor
    factor: Optional[RiccatiFactor] = None  # kept when asked for (a corrector reuses it)


def direction(lqr: LQR, rhs: LQRVectors, delta: Tensor, model: Model, it: Iterate, mu: Tensor,
              target: Optional[tuple] = None, factor: Optional[RiccatiFactor] = None,
              keep_factor: bool = False) -> Direction:
    """Factorise the system regularised by ``δ_w I`` (``delta (B,)``; or take its ``factor``), solve it and recover
    ``Δs``, ``Δz`` (FATROP eq. 8) for the complementarity ``μ`` or ``target`` (:func:`newton_rhs`)."""
    factor = factorize(lqr, shift=delta) if factor is None else factor
    sol = factor.solve(rhs, multipliers=True)
    dX, dU = sol.dx, sol.du
    dw = torch.cat([dX[:, :-1], dU], -1)
    Gdw = _mv(model.Gz, dw)
    GdwN = _mv(model.GN, dX[:, -1])
    on = model.knots
    m, mN = _targets(mu, target)
    ds = (-(model.g + it.s) - Gdw) * on
    dz = (m + it.z * model.g + it.z * Gdw) / it.s * on
    dsN = -(model.gN + it.sN) - GdwN
    dzN = (mN + it.zN * model.gN + it.zN * GdwN) / it.sN
    dnu = sol.nu if sol.nu is not None else it.nu.new_zeros(it.nu.shape)
    dnuN = sol.nuN if sol.nuN is not None else it.nuN.new_zeros(it.nuN.shape)
    finite = all_finite([dX, dU, sol.costate])
    # the full step takes the multipliers y of g + s = 0 to z + Δz (stationarity in s)
    dy, dyN = (it.z + dz - it.y) * on, it.zN + dzN - it.yN
    return Direction(dX, dU, ds, dsN, dz, dzN, dy, dyN, sol.costate, dnu, dnuN, factor.K, factor.ok & finite,
                     factor if keep_factor else None)


# ------------------------------------------------------------------------------------- line search
def _max_step(value: Tensor, step: Tensor, tau: Tensor) -> Tensor:
    """Largest ``α ≤ 1`` with ``value + α step ≥ (1 − τ) value`` (fraction to boundary), ``(B,)``."""
    ratio = torch.where(step < 0, -tau.unsqueeze(-1) * value / torch.where(step < 0, step, -1.0), 1.0)
    return torch.cat([ratio, ratio.new_ones(ratio.shape[0], 1)], -1).amin(-1)


def _log_barrier(s: Tensor, sN: Tensor, knots: Tensor) -> Tensor:
    """``Σ log s`` over the rows that apply: ``(B, *E)``."""
    stage = torch.where(knots > 0, torch.log(s), 0.0).flatten(-2).sum(-1)
    return stage + torch.log(sN).sum(-1)


def _cost_directional(model: Model, it: Iterate, d: Direction) -> Tensor:
    """``∇J · Δw`` from the Lagrangian gradient, without a further derivative: ``(B,)``."""
    dw = torch.cat([d.dX[:, :-1], d.dU], -1)
    stage = (model.Lz * dw).sum(-1) - (it.lam[:, 1:] * _mv(model.fz, dw)).sum(-1) \
        - (it.nu * _mv(model.Hz, dw)).sum(-1) - (it.y * _mv(model.Gz, dw)).sum(-1)
    dxN = d.dX[:, -1]
    terminal = (model.LNx * dxN).sum(-1) - (it.nuN * _mv(model.HN, dxN)).sum(-1) - (it.yN * _mv(model.GN, dxN)).sum(-1)
    return stage.sum(-1) + terminal


@dataclass
class Filter:
    """Per-instance filter: ``entries (B, F, 2)`` of ``(θ, φ)`` (``+inf`` where empty) and the next slot."""

    entries: Tensor
    slot: Tensor

    @classmethod
    def empty(cls, batch: int, size: int, like: Tensor) -> "Filter":
        return cls(like.new_full((batch, size, 2), float("inf")), torch.zeros(batch, dtype=torch.long, device=like.device))

    def reset(self, mask: Tensor) -> "Filter":
        return Filter(torch.where(mask.reshape(-1, 1, 1), float("inf"), self.entries), torch.where(mask, 0, self.slot))

    def acceptable(self, theta: Tensor, phi: Tensor) -> Tensor:
        """Candidates ``(B, L)`` not dominated by an entry."""
        t, p = self.entries[..., 0].unsqueeze(1), self.entries[..., 1].unsqueeze(1)
        return ((theta.unsqueeze(-1) < t) | (phi.unsqueeze(-1) < p)).all(-1)

    def add(self, mask: Tensor, theta: Tensor, phi: Tensor) -> "Filter":
        size = self.entries.shape[1]
        slot = torch.nn.functional.one_hot(self.slot % size, size).to(torch.bool) & mask.unsqueeze(-1)
        entry = torch.stack([theta, phi], -1).unsqueeze(1)
        return Filter(torch.where(slot.unsqueeze(-1), entry, self.entries), self.slot + mask.long())


def _step_and_round_off(it: Iterate, d: Direction) -> tuple:
    """``(|Δw|∞, 10 ε (1 + |w|∞))``, ``(B,)`` each, of the primal step ``Δw = (ΔX, ΔU)``: a step below the second
    is at round-off (IPOPT's tiny step)."""
    scale = 1.0 + torch.cat([it.X.flatten(1), it.U.flatten(1)], -1).abs().amax(-1)
    size = torch.cat([d.dX.flatten(1), d.dU.flatten(1)], -1).abs().amax(-1)
    return size, 10 * torch.finfo(it.X.dtype).eps * scale


def fraction_to_boundary(it: Iterate, d: Direction, tau: Tensor) -> tuple:
    """The largest primal and dual steps ``(B,)`` that keep ``s`` and ``z`` at least ``1 − τ`` of their distance to zero."""
    a_max = _max_step(torch.cat([it.s.flatten(1), it.sN], -1), torch.cat([d.ds.flatten(1), d.dsN], -1), tau)
    a_dual = _max_step(torch.cat([it.z.flatten(1), it.zN], -1), torch.cat([d.dz.flatten(1), d.dzN], -1), tau)
    return a_max, a_dual


def step_measures(model: Model, it: Iterate, d: Direction, mu: Tensor, opts: IPOptions):
    """At the current iterate, for the line search (``(B,)`` each): the largest primal and dual steps of the
    fraction-to-boundary rule, ``τ = max(τ_min, 1 − μ)``, the barrier objective ``φ`` and its slope ``∇φ · Δ``."""
    a_max, a_dual = fraction_to_boundary(it, d, torch.clamp(1.0 - mu, min=opts.fraction_to_boundary))
    knots = model.knots
    phi = model.J - mu * _log_barrier(it.s, it.sN, knots)
    barrier_slope = torch.where(knots > 0, d.ds / it.s, 0.0).flatten(1).sum(-1) + (d.dsN / it.sN).sum(-1)
    slope = _cost_directional(model, it, d) - mu * barrier_slope
    return a_max, a_dual, phi, slope


def trial(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model, mu: Tensor,
          phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor, alphas: Tensor,
          opts: IPOptions):
    """The filter tests (module docstring) at the step sizes ``alphas (B, l)``, all evaluated at once, from the
    current barrier objective ``phi`` and its slope ``slope`` (:func:`step_measures`).

    Returns ``accept (B, l)`` and ``f_type (B, l)``: the step is an f-type step that met the Armijo condition
    (no filter entry is added for those)."""
    B, L = alphas.shape
    knots = model.knots
    a4 = alphas.reshape(B, L, 1, 1)
    Xc = it.X.unsqueeze(1) + a4 * d.dX.unsqueeze(1)
    Uc = it.U.unsqueeze(1) + a4 * d.dU.unsqueeze(1)
    sc = it.s.unsqueeze(1) + a4 * d.ds.unsqueeze(1)
    sNc = it.sN.unsqueeze(1) + alphas.unsqueeze(-1) * d.dsN.unsqueeze(1)
    Jc = total_cost(problem, Xc, Uc, params)
    defects = map_stage(problem.dynamics, Xc[..., :-1, :], Uc, params) - Xc[..., 1:, :]
    g, _, h, _, gN, _, hN, _ = _constraint_parts(cons, Xc, Uc, params, jacobians=False)
    parts = (defects, h, hN, (g + sc) * knots, gN + sNc)
    theta_c = torch.cat([p.reshape(B, L, -1).abs() for p in parts], -1).sum(-1)
    phi_c = Jc - mu.unsqueeze(1) * _log_barrier(sc, sNc, knots)
    theta, phi, slope = model.theta.unsqueeze(1), phi.unsqueeze(1), slope.unsqueeze(1)
    switching = (slope < 0) & (alphas * (-slope).clamp_min(0) ** opts.switching_phi_power
                               > opts.switching * theta ** opts.switching_theta_power)
    f_type = switching & (theta <= theta_min.unsqueeze(1))
    armijo = phi_c <= phi + opts.armijo * alphas * slope
    decrease = (theta_c <= (1.0 - opts.filter_theta) * theta) | (phi_c <= phi - opts.filter_phi * theta)
    finite = torch.isfinite(theta_c) & torch.isfinite(phi_c)
    accept = finite & (theta_c <= theta_max.unsqueeze(1)) & filt.acceptable(theta_c, phi_c) \
        & torch.where(f_type, armijo, decrease)
    return accept, f_type & armijo


def advance(it: Iterate, d: Direction, alpha: Tensor, a_dual: Tensor, mu: Tensor, knots: Tensor,
            opts: IPOptions) -> Iterate:
    """The iterate after primal step ``alpha (B,)`` and dual step ``a_dual (B,)``, with the multipliers ``z``
    kept within ``[μ/(κ_Σ s), κ_Σ μ/s]``."""
    B = alpha.shape[0]
    a = alpha.reshape(B, 1, 1)
    s = it.s + a * d.ds
    sN = it.sN + alpha.unsqueeze(-1) * d.dsN
    z = it.z + a_dual.reshape(B, 1, 1) * d.dz
    zN = it.zN + a_dual.unsqueeze(-1) * d.dzN
    kappa, m3, mN = opts.dual_safeguard, mu.reshape(B, 1, 1), mu.unsqueeze(-1)
    z = torch.maximum(torch.minimum(z, kappa * m3 / s), m3 / (kappa * s)) * knots
    zN = torch.maximum(torch.minimum(zN, kappa * mN / sN), mN / (kappa * sN))
    return Iterate(X=it.X + a * d.dX, U=it.U + a * d.dU, s=s, sN=sN, z=z, zN=zN, y=it.y + a * d.dy,
                   yN=it.yN + alpha.unsqueeze(-1) * d.dyN, lam=it.lam + a * d.dlam, nu=it.nu + a * d.dnu,
                   nuN=it.nuN + alpha.unsqueeze(-1) * d.dnuN)


@dataclass
class Step:
    it: Iterate
    alpha: Tensor
    found: Tensor
    filter: Filter


def line_search(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model, mu: Tensor,
                filt: Filter, theta_max: Tensor, theta_min: Tensor, pending: Tensor, opts: IPOptions) -> Step:
    """Backtracking over ``α_max β^j``, ``line_search_parallel`` step sizes per batched evaluation; a further
    round only while a ``pending`` instance has found no acceptable step."""
    B, L = it.X.shape[0], opts.line_search_steps
    a_max, a_dual, phi, slope = _kernel(step_measures, opts, it.X.device)(model, it, d, mu, opts)
    size, round_off = _step_and_round_off(it, d)
    tiny = size < round_off  # IPOPT's tiny step: taken whole, no filter entry
    powers = opts.line_search_decrease ** torch.arange(L, dtype=it.X.dtype, device=it.X.device)
    rows = torch.arange(B, device=it.X.device)
    found, alpha, f_type = tiny, torch.where(tiny, a_max, 0.0), tiny
    per_round = max(1, opts.line_search_parallel)
    for start in range(0, L, per_round):
        if not bool((pending & ~found).any()):
            break
        alphas = a_max.unsqueeze(1) * powers[start:start + per_round]
        accept, f_ok = _kernel(trial, opts, it.X.device)(problem, cons, params, it, d, model, mu, phi, slope, filt, theta_max,
                                               theta_min, alphas, opts)
        idx = first_true(accept)
        new = accept.any(1) & ~found
        alpha = torch.where(new, alphas[rows, idx], alpha)
        f_type = torch.where(new, f_ok[rows, idx], f_type)
        found = found | new
    filt = filt.add(found & ~f_type, (1.0 - opts.filter_theta) * model.theta, phi - opts.filter_phi * model.theta)
    new_it = _kernel(advance, opts, it.X.device)(it, d, alpha, a_dual, mu, model.knots, opts)
    return Step(new_it, alpha, found, filt)


# ------------------------------------------------------------------------------------------ solver
def _kernel(fn, opts: IPOptions, device: torch.device):
    """``fn`` compiled (``opts.compile``), replayed from CUDA graphs (:func:`~torchtraj.core.graphs.graphs_used`), or
    itself."""
    if graphs_used(opts, device):
        return graphed(fn)
    return kernel(fn, opts.compile)


def initial_iterate(cons: Constraints, params, X: Tensor, U: Tensor, opts: IPOptions) -> Iterate:
    """Slacks ``max(−g, κ_1)`` (IPOPT's bound push for ``s ≥ 0``), ``z = dual_initial``, zero ``λ``, ``ν``."""
    B, N, nx = X.shape[0], U.shape[1], X.shape[-1]
    g, _, _, _, gN, _, _, _ = _constraint_parts(cons, X, U, params, jacobians=False)
    knots = cons.ineq_knot_mask
    s = torch.where(knots > 0, torch.clamp(-g, min=opts.bound_push), 1.0)
    sN = torch.clamp(-gN, min=opts.bound_push)
    z = opts.dual_initial * knots.expand_as(s)
    zN = torch.full_like(sN, opts.dual_initial)
    return Iterate(X, U, s, sN, z.clone(), zN, torch.zeros_like(s), torch.zeros_like(sN), X.new_zeros(B, N + 1, nx),
                   X.new_zeros(B, N, cons.me), X.new_zeros(B, cons.meN))


def _next_regularization(delta: Tensor, last: Tensor, opts: IPOptions) -> Tensor:
    """IPOPT's inertia-correction rule for the next attempt after a failed factorisation with ``delta``."""
    first = torch.where(last == 0, torch.full_like(delta, opts.regularization_first),
                        torch.clamp(opts.regularization_decrease * last, min=opts.regularization_min))
    grow = torch.where(last == 0, opts.regularization_increase_first, opts.regularization_increase) * delta
    return torch.where(delta == 0, first, grow)


def _barrier_update(cons: Constraints, model: Model, it: Iterate, mu: Tensor, running: Tensor, filt: Filter,
                    tol: float, opts: IPOptions):
    """Monotone barrier update, repeated while the barrier problem is already solved; resets the filter."""
    floor = tol / 10.0
    for _ in range(4):
        error = torch.maximum(torch.maximum(model.dual_error, model.primal_error),
                              complementarity_error(cons, it, mu, opts))
        update = running & (error <= opts.barrier_tolerance_factor * mu) & (mu > floor)
        smaller = torch.clamp(torch.minimum(opts.barrier_decrease * mu, mu ** opts.barrier_power), min=floor)
        mu = torch.where(update, smaller, mu)
        filt = filt.reset(update)
    return mu, filt


def kkt_error(cons: Constraints, model: Model, it: Iterate, opts: IPOptions) -> Tensor:
    """The convergence measure ``E_0`` ``(B,)``: the largest of the scaled dual, primal and complementarity errors."""
    zero = it.s.new_zeros(it.s.shape[0])
    return torch.maximum(torch.maximum(model.dual_error, model.primal_error), complementarity_error(cons, it, zero, opts))


def _cross_over(problem: Problem, cons: Constraints, params, model: Model, it: Iterate, x0: Tensor, base: Base,
                opts: IPOptions, tol: float, error: Tensor, K: Tensor, trying: Tensor, rounds: int,
                start: bool = False) -> tuple:
    """The crossover (:mod:`torchtraj.solvers.ipm.crossover`) of the instances ``trying``, gathered: up to ``rounds`` active
    sets, the first proposed by the iterate (``start``: none held, the unconstrained optimum), each next one the
    primal-dual active-set update of the last candidate. An instance's rounds end where its set stops changing (the
    candidate is then the KKT point of its set), where its system fails, or with the last round; the candidates
    they end with are then checked together, and accepted where they pass the convergence test ``E_0 ≤ tol``.
    Returns ``(iterate, model, E_0, gains K, rounds (B,))``: the accepted candidates' values, the given ones
    elsewhere, and the rounds each instance took part in, negative where none was accepted."""
    if graphs_used(opts, x0.device) and not cons.back_propagated:
        return _cross_over_masked(problem, cons, params, model, it, x0, base, opts, tol, error, K, trying, rounds,
                                  start)
    B = trying.shape[0]
    index = trying.nonzero().squeeze(-1)  # the rows still tried
    whole = index.numel() == B
    sub_model, sub_it = (model, it) if whole else (_rows(model, index), _rows(it, index))
    sub_x0 = x0 if whole else x0[index]
    knots = model.knots
    active = crossover.first_active_set(sub_it, knots, start)
    taken = torch.zeros(B, dtype=torch.long, device=index.device)
    ended = []  # per round: the rows it ended, their candidates' iterates, gains and factorisations' success
    for r in range(rounds):
        c = crossover.candidate(sub_model, cons, sub_it, sub_x0, active)
        taken = taken.index_add(0, index, torch.ones_like(index))
        following = crossover.next_active_set(c, active, knots)
        going = c.ok & crossover.changed(active, following)
        if r == rounds - 1:
            going = torch.zeros_like(going)
        rows = (~going).nonzero().squeeze(-1)
        ended.append((index[rows], _rows(c.point, rows), c.K[rows], c.ok[rows]))
        on = going.nonzero().squeeze(-1)
        if on.numel() == 0:
            break
        index, sub_model, sub_it, sub_x0 = index[on], _rows(sub_model, on), _rows(sub_it, on), sub_x0[on]
        active = tuple(a[on] for a in following)
    done = torch.cat([e[0] for e in ended])
    new = Iterate(**{f.name: torch.cat([getattr(e[1], f.name) for e in ended]) for f in fields(Iterate)})
    # one expansion checks them all (eager: the gathered batch changes from call to call)
    new_model = expand(problem, cons, param_rows(params, done), new, opts, None if base is None else _rows(base, done))
    new_error = kkt_error(cons, new_model, new, opts)
    accept = torch.cat([e[3] for e in ended]) & new_model.finite & (new_error <= tol)
    rows = accept.nonzero().squeeze(-1)
    done, new = done[rows], _rows(new, rows)
    it = Iterate(**{f.name: getattr(it, f.name).index_copy(0, done, getattr(new, f.name)) for f in fields(Iterate)})
    values = {name: getattr(model, name).index_copy(0, done, getattr(new_model, name)[rows]) for name in _VALUE_FIELDS}
    accepted = torch.zeros_like(trying).index_fill(0, done, True)
    return (it, dataclasses.replace(model, **values), error.index_copy(0, done, new_error[rows]),
            K.index_copy(0, done, torch.cat([e[2] for e in ended])[rows]), torch.where(accepted, taken, -taken))


def _cross_over_masked(problem: Problem, cons: Constraints, params, model: Model, it: Iterate, x0: Tensor,
                       base: Base, opts: IPOptions, tol: float, error: Tensor, K: Tensor, trying: Tensor, rounds: int,
                       start: bool) -> tuple:
    """:func:`_cross_over` on the whole batch, for CUDA graphs: the rows not tried, or whose rounds have ended, are
    masked instead of gathered, so that every round's candidate, and the expansion that checks them, keep the
    batch's shapes and replay one graph each. Each row keeps the candidate its rounds ended with. Where the held
    rows are control bounds alone (general rows take the core's SVD, which cannot be captured)."""
    knots = model.knots
    active = crossover.first_active_set(it, knots, start)
    candidate = _kernel(crossover.candidate, opts, x0.device)
    going, taken, ended = trying, torch.zeros_like(trying, dtype=torch.long), None
    for r in range(rounds):
        c = candidate(model, cons, it, x0, active)
        ended = c if ended is None else crossover.Candidate(
            point=_pick(going, c.point, ended.point), K=where_rows(going, c.K, ended.K), ok=torch.where(going, c.ok, ended.ok))
        taken = taken + going.long()
        following = crossover.next_active_set(c, active, knots)
        going = going & c.ok & crossover.changed(active, following)
        if r == rounds - 1 or not bool(going.any()):
            break
        active = following  # the rows no longer going ignore theirs
    new_model = _kernel(expand, opts, x0.device)(problem, cons, params, ended.point, opts, base)
    new_error = kkt_error(cons, new_model, ended.point, opts)
    accept = trying & ended.ok & new_model.finite & (new_error <= tol)
    values = {name: where_rows(accept, getattr(new_model, name), getattr(model, name)) for name in _VALUE_FIELDS}
    return (_pick(accept, ended.point, it), dataclasses.replace(model, **values), torch.where(accept, new_error, error),
            where_rows(accept, ended.K, K), torch.where(accept, taken, -taken))


#: The fields of a linear-quadratic problem's :class:`Model` that change from point to point (its Jacobians and
#: Hessians are the problem's constants).
_VALUE_FIELDS = ("J", "Lz", "LNx", "f", "g", "h", "gN", "hN", "theta", "violation", "dual_error", "primal_error",
                 "finite")


def _complementarity(s: Tensor, sN: Tensor, z: Tensor, zN: Tensor, knots: Tensor) -> Tensor:
    """The average ``sᵀz`` over the rows that apply, ``(B,)`` (zero without inequality rows)."""
    count = (knots.sum() + sN.shape[-1]).clamp_min(1)
    return ((s * z * knots).flatten(1).sum(-1) + (sN * zN).sum(-1)) / count


def mehrotra_step(model: Model, it: Iterate, predictor: Direction, lqr: LQR, delta: Tensor, x0: Tensor,
                  floor: float, ceiling: Tensor, filt: Filter, factored: Tensor, opts: IPOptions) -> tuple:
    """Mehrotra's probing barrier parameter and corrector step (IPOPT's ``mehrotra_algorithm``), from the
    affine-scaling ``predictor`` (the step for ``S z = 0``) and its factorisation: ``μ = σ μ̄``,
    ``σ = min((μ_aff / μ̄)³, σ_max)`` with the average complementarity ``μ̄`` now and ``μ_aff`` after the largest
    predictor steps to the boundary, kept within ``[floor, ceiling (B,)]``; then the step for
    ``S z = μ − ΔS_aff Δz_aff``, taken whole to the fraction-to-boundary limits (no line search). A step that the
    boundary cuts to round-off is not found, as after a failed line search. Returns ``(μ (B,), direction, step)``."""
    knots = model.knots
    a_p, a_d = fraction_to_boundary(it, predictor, torch.ones_like(delta))
    ap, ad = a_p.reshape(-1, 1, 1), a_d.reshape(-1, 1, 1)
    average = _complementarity(it.s, it.sN, it.z, it.zN, knots)
    affine = _complementarity(it.s + ap * predictor.ds, it.sN + a_p.unsqueeze(-1) * predictor.dsN,
                              it.z + ad * predictor.dz, it.zN + a_d.unsqueeze(-1) * predictor.dzN, knots)
    sigma = torch.clamp((affine / torch.where(average > 0, average, 1.0)) ** 3, max=opts.mehrotra_sigma_max)
    mu = torch.maximum(torch.minimum(sigma * average, ceiling), torch.full_like(ceiling, floor))
    target = (mu.reshape(-1, 1, 1) - predictor.ds * predictor.dz, mu.unsqueeze(-1) - predictor.dsN * predictor.dzN)
    rhs = newton_rhs(model, it, mu, x0, it.X.shape[-1], target)
    factor = predictor.factor if predictor.factor is not None else factorize(lqr, shift=delta)
    d = direction(lqr, rhs, delta, model, it, mu, target, factor=factor)
    a_max, a_dual = fraction_to_boundary(it, d, torch.clamp(1.0 - mu, min=opts.fraction_to_boundary))
    size, round_off = _step_and_round_off(it, d)
    stalled = (a_max * size <= round_off) & (size > round_off)
    found = factored & d.ok & ~stalled
    return mu, d, Step(advance(it, d, a_max, a_dual, mu, knots, opts), a_max, found, filt)


def _rows(value, index: Tensor):
    """The rows ``index`` of a batch-first tensor or dataclass (:class:`Model`'s ``knots`` is per stage)."""
    if isinstance(value, Tensor):
        return value[index]
    return type(value)(**{f.name: getattr(value, f.name) if f.name == "knots" else _rows(getattr(value, f.name), index)
                          for f in fields(value)})


@dataclass
class _Final:
    """What the solution reports of every instance of the full batch, written back as instances leave the
    iterated set (``IPOptions.compact_below``) and at the end."""

    X: Tensor
    U: Tensor
    lam: Tensor
    z: Tensor
    zN: Tensor
    nu: Tensor
    nuN: Tensor
    J: Tensor
    violation: Tensor
    status: Tensor
    iterations: Tensor
    K: Tensor

    @classmethod
    def of(cls, it: Iterate, model: Model, status: Tensor, iterations: Tensor, K: Tensor) -> "_Final":
        return cls(X=it.X, U=it.U, lam=it.lam, z=it.z, zN=it.zN, nu=it.nu, nuN=it.nuN, J=model.J,
                   violation=model.violation, status=status, iterations=iterations, K=K)

    def write(self, index: Tensor, rows: "_Final") -> "_Final":
        """Overwrite the rows ``index`` with ``rows`` (in place: the buffers are this object's own copies)."""
        for f in fields(self):
            getattr(self, f.name)[index] = getattr(rows, f.name)
        return self


def _history_row(model: Model, step_size: Tensor, regularization: Tensor, mu: Tensor, error: Tensor) -> dict:
    """One iteration's entry of the history, ``(B,)`` each."""
    return {"cost": model.J, "max_violation": model.violation, "step_size": step_size,
            "regularization": regularization, "barrier": mu, "kkt_error": error}


def _full_history(rows: list) -> History:
    """The history of the full batch from records ``(index, values, iteration)`` of the iterated rows ``index``
    (``None``: all): an iteration's row, or (``iteration`` false) the values that the instances about to leave
    the iterated set repeat from then on, with step size 0."""
    full, previous = [], None
    for index, row, iteration in rows:
        if index is not None:
            row = {k: (torch.zeros_like(v) if k == "step_size" else v.clone()).index_copy_(0, index, row[k])
                   for k, v in previous.items()}
        if iteration:
            full.append(row)
        previous = row
    return History.from_rows(full)


def solve_interior_point(problem: Problem, x0: Tensor, U0: Tensor, params, options: Optional[IPOptions] = None,
                         X0: Optional[Tensor] = None, method: str = "ipm") -> Solution:
    """Solve ``problem`` from ``x0 (B, nx)``, controls ``U0 (B, N, nu)`` and, optionally, states ``X0 (B, N+1, nx)``
    (any guess: multiple shooting starts from defects; without it the controls are rolled out)."""
    opts = options or IPOptions()
    B, N, nx = x0.shape[0], problem.N, problem.nx
    cons = Constraints(problem)
    tol = opts.tolerance_for(x0.dtype)
    if X0 is None:
        X = kernel(rollout, opts.compile)(problem.dynamics, x0, U0, params)
    else:
        X = torch.cat([x0.unsqueeze(1), X0[:, 1:]], 1)
    it = initial_iterate(cons, params, X, U0, opts)
    expand_k = _kernel(expand, opts, x0.device)
    direction_k = _kernel(direction, opts, x0.device)
    mu = torch.full((B,), opts.barrier_initial, dtype=x0.dtype, device=x0.device)
    status = torch.full((B,), int(Status.RUNNING), dtype=torch.long, device=x0.device)
    start_ok = torch.isfinite(X).flatten(1).all(-1) & torch.isfinite(U0).flatten(1).all(-1)
    status = torch.where(~torch.isfinite(x0).all(-1), int(Status.NON_FINITE), status)
    status = torch.where((status == Status.RUNNING) & ~start_ok, int(Status.INFEASIBLE_START), status)
    filt = Filter.empty(B, opts.filter_size, x0)
    last = torch.zeros_like(mu)  # last nonzero δ_w that gave a positive definite system
    floor = torch.zeros_like(mu)  # smallest δ_w of the next attempt (raised after a failed line search)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    K = x0.new_zeros(B, N, problem.nu, nx)
    rows = []
    theta_max = theta_min = None
    base = None
    compacting = opts.compact_below > 0 and not opts.compile and not graphs_used(opts, x0.device)
    mehrotra = opts.barrier_strategy == "mehrotra"
    crossing = opts.crossover and problem.linear_quadratic and cons.mi + cons.miN > 0
    # from the unconstrained optimum only where every row is a control bound: with state rows the active-set
    # updates can go round in circles (the oscillator of the tests: eight sets without settling)
    starting = crossing and opts.crossover_start_rounds > 0 and cons.bound_rows() is not None
    # IPOPT's mu_max: its factor times the initial average complementarity
    ceiling = opts.mehrotra_mu_max_factor * _complementarity(it.s, it.sN, it.z, it.zN, cons.ineq_knot_mask)
    index, final = None, None  # the rows of the full batch being iterated (None: all), and the others' results
    for step in range(opts.iterations + 1):
        model = expand_k(problem, cons, params, it, opts, base)
        if problem.linear_quadratic and base is None:  # the initial iterate's multipliers are zero
            base = Base(it.X, it.U, model)
        if theta_max is None:
            theta_0 = torch.clamp(torch.nan_to_num(model.theta, nan=1.0, posinf=1.0), min=1.0)
            theta_max, theta_min = opts.theta_max_factor * theta_0, opts.theta_min_factor * theta_0
        running = status == Status.RUNNING
        error = kkt_error(cons, model, it, opts)
        status = torch.where(running & ~model.finite, int(Status.NON_FINITE), status)
        status = torch.where(running & model.finite & (error <= tol), int(Status.CONVERGED), status)
        diverged = running & (it.X.abs().flatten(1).amax(-1) > opts.max_state)
        status = torch.where(diverged & (status == Status.RUNNING), int(Status.DIVERGED), status)
        running = status == Status.RUNNING
        start = starting and step == 0
        rounds = opts.crossover_start_rounds if start else opts.crossover_rounds
        trying = running & ((error <= opts.crossover_from) | start) if crossing and rounds > 0 else None
        if trying is not None and bool(trying.any()):
            it, model, error, K, taken = _cross_over(problem, cons, params, model, it, x0, base, opts, tol, error, K,
                                                     trying, rounds, start)
            status = torch.where(taken > 0, int(Status.CONVERGED), status)
            iterations = iterations + taken.abs()  # each round solves a Newton system, as an iteration
            running = status == Status.RUNNING
        count = int(running.sum())
        if step == opts.iterations or count == 0:
            break
        if compacting and count <= opts.compact_below * running.shape[0]:
            # the finished instances' results are final: iterate on the running ones alone
            now = _Final.of(it, model, status, iterations, K)
            final = _rows(now, torch.arange(running.shape[0], device=x0.device)) if final is None \
                else final.write(index, now)  # the first: copies of the full batch's
            # what the history repeats for the instances that leave (its values at their final iterate)
            rows.append((index, _history_row(model, torch.zeros_like(mu), floor, mu, error), False))
            keep = running.nonzero().squeeze(-1)
            index = keep if index is None else index[keep]
            it, model, filt, base = _rows(it, keep), _rows(model, keep), _rows(filt, keep), \
                None if base is None else _rows(base, keep)
            mu, status, last, floor, iterations, K, theta_max, theta_min, x0, error, running, ceiling = (
                v[keep] for v in (mu, status, last, floor, iterations, K, theta_max, theta_min, x0, error, running,
                                  ceiling))
            params = param_rows(params, keep)
        if mehrotra:  # the affine-scaling predictor: complementarity S z = 0
            target_mu = torch.zeros_like(mu)
        else:
            mu, filt = _barrier_update(cons, model, it, mu, running, filt, tol, opts)
            target_mu = mu
        lqr, rhs = newton_lqr(model, it, target_mu, x0, nx)

        def attempt(delta):  # Mehrotra runs eager, keeping the factorisation for its corrector (kernels: no kwargs)
            if mehrotra:
                return direction(lqr, rhs, delta, model, it, target_mu, keep_factor=True)
            return direction_k(lqr, rhs, delta, model, it, target_mu)

        delta = floor
        d = attempt(delta)
        pending = running & ~d.ok
        for _ in range(opts.regularization_attempts):
            if not bool(pending.any()):
                break
            delta = torch.where(pending, _next_regularization(delta, last, opts), delta)
            pending = pending & (delta <= opts.regularization_max)
            d = _pick(pending, attempt(delta), d)
            pending = pending & ~d.ok
        factored = running & d.ok
        if mehrotra:  # no line search: the corrector's largest steps to the boundary
            mu, d, ls = mehrotra_step(model, it, d, lqr, delta, x0, tol / 10.0, ceiling, filt, factored, opts)
            factored = factored & d.ok
        else:
            ls = line_search(problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, factored, opts)
        take = factored & ls.found
        it = _pick(take, ls.it, it)
        filt = _pick(take, ls.filter, filt)
        K = where_rows(take, d.K, K)
        last = torch.where(take & (delta > 0), delta, last)
        missed = factored & ~ls.found
        floor = torch.where(missed, torch.clamp(opts.regularization_increase * torch.maximum(floor, delta),
                                                min=opts.regularization_first), torch.where(take, 0.0, floor))
        blown = running & (~d.ok | (floor > opts.regularization_max))
        status = torch.where(blown, int(Status.MAX_REGULARIZATION), status)
        iterations = iterations + running.long()
        rows.append((index, _history_row(model, torch.where(take, ls.alpha, 0.0), delta, mu, error), True))
        if opts.verbose:
            logger.info("%s %4d  cost %.10g..%.10g  kkt %.2e  mu %.1e  running %d", method, step,
                        model.J.min().item(), model.J.max().item(), error.max().item(), mu.max().item(),
                        running.sum().item())
    status = torch.where(status == Status.RUNNING, int(Status.MAX_ITERATIONS), status)
    out = _Final.of(it, model, status, iterations, K)
    out = out if final is None else final.write(index, out)
    knots = cons.ineq_knot_mask
    multipliers = multiplier_blocks(cons, torch.cat([out.z * knots, out.nu], -1), torch.cat([out.zN, out.nuN], -1))
    return Solution(
        X=out.X, U=out.U, K=out.K, cost=out.J, max_violation=out.violation, status=out.status,
        iterations=out.iterations, history=_full_history(rows), costate=out.lam, multipliers=multipliers,
        method=method,
    )
