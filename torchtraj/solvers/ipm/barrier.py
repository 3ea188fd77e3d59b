r"""The barrier parameter ``μ``: IPOPT's monotone update, or Mehrotra's predictor-corrector (opt-in).

**Monotone update** (Fiacco-McCormick; Wächter & Biegler 2006 §2.1, eq. 7): when the barrier problem's error
``E_μ ≤ κ_ε μ`` (:mod:`~torchtraj.solvers.ipm.expansion`),

.. math::  μ ← \max\big(\text{tol}/10,\ \min(κ_μ μ,\ μ^{θ_μ})\big),

repeatedly within one iteration, and the instance's filter is reset. **Very small search directions** (W&B §3.9):
where the primal step was at round-off (IPOPT's tiny step, :mod:`~torchtraj.solvers.ipm.line_search`) in two
successive iterations and the multiplier step is below ``tiny_step_dual`` (``tiny_step_y_tol``), the Newton steps
cannot improve the barrier problem any further in this precision: ``μ`` is decreased even though ``E_μ > κ_ε μ``;
where ``μ`` is already at its floor the search direction is too small to go on (IPOPT's
``Search_Direction_Becomes_Too_Small``) and the instance stops, ``STALLED``.

**Mehrotra's predictor-corrector** (``barrier_strategy="mehrotra"``; IPOPT's ``mehrotra_algorithm``, for LPs and
convex QPs): each iteration solves the factorised system twice, first for the affine-scaling step (``S z = 0``),
whose largest steps to the boundary give ``μ_aff``; then ``μ = σ μ̄`` with ``σ = min((μ_aff / μ̄)³, σ_max)`` and the
average complementarity ``μ̄`` (within ``[tol/10, 10³ μ̄_0]``), and the corrector step for
``S z = μ − ΔS_aff Δz_aff``. No line search: the fraction-to-boundary steps are taken whole (a step the boundary
cuts to round-off counts as a failed one). On the bench's box-constrained linear system (B = 256) it takes 6.9
iterations on average, at most 11, against 10.9 and 17; on the nonlinear pendulum with state bounds, without a
globalisation, 80 against 28, and one instance ends at another local optimum: it is not the default.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from ...core.constraints import Constraints
from ...core.status import Status
from ...globalization.filter import Filter
from ...riccati import LQR
from .expansion import complementarity_of, complementarity_parts
from .iterate import Iterate, Model
from .line_search import Step, advance, fraction_to_boundary, step_and_round_off
from .newton import Direction, direction, factorize_step, newton_rhs
from .options import IPOptions


def monotone_update(cons: Constraints, model: Model, it: Iterate, mu: Tensor, running: Tensor, filt: Filter,
                    tol: float, opts: IPOptions, forced: Optional[Tensor] = None, settle: bool = True) -> tuple:
    """Monotone barrier update of ``mu (B,)``, repeated while the barrier problem is already solved, and once where
    ``forced (B,)`` (very small search directions); resets the filter of the instances it updates. Returns ``(μ,
    filter)``. ``settle``: the rounds end at the first that updates no instance (one host read a round); else all
    four run (a compiled kernel's one graph), with the same answer: such a round leaves μ, and every later one, as
    it was."""
    floor = tol / 10.0
    # what does not depend on μ, once for the four rounds
    others, parts = torch.maximum(model.dual_error, model.primal_error), complementarity_parts(cons, it, opts)
    updated = torch.zeros_like(running)
    for round_ in range(4):
        error = torch.maximum(others, complementarity_of(parts, mu, cons.ineq_knot_mask))
        solved = error <= opts.barrier_tolerance_factor * mu
        if forced is not None:
            solved, forced = solved | forced, None
        update = running & solved & (mu > floor)
        smaller = torch.clamp(torch.minimum(opts.barrier_decrease * mu, mu ** opts.barrier_power), min=floor)
        mu = torch.where(update, smaller, mu)
        updated = updated | update
        if settle and round_ < 3 and not bool(update.any()):
            break
    # emptying a filter twice empties it once: one reset for the rounds
    return mu, filt.reset(updated)


def barrier_step(cons: Constraints, model: Model, it: Iterate, mu: Tensor, status: Tensor, running: Tensor,
                 tiny_steps: Tensor, filt: Filter, tol: float, opts: IPOptions, settle: bool = True) -> tuple:
    """An iteration's monotone update (:func:`monotone_update`) with IPOPT's very small search directions (W&B
    §3.9): where ``tiny_steps (B,)`` reached two, ``μ`` decreases even though the barrier problem is not solved, and
    where it is at its floor already the instance stops, ``STALLED``; those counts restart. Returns ``(μ, filter,
    status, running, tiny_steps, changed)``, ``changed (B,)`` where ``μ`` moved. ``settle``: as
    :func:`monotone_update`'s (off in a compiled kernel: no host read)."""
    forced = running & (tiny_steps >= 2)
    stuck = forced & (mu <= tol / 10.0)
    status = torch.where(stuck, int(Status.STALLED), status)
    running = running & ~stuck
    updated, filt = monotone_update(cons, model, it, mu, running, filt, tol, opts, forced & running, settle)
    return updated, filt, status, running, torch.where(forced, 0, tiny_steps), updated != mu


def average_complementarity(s: Tensor, sN: Tensor, z: Tensor, zN: Tensor, knots: Tensor) -> Tensor:
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
    boundary cuts to round-off, or to less than ε of the Newton step, is not found, as after a failed line search.
    Returns ``(μ (B,), direction, step)``."""
    knots = model.knots
    a_p, a_d = fraction_to_boundary(it, predictor, torch.ones_like(delta))
    ap, ad = a_p.reshape(-1, 1, 1), a_d.reshape(-1, 1, 1)
    average = average_complementarity(it.s, it.sN, it.z, it.zN, knots)
    affine = average_complementarity(it.s + ap * predictor.ds, it.sN + a_p.unsqueeze(-1) * predictor.dsN,
                                     it.z + ad * predictor.dz, it.zN + a_d.unsqueeze(-1) * predictor.dzN, knots)
    sigma = torch.clamp((affine / torch.where(average > 0, average, 1.0)) ** 3, max=opts.mehrotra_sigma_max)
    mu = torch.maximum(torch.minimum(sigma * average, ceiling), torch.full_like(ceiling, floor))
    target = (mu.reshape(-1, 1, 1) - predictor.ds * predictor.dz, mu.unsqueeze(-1) - predictor.dsN * predictor.dzN)
    rhs = newton_rhs(model, it, mu, x0, it.X.shape[-1], target)
    factor = predictor.factor if predictor.factor is not None else factorize_step(lqr, delta, opts)
    d = direction(lqr, rhs, delta, model, it, mu, target, factor=factor)
    a_max, a_dual = fraction_to_boundary(it, d, torch.clamp(1.0 - mu, min=opts.fraction_to_boundary))
    size, round_off = step_and_round_off(it, d)
    # cut to round-off: the step itself, or its fraction of the Newton step (a huge step cut below ε moves the point
    # by barely more than round-off, iteration after iteration)
    stalled = ((a_max * size <= round_off) & (size > round_off)) | (a_max < torch.finfo(a_max.dtype).eps)
    found = factored & d.ok & ~stalled
    return mu, d, Step(advance(it, d, a_max, a_dual, mu, knots, opts), a_max, found, filt)
