r"""Regularisation schedules: how much is added to a Hessian whose factorisation failed or whose step was refused.

**ALTRO's ρ schedule** (Tassa, Erez & Todorov 2012, "improved regularization", as Altro.jl uses it for its
backward pass, ALTRO §II-A eq. 13): ``ρ I`` is added to ``Q_uu`` and moves with a multiplicative speed ``δ`` and
the factor ``φ > 1``:

.. math::

    \text{success: } δ ← \min(δ/φ,\ 1/φ),\; ρ ← ρ δ \ (0 \text{ below } ρ_{min}); \qquad
    \text{failure: } δ ← \max(δ φ,\ φ),\; ρ ← \max(ρ δ,\ ρ_{min}).

**IPOPT's inertia correction** (Wächter & Biegler 2006 §3.1, Algorithm IC; FATROP §III "Hessian regularization"):
when the reduced Hessians are not positive definite, the primal regularisation ``δ_w`` of the next attempt is
``δ_w^0`` where no earlier iterate needed one (``δ_w^{last} = 0``), else ``max(δ_w^{min}, κ_w^- δ_w^{last})``; each
further attempt multiplies it by ``κ̄_w^+`` (no ``δ_w^{last}``) or ``κ_w^+``.

Both act on the batch: ``(B,)`` tensors in and out, one element's schedule independent of the others'.
:func:`corrected_attempts` runs the inertia correction's attempts for a whole batch of Newton steps.
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor


def rho_schedule(rho: Tensor, drho: Tensor, success: Tensor, increase: float, minimum: float) -> tuple:
    """ALTRO's next ``(ρ, δ)`` (``(B,)`` each) after a ``success (B,)`` or a failure, with ``φ = increase`` and
    ``ρ_min = minimum``."""
    phi = increase
    # decrease on success
    d_dec = torch.clamp(drho / phi, max=1.0 / phi)
    r_dec = rho * d_dec
    r_dec = torch.where(r_dec > minimum, r_dec, torch.zeros_like(r_dec))
    # increase on failure
    d_inc = torch.clamp(drho * phi, min=phi)
    r_inc = torch.clamp(rho * d_inc, min=minimum)
    return torch.where(success, r_dec, r_inc), torch.where(success, d_dec, d_inc)


def inertia_correction(delta: Tensor, last: Tensor, first: float, minimum: float, decrease: float,
                       increase_first: float, increase: float) -> Tensor:
    """IPOPT's ``δ_w`` ``(B,)`` of the attempt after a failed factorisation with ``delta (B,)``: ``last (B,)`` is the
    last nonzero ``δ_w`` that gave a positive definite system (0: none yet); ``first`` ``δ_w^0``, ``minimum``
    ``δ_w^{min}``, ``decrease`` ``κ_w^-``, ``increase_first`` ``κ̄_w^+``, ``increase`` ``κ_w^+``."""
    start = torch.where(last == 0, torch.full_like(delta, first), torch.clamp(decrease * last, min=minimum))
    grow = torch.where(last == 0, increase_first, increase) * delta
    return torch.where(delta == 0, start, grow)


def corrected_attempts(attempt: Callable, floor: Tensor, last: Tensor, running: Tensor, opts, pick: Callable,
                       attempts: int, write: Optional[Callable] = None, first=None) -> tuple:
    """IPOPT's inertia correction for a batch: the step of every ``running (B,)`` instance with the smallest
    ``δ_w`` from ``floor (B,)`` up whose reduced Hessians are positive definite.

    ``attempt(δ_w)`` factorises and solves the whole batch, returning a step with ``ok (B,)``; ``pick(mask, new,
    old)`` takes ``new`` on ``mask``; ``last (B,)`` is the last nonzero ``δ_w`` that worked; ``opts`` holds the
    schedule's ``regularization_first``, ``_min``, ``_decrease``, ``_increase_first``, ``_increase`` and ``_max``.
    At most ``attempts`` attempts follow the first. An instance whose ``δ_w`` passes ``regularization_max`` or whose
    attempts run out keeps its last, failed, step. ``write(step, rows, new)``, given, makes the attempts after the
    first on the pending instances' rows alone: ``attempt(δ_w, rows)`` factorises and solves the instances ``rows
    (R,)`` and ``write`` puts their step into ``step`` (one read of their count by the host each; the whole batch
    where every instance is pending). In a large batch a few instances need a correction, and the others'
    factorisations would be made again to be thrown away; each instance's arithmetic is the same. ``first``: the
    first attempt's step where the caller has made it already (at ``floor``). Returns ``(step, δ_w (B,))``: where
    the first attempt holds for every running instance, ``first`` and ``floor`` themselves."""
    delta = floor
    step = attempt(delta) if first is None else first
    pending = running & ~step.ok
    for _ in range(attempts):
        if not bool(pending.any()):
            break
        larger = inertia_correction(delta, last, opts.regularization_first, opts.regularization_min,
                                    opts.regularization_decrease, opts.regularization_increase_first,
                                    opts.regularization_increase)
        delta = torch.where(pending, larger, delta)
        pending = pending & (delta <= opts.regularization_max)
        step = pick(pending, attempt(delta), step) if write is None else \
            _attempt_rows(attempt, delta, pending, step, pick, write)
        pending = pending & ~step.ok
    return step, delta


def _attempt_rows(attempt: Callable, delta: Tensor, pending: Tensor, step, pick: Callable, write: Callable):
    """``step`` with the ``pending (B,)`` instances attempted again at ``delta``, on their rows alone
    (:func:`corrected_attempts`' ``write``)."""
    rows = pending.nonzero().squeeze(-1)
    if rows.numel() == 0:
        return step
    if rows.numel() == pending.shape[0]:  # every instance: no gathering
        return pick(pending, attempt(delta), step)
    return write(step, rows, attempt(delta, rows))
