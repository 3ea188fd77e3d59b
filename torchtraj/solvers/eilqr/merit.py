r"""Globalisation of eILQR (Horizon §II-F): backtracking on the exact ℓ1 merit function, batched.

The merit (Horizon eq. 8; Nocedal & Wright 2006 §15.4) of a multiple-shooting point ``w = (X, U)`` is

.. math::

    m(w) = J(w) + γ \|C(w)\|_1,\qquad
    \|C\|_1 = \sum_k \|f(x_k, u_k) − x_{k+1}\|_1 + \sum_k \|h_k\|_1 + \|h_N\|_1 + \|c_0\|_1,

``J`` the barrier-augmented cost (the cost and ``Σ w β(−g)``, :mod:`~torchtraj.solvers.eilqr.continuation`) and ``c_0``
the initial rows (``x̄_0 − x_0``, or ``h_0(x_0)`` and the fixed components of a free start). It is exact where ``γ``
exceeds every multiplier (eq. 9), so :func:`penalty` sets ``γ = κ max|y⁺| + γ_0`` from the Newton step's own estimates
``y⁺`` (``κ = merit_factor`` the margin, ``γ_0 = merit_floor``; with ``merit_monotone`` never lowered).
Along a step ``p`` that satisfies the linearised constraints (``C + ∇C p = 0``) the directional derivative is

.. math::  D m(w; p) = ∇J^T p − γ \|C\|_1 \ \le\ −p^T (∇^2 L + εI) p − (γ − \|y^+\|_∞) \|C\|_1 < 0

(Nocedal & Wright Thm. 18.2), and the step sizes ``α = β^j`` are tried until Armijo's
``m(w + α p) ≤ m(w) + η α D m`` holds. Every trial point of every instance is evaluated in one batched call per round
of ``per_round`` step sizes (:func:`torchtraj.globalization.line_search.backtrack`): the dynamics, the costs and the
rows at all knots at once, no rollout. A tolerance of a few hundred rounding errors of ``m`` lets the full step
through once the decrease is below round-off, where the Newton iteration converges quadratically.

**Nonmonotone reference** (Grippo, Lampariello & Lucidi 1986, "A nonmonotone line search technique for Newton's
method", SIAM J. Numer. Anal. 23(4), with their memory ``M = 10``; Panier & Tits 1991 use such a test against the
Maratos effect of the ℓ1 merit; Nocedal & Wright 2006 §15.5, the nonmonotone strategy). The Armijo test compares the
trial merit with the largest merit of the last ``M`` iterates instead of the current one,

.. math::  m(w + α p) \le \max_{0 \le j < M} m_γ(w_{k−j}) + η α D m,\qquad m_γ(w_j) = J(w_j) + γ \|C(w_j)\|_1,

the past points' merits taken with the current ``γ`` (:class:`MeritMemory` keeps their ``J`` and ``‖C‖₁``; the
memory is emptied where the barrier's weight changes, which changes ``J``). Why: the ℓ1 merit charges a step's
second-order defects at ``γ ≥ max|y|`` on every row, while the Lagrangian's Hessian weighs them by each row's own
multiplier, so along directions where the reduced Hessian is small or indefinite the merit refuses steps that the
Newton model and the Lagrangian accept (the Maratos effect). On the cart-pole's ``sample_x0`` starts (issue 23) the
monotone test cut such steps to ``α = 1/16`` for hundreds of iterations along valleys of negative curvature (the
defects, reduced by ``α`` of their value a step, stayed at ``1e-4`` to ``1e-3``), and near some optima refused
Newton steps of ``|δu| = 1e-3`` whose defects' ℓ1 norm rose from ``2e-10`` to about ``1e-6``, with the KKT error at
``6e-8``. Letting the merit rise over a few iterations lets the full steps through; the following Newton steps
remove the defects, and the reference values never increase.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state, param_rows, rows_of
from ...core.compiled import kernel
from ...core.constraints import Constraints
from ...core.one_pass import problem_values
from ...core.problem import Problem
from ...globalization.line_search import Accepted, backtrack
from .continuation import Weights, barrier_cost
from .initial_state import InitialState
from .model import Model
from .newton import Direction, multiplier_size
from .options import EILQROptions


@dataclass
class MeritMemory:
    """The cost ``J (B, M)`` and infeasibility ``‖C‖₁ (B, M)`` of each instance's last ``M`` iterates, oldest first
    (``J = −∞`` where empty): the nonmonotone reference (module docstring)."""

    J: Tensor
    l1: Tensor

    @classmethod
    def empty(cls, batch: int, memory: int, like: Tensor) -> "MeritMemory":
        return cls(like.new_full((batch, max(memory, 1)), float("-inf")), like.new_zeros(batch, max(memory, 1)))

    def record(self, J: Tensor, l1: Tensor) -> "MeritMemory":
        """The memory with the current iterates' ``J``, ``‖C‖₁`` (``(B,)`` each) in place of the oldest (a shift:
        no slot counter, which a compiled kernel would take as a constant)."""
        return MeritMemory(torch.cat([self.J[:, 1:], J.unsqueeze(-1)], -1),
                           torch.cat([self.l1[:, 1:], l1.unsqueeze(-1)], -1))

    def forget(self, mask: Tensor) -> "MeritMemory":
        """The memory emptied for the instances of ``mask (B,)`` (their barrier's weight changed)."""
        return MeritMemory(torch.where(mask.unsqueeze(-1), float("-inf"), self.J), self.l1)

    def reference(self, gamma: Tensor) -> Tensor:
        """``max_j J_j + γ ‖C_j‖₁ (B,)`` over the remembered iterates, with the current ``gamma (B,)``."""
        return (self.J + gamma.unsqueeze(-1) * self.l1).amax(-1)


def weighed(d: Direction, gamma: Tensor, factored: Tensor, free: bool, J: Tensor, l1: Tensor, memory: MeritMemory,
            opts: EILQROptions) -> tuple:
    """The merit's weight after the step ``d``: ``(γ, memory, m(w), reference)``, ``γ`` from ``d``'s multipliers
    where ``factored (B,)`` (:func:`penalty`; ``free``: the start is a variable), the memory with the iterate's
    ``J`` and ``‖C‖₁ = l1`` (``(B,)`` each), the merit ``J + γ ‖C‖₁`` and the Armijo test's nonmonotone reference."""
    gamma = torch.where(factored, penalty(gamma, multiplier_size(d, free), opts), gamma)
    memory = memory.record(J, l1)
    return gamma, memory, J + gamma * l1, memory.reference(gamma)


def constraint_values(problem: Problem, cons: Constraints, params, X: Tensor, U: Tensor, x0: Tensor,
                      initial: Optional[InitialState]) -> tuple:
    """The constraints at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``: defects ``(B, *E, N, nx)``, ``h`` (or
    ``None``), ``h_N`` (or ``None``) and the initial rows ``c_0 (B, *E, m_0)``."""
    defects = map_stage(problem.dynamics, X[..., :-1, :], U, params) - X[..., 1:, :]
    h = map_stage(cons.stage_eq, X[..., :-1, :], U, params) if cons.me else None
    hN = map_state(cons.terminal_eq, X[..., -1, :], params) if cons.meN else None
    return defects, h, hN, _initial_rows(X, x0, initial, params)


def _initial_rows(X: Tensor, x0: Tensor, initial: Optional[InitialState], params) -> Tensor:
    """The initial rows ``c_0 (B, *E, m_0)``: a free start's ``h_0``, else ``x_0 − x̄_0``."""
    if initial is not None:
        return initial.evaluate(X[..., 0, :], params).e0
    return x0.reshape(x0.shape[0], *([1] * (X.dim() - 3)), -1) - X[..., 0, :]


def l1_norm(values: tuple) -> Tensor:
    """``‖C‖₁ (B, *E)`` of :func:`constraint_values`."""
    defects, h, hN, c0 = values
    total = defects.abs().sum((-1, -2)) + c0.abs().sum(-1)
    if h is not None:
        total = total + h.abs().sum((-1, -2))
    if hN is not None:
        total = total + hN.abs().sum(-1)
    return total


def model_infeasibility(model: Model, x0: Tensor, X: Tensor) -> Tensor:
    """``‖C‖₁ (B,)`` at the model's point, from its values."""
    c0 = model.initial.e0 if model.initial is not None else x0 - X[:, 0]
    return l1_norm((model.defects, model.h, model.hN, c0))


def penalty(gamma: Tensor, size: Tensor, opts: EILQROptions) -> Tensor:
    """``γ = κ max|y⁺| + γ_0``, or its maximum with the last ``γ`` (``merit_monotone``); ``size (B,)`` is
    ``max|y⁺|``."""
    target = opts.merit_factor * size + opts.merit_floor
    return target if opts.merit_monotone is False else torch.maximum(gamma, target)


def slope(model: Model, d: Direction, gamma: Tensor, l1: Tensor) -> Tensor:
    """The directional derivative ``D m(w; p) (B,)`` of the merit along the step."""
    dz = torch.cat([d.dX[:, :-1], d.dU], -1)
    grad = (model.lz * dz).sum((-1, -2)) + (model.lNx * d.dX[:, -1]).sum(-1)
    return grad - gamma * l1


def trial_steps(opts: EILQROptions, like: Tensor) -> Tensor:
    """The step sizes ``α = β^j``, ``j < line_search_steps`` (only ``α = 1`` without globalisation)."""
    count = opts.line_search_steps if opts.globalization else 1
    return opts.backtracking ** torch.arange(count, dtype=like.dtype, device=like.device)


def armijo_bound(merit0: Tensor, derivative: Tensor, alphas: Tensor, opts: EILQROptions) -> Tensor:
    """``m(0) + η α D m`` plus a few hundred rounding errors of ``m``: ``(B, l)`` for ``alphas (l,)``."""
    slack = 1e3 * torch.finfo(merit0.dtype).eps * (merit0.abs() + 1.0)
    return (merit0 + slack).unsqueeze(-1) + opts.armijo * alphas.unsqueeze(0) * derivative.unsqueeze(-1)


def merit_at(problem: Problem, cons: Constraints, params, X: Tensor, U: Tensor, x0: Tensor,
             initial: Optional[InitialState], gamma: Tensor, weights: Weights,
             record: Optional[bool] = False) -> Tensor:
    """``m = J + γ ‖C‖₁`` at ``X (B, *E, N+1, nx)``, ``U``: ``(B, *E)``, with the barrier of ``weights``; the costs,
    dynamics and rows in one pass (:func:`~torchtraj.core.one_pass.problem_values`, replayed from its recorded graph
    as ``record``, ``EILQROptions.record``, says)."""
    g = gamma.reshape(-1, *([1] * (X.dim() - 3)))
    values = problem_values(problem, cons, X, U, params, record=record)
    J = values.cost + barrier_cost(cons, values.g, values.gN, weights)
    rows = (values.f - X[..., 1:, :], values.h if cons.me else None, values.hN if cons.meN else None,
            _initial_rows(X, x0, initial, params))
    return J + g * l1_norm(rows)


def line_search(problem: Problem, cons: Constraints, params, X: Tensor, U: Tensor, x0: Tensor,
                initial: Optional[InitialState], d: Direction, merit0: Tensor, derivative: Tensor, gamma: Tensor,
                pending: Tensor, steps: Tensor, opts: EILQROptions, weights: Weights) -> Accepted:
    """Backtracking over ``steps (L,)`` on the merit from ``merit0 (B,)`` with slope ``derivative (B,)``, for the
    ``pending (B,)`` instances; all trial points of a round in one batched evaluation, and a round after the first
    of the instances still looking alone (with a fixed start: a free one's rows are not gathered). Returns
    :class:`~torchtraj.globalization.line_search.Accepted` with ``values = (merit (B,),)``."""

    def evaluate(alphas: Tensor, rows: Optional[Tensor] = None):
        a = alphas.reshape(1, -1, 1, 1)
        if rows is None:
            at = (X, U, d.dX, d.dU, params, x0, gamma, weights, merit0, derivative)
        else:
            at = (X[rows], U[rows], d.dX[rows], d.dU[rows], param_rows(params, rows), x0[rows], gamma[rows],
                  rows_of(weights, rows), merit0[rows], derivative[rows])
        X_, U_, dX, dU, params_, x0_, gamma_, weights_, merit0_, derivative_ = at
        Xa = X_.unsqueeze(1) + a * dX.unsqueeze(1)
        Ua = U_.unsqueeze(1) + a * dU.unsqueeze(1)
        m = kernel(merit_at, opts.compile)(problem, cons, params_, Xa, Ua, x0_, initial, gamma_, weights_, opts.record)
        accept = torch.isfinite(m) & (m <= armijo_bound(merit0_, derivative_, alphas, opts))
        if not opts.globalization:
            accept = torch.ones_like(accept)
        return accept, (m,)

    start = Accepted(found=~pending, alpha=torch.zeros_like(merit0), values=(merit0,))
    return backtrack(steps, opts.per_round, evaluate, pending, start, by_rows=initial is None)
