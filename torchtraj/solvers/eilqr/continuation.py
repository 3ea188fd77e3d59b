r"""Barrier continuation: an extension of eILQR *beyond the paper*, so that a converged point is the
hard-constrained KKT point rather than the soft barrier's.

Horizon's eILQR keeps its inequalities as soft barriers of a fixed weight ``w`` (Laurenzi et al. §III;
:mod:`~torchtraj.solvers.eilqr.barrier`), whose optimum sits ``O(w)`` off the hard-constrained one. Here the weight
decreases between Newton stages as an interior point's barrier parameter ``μ`` does (Wächter & Biegler 2006,
§2.1, eq. (7); Fiacco & McCormick's barrier path):

.. math::

    w \leftarrow \max\big(w_{\min},\ \min(κ_w w,\ w^{θ_w})\big)
    \quad\text{once}\quad E_w \le κ_ε\, w,

per instance (``w (B,)``), with ``E_w`` the KKT error of the current weight (stationarity with the inequality
multipliers ``z``, the defects and equalities, and the complementarity ``|t (z − w s(t))|``, ``t = −g``,
``s = −β'``) and ``w_min`` tied to the tolerance (``tol / 10``: the last stage's barrier gap, about ``w`` per active
row, is then below what the tolerance resolves; ``tol / 100`` in float32, :func:`final_weight`). The relaxation
follows the weight, ``δ = w / 10`` (the options' ``barrier_relaxation / barrier_weight``). At
``w_min`` an instance has converged where ``E_w ≤ tol``: a KKT point of the problem with *hard* inequalities to
``tol`` (complementarity ``z_i (−g_i) = w_min``), which the certificate of :mod:`torchtraj.kkt.certificate` checks.

**Primal-dual Newton step** (also beyond the paper). The multipliers ``z`` of the inequality rows are iterates
beside ``λ, ν``, and the barrier's curvature in the Newton matrix is ``Gᵀ diag(σ) G`` with ``σ = z / t`` (the
primal-dual form; ``w/δ²`` on relaxed rows, ``t < δ``) instead of the primal ``w / t²``, with the barrier's gradient
``Gᵀ w s(t)`` on the right-hand side. The step's new multipliers are ``z⁺ = w s(t) + σ G δz``. Two reasons:

- after a decrease of ``w`` a primal barrier's Newton step overshoots an active row by the factor ``w_old/w_new``
  (its curvature ``w_new/t²`` is that much too small at ``t = w_old/z``) and the line search cuts every step;
  with ``σ = z/t`` the first step lands on the new weight's central point to first order;
- the multipliers read off the barrier, ``w s(t)``, carry the rounding of ``t``: at an active row
  ``δz = z² ε |g| / w``, ``1e-4`` in float64 at ``w = 1e-10`` and ``z = 10``, and ``5e-3`` in float32 at
  ``w = 1e-4`` (the ``STALLED`` instances of the fixed weight), far above the certificate. As iterates the
  multipliers make the Lagrangian stationary to the dtype's accuracy; ``w s(t)`` equals them to the complementarity
  tolerance.

Each ``z`` is kept in ``[w s(t) / κ_Σ, κ_Σ w s(t)]`` (IPOPT's safeguard, §3.7) so that ``σ`` stays within a factor
of the primal curvature. IPOPT's ``κ_Σ = 1e10`` let the cart-pole's first steps, which cross the control bounds into
the relaxed rows (``σ = w/δ² = 1e6``), set multipliers ``1e10`` times the barrier's (a complementarity error of
``3e6``, the merit's ``γ`` at ``1e7``, 30 iterations to recover); ``κ_Σ = 1e4`` still keeps the largest ratio a
decrease of ``w`` makes (``w_old / w_new = 1e3``). ``barrier_continuation=False`` keeps the paper's fixed weight (the
same primal-dual steps converge to the soft problem's KKT point, whose multipliers are ``w s(t)``).

The state rows apply from knot 1 as in the hard problem
(:attr:`~torchtraj.core.constraints.Constraints.ineq_knot_mask`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...core.constraints import Constraints
from ...core.derivatives import stage_jacobian, terminal_jacobian
from .barrier import relaxed_log, relaxed_log_curvature, relaxed_log_slope

#: ``κ_Σ``: how far a multiplier may stray from the barrier's ``w s(t)`` (Wächter & Biegler 2006, §3.7, where it is
#: 1e10; module docstring).
KAPPA_SIGMA = 1e4


@dataclass
class Weights:
    """The barrier of each instance: weight ``w (B,)`` and relaxation ``δ (B,)``."""

    weight: Tensor
    delta: Tensor

    def like(self, t: Tensor) -> tuple:
        """``(w, δ)`` shaped to broadcast against ``t (B, ...)``."""
        shape = (-1, *([1] * (t.dim() - 1)))
        return self.weight.reshape(shape), self.delta.reshape(shape)


@dataclass
class Rows:
    """The inequality rows at a point: slacks ``t = −g`` ``(B, N, mi)`` and ``tN (B, miN)``, their Jacobians
    ``G (B, N, mi, nz)`` and ``GN (B, miN, nx)`` (``∂g``), and the knot mask ``(N, mi)``."""

    t: Tensor
    G: Tensor
    tN: Tensor
    GN: Tensor
    mask: Tensor


def rows_at(cons: Constraints, X: Tensor, U: Tensor, params) -> Rows:
    """The :class:`Rows` of ``cons``'s inequalities at ``X (B, N+1, nx)``, ``U (B, N, nu)``."""
    B, N, nx, nu = U.shape[0], U.shape[1], X.shape[-1], U.shape[-1]
    if cons.mi:
        g, G = stage_jacobian(cons.stage_ineq, X[:, :-1], U, params)
    else:
        g, G = X.new_zeros(B, N, 0), X.new_zeros(B, N, 0, nx + nu)
    if cons.miN:
        gN, GN = terminal_jacobian(cons.terminal_ineq, X[:, -1], params)
    else:
        gN, GN = X.new_zeros(B, 0), X.new_zeros(B, 0, nx)
    mask = cons.ineq_knot_mask if cons.mi else X.new_zeros(N, 0)
    return Rows(t=-g, G=G, tN=-gN, GN=GN, mask=mask)


def barrier_cost(cons: Constraints, g: Tensor, gN: Tensor, weights: Weights) -> Tensor:
    """``Σ w β(−g)`` over the rows that apply, from the rows' values ``g (B, *E, N, mi)`` and ``gN (B, *E, miN)``:
    ``(B, *E)``."""
    total = g.new_zeros(g.shape[:-2])
    if cons.mi:
        t = -g
        w, delta = weights.like(t)
        total = total + (w * relaxed_log(t, delta) * cons.ineq_knot_mask).sum((-1, -2))
    if cons.miN:
        tN = -gN
        w, delta = weights.like(tN)
        total = total + (w * relaxed_log(tN, delta)).sum(-1)
    return total


def barrier_multipliers(rows: Rows, weights: Weights) -> tuple:
    """The barrier's multipliers ``w s(t) = −w β'(t)`` of the stage ``(B, N, mi)`` and terminal ``(B, miN)`` rows
    (zero on rows off at a knot)."""
    w, delta = weights.like(rows.t)
    wN, deltaN = weights.like(rows.tN)
    return -w * relaxed_log_slope(rows.t, delta) * rows.mask, -wN * relaxed_log_slope(rows.tN, deltaN)


def barrier_value(rows: Rows, weights: Weights) -> Tensor:
    """``Σ w β(t)`` over the rows that apply, from their slacks: ``(B,)``."""
    w, delta = weights.like(rows.t)
    wN, deltaN = weights.like(rows.tN)
    return ((w * relaxed_log(rows.t, delta) * rows.mask).flatten(1).sum(-1)
            + (wN * relaxed_log(rows.tN, deltaN)).sum(-1))


def curvatures(rows: Rows, z: Tensor, zN: Tensor, weights: Weights) -> tuple:
    """The primal-dual ``σ = z / t`` (``w β''(t) = w/δ²`` on relaxed rows, ``t < δ``), stage and terminal."""
    def one(t, zz):
        w, delta = weights.like(t)
        return torch.where(t >= delta, zz / torch.maximum(t, delta), w * relaxed_log_curvature(t, delta))
    return one(rows.t, z) * rows.mask, one(rows.tN, zN)


def safeguarded(z: Tensor, barrier: Tensor) -> Tensor:
    """``z`` within ``[w s / κ_Σ, κ_Σ w s]`` of the barrier's multipliers ``barrier = w s(t)``."""
    return torch.minimum(torch.maximum(z, barrier / KAPPA_SIGMA), barrier * KAPPA_SIGMA)


def final_weight(opts, tolerance: float, dtype: torch.dtype) -> float:
    """``w_min``: ``barrier_weight_final``, or ``tol / 10`` in float64 (1e-10) and ``tol / 100`` in float32
    (1e-7); without continuation the weight itself. The last stage's gap to the hard optimum is about ``w`` per
    active row: float32's tolerance (1e-5) is set by its resolution of the residuals, and ``tol / 10`` left the
    contract test's pendulum 3.9e-6 above its float64 optimum, ``tol / 100`` within float32's resolution of the
    cost."""
    if not opts.barrier_continuation:
        return opts.barrier_weight
    if opts.barrier_weight_final is not None:
        return min(opts.barrier_weight_final, opts.barrier_weight_initial)
    return min(tolerance / (10.0 if dtype == torch.float64 else 100.0), opts.barrier_weight_initial)


def next_weight(weight: Tensor, final: float, opts) -> Tensor:
    """``max(w_min, min(κ_w w, w^θ_w))`` (``(B,)``)."""
    return torch.clamp(torch.minimum(opts.barrier_decrease * weight, weight ** opts.barrier_superlinear), min=final)


def stage_done(error: Tensor, weight: Tensor, opts) -> Tensor:
    """Where the KKT error of the current weight is below ``κ_ε w``."""
    return error <= opts.barrier_error_factor * weight


def first_weight(opts) -> float:
    """The first stage's weight: ``barrier_weight_initial`` with continuation, else the fixed ``barrier_weight``."""
    return opts.barrier_weight_initial if opts.barrier_continuation else opts.barrier_weight


def weights_for(weight: Tensor, opts) -> Weights:
    """The :class:`Weights` of ``weight (B,)``, the relaxation in the options' ratio ``δ / w``."""
    return Weights(weight=weight, delta=weight * (opts.barrier_relaxation / opts.barrier_weight))


__all__ = ["Weights", "Rows", "rows_at", "barrier_cost", "barrier_multipliers", "barrier_value", "curvatures",
           "safeguarded", "final_weight", "first_weight", "next_weight", "stage_done", "weights_for", "KAPPA_SIGMA"]
