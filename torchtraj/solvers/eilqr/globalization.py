r"""One globalised step of eILQR (Horizon §II-F): the step truncated to the barrier's domain, its second-order
correction, then backtracking.

**Fraction to the boundary** (Wächter & Biegler 2006 §2.2, eq. (15); Nocedal & Wright 2006 §19.2, eq. (19.9)). The
Newton model of a log barrier is a quadratic that does not see the barrier's boundary ``t = 0``: in a stage with a
small weight the step runs through an active row and the merit, whose barrier is infinite there (its relaxed
extension stiff, ``w/δ²``), refuses every step size above the crossing. The step is first scaled by

.. math::  α_{\max} = \max\{α ∈ (0, 1] : t + α\,δt \ge (1 − τ)\,t\},\qquad δt = −G\,δz,\ τ = \max(τ_{\min}, 1 − w)

over the rows in the log region (``t ≥ δ``; the relaxed region below is quadratic, it has no boundary), the rows
linearised (exact for bounds). The multipliers move the same fraction, ``y ← y + α_max (y⁺ − y)``.

**Second-order correction** (Nocedal & Wright 2006 §18.3; IPOPT's, Wächter & Biegler 2006 §2.4, applied at the first
trial step ``α_max``). A step that the ℓ1 merit refuses because the linearised dynamics leave a second-order defect
that ``γ ‖C‖₁`` charges more than the step gains (the Maratos effect) would cut the step size for ever. Where the
truncated step ``α_max p`` is refused, it is corrected once: the same factorised KKT system (one vector solve; a
refactorisation with the same ``ε`` where the inertia correction mixed factorisations) gives ``q`` with
``∇c q = −r``, ``r = c(w + α_max p) − (1 − α_max) c(w)`` the constraints' departure from their linearisation (for
``α_max = 1`` IPOPT's ``c(w) + c(w + p)`` system), and ``α_max p + q`` is taken whole if it passes the Armijo test of
the truncated step. Before the truncation the correction was tried only at ``α = 1``, which on the cart-pole crossed a
control bound in most iterations of its last stages: the correction was never taken and the steps were cut to
``α ≈ 1/16``, where the defects' second-order error dominates (hundreds of iterations). Otherwise the step sizes
``α = β, β², …`` of the truncated step are tried in batched rounds (:func:`~torchtraj.solvers.eilqr.merit.line_search`).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...globalization.line_search import Accepted
from .initial_state import InitialRows
from .merit import armijo_bound, constraint_values, line_search, merit_at, slope, trial_steps
from .model import Iterate, Model
from .newton import Direction, direction, pick_direction, resolve

#: the direction's multiplier fields, moved as ``y ← y + α (y⁺ − y)``
_MULTIPLIERS = ("lam", "nu", "nuN", "mu0", "z", "zN")


def boundary_fraction(model: Model, d: Direction, weight: Tensor, delta: Tensor, tau_min: float) -> Tensor:
    """``α_max (B,)`` of the fraction-to-the-boundary rule (module docstring) on the linearised rows of ``model``
    along ``d``, with ``τ = max(tau_min, 1 − w)`` per instance (``weight``, ``delta``: ``(B,)``)."""
    rows = model.rows
    tau = torch.clamp(1.0 - weight, min=tau_min)
    dz = torch.cat([d.dX[:, :-1], d.dU], -1)
    shrink = (rows.G @ dz.unsqueeze(-1)).squeeze(-1) * rows.mask  # −δt of the stage rows
    shrinkN = (rows.GN @ d.dX[:, -1].unsqueeze(-1)).squeeze(-1)

    def largest(t, s, d_like):
        limited = (t >= d_like) & (s > 0)
        ratio = torch.where(limited, tau.reshape(-1, *([1] * (t.dim() - 1))) * t / torch.where(limited, s, 1.0),
                            torch.ones_like(t))
        return torch.cat([ratio.reshape(t.shape[0], -1), t.new_ones(t.shape[0], 1)], -1).amin(-1)

    stage = largest(rows.t, shrink, delta.reshape(-1, 1, 1))
    terminal = largest(rows.tN, shrinkN, delta.reshape(-1, 1))
    return torch.clamp(torch.minimum(stage, terminal), max=1.0)


def truncated(d: Direction, it: Iterate, alpha: Tensor) -> Direction:
    """``d`` scaled by ``alpha (B,)``: the primal step and the multipliers' move ``y + α (y⁺ − y)``."""
    def scale(t):
        return alpha.reshape(-1, *([1] * (t.dim() - 1))) * t

    moved = {name: getattr(it, name) + scale(getattr(d, name) - getattr(it, name)) for name in _MULTIPLIERS}
    return dataclasses.replace(d, dX=scale(d.dX), dU=scale(d.dU), **moved)


def corrected_step(problem, cons, params, model, it, x0, initial, d, p, alpha, eps):
    """The second-order correction of the truncated step ``p = α d`` (``alpha (B,)``): ``p + q`` with ``q`` the
    step of the constraint residual ``r = c(w + p) − (1 − α) c(w)`` (module docstring), its multipliers
    ``y + α (ŷ⁺ − y)`` from the corrected system."""
    defects, h, hN, c0 = constraint_values(problem, cons, params, it.X + p.dX, it.U + p.dU, x0, initial)

    def residual(at_trial, here):
        return at_trial - (1.0 - alpha.reshape(-1, *([1] * (here.dim() - 1)))) * here

    # a fixed start's row x̄_0 − x_0 is linear (no residual); a free start's rows h_0 are corrected
    r0 = residual(c0, model.initial.e0) if model.initial is not None else None
    corrected = dataclasses.replace(
        model, defects=model.defects + residual(defects, model.defects),
        h=model.h if h is None else model.h + residual(h, model.h),
        hN=model.hN if hN is None else model.hN + residual(hN, model.hN),
        initial=None if model.initial is None else InitialRows(e0=model.initial.e0 + r0, E0=model.initial.E0))
    # the same factorisation, one vector solve, where every instance's step came from one
    soc = resolve(d, corrected, it, x0) if d.factor is not None else direction(corrected, it, x0, eps)
    step = truncated(soc, it, alpha)
    return dataclasses.replace(step, dX=p.dX + soc.dX - d.dX, dU=p.dU + soc.dU - d.dU, ok=soc.ok)


def globalized_step(problem, cons, params, model, it, x0, initial, d, eps, gamma, l1, pending, opts, weights):
    """The accepted step of the ``pending (B,)`` instances from the direction ``d`` (computed with ``eps (B,)``):
    ``(direction, Accepted, merit0 (B,))``, the direction truncated to the boundary (its ``α = 1`` the truncated
    step) and replaced by its correction where that was taken."""
    merit0 = model.J + gamma * l1
    alpha_max = boundary_fraction(model, d, weights.weight, weights.delta, opts.boundary_fraction) \
        if opts.globalization else torch.ones_like(merit0)
    p = truncated(d, it, alpha_max)
    derivative = slope(model, p, gamma, l1)
    steps = trial_steps(opts, merit0)
    ls = line_search(problem, cons, params, it.X, it.U, x0, initial, p, merit0, derivative, gamma, pending,
                     steps[:1], opts, weights)
    refused = pending & ~ls.found
    if opts.globalization and opts.second_order_correction and bool(refused.any()):
        soc = corrected_step(problem, cons, params, model, it, x0, initial, d, p, alpha_max, eps)
        m = merit_at(problem, cons, params, it.X + soc.dX, it.U + soc.dU, x0, initial, gamma, weights)
        bound = armijo_bound(merit0, derivative, steps[:1], opts)[:, 0]
        taken = refused & soc.ok & torch.isfinite(m) & (m <= bound)
        p = pick_direction(taken, soc, p)
        ls = Accepted(found=ls.found | taken, alpha=torch.where(taken, 1.0, ls.alpha),
                      values=(torch.where(taken, m, ls.values[0]),))
    refused = pending & ~ls.found
    if steps.shape[0] > 1 and bool(refused.any()):
        rest = line_search(problem, cons, params, it.X, it.U, x0, initial, p, merit0, derivative, gamma, refused,
                           steps[1:], opts, weights)
        ls = Accepted(found=ls.found | rest.found, alpha=torch.where(ls.found, ls.alpha, rest.alpha),
                      values=(torch.where(ls.found, ls.values[0], rest.values[0]),))
    return p, ls, merit0
