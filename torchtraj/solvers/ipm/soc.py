r"""Second-order corrections of a rejected full step (Wächter & Biegler 2006 §2.3, "second-order corrections").

Where the first trial point ``w + α_max Δw`` of the filter line search is rejected and its constraint violation
did not decrease, ``θ(w + α_max Δw) ≥ θ(w)`` — the Maratos effect of a curved constraint, whose linearisation
the full step leaves —, the step is corrected before a shorter one is tried: the same factorised system (the
primal-dual matrix does not change) is solved for the constraint right-hand side

.. math::  c^{soc}_{p+1} = α^{soc}_p\, c^{soc}_p + c(w + α^{soc}_p Δw^{soc}_p), \qquad
           c^{soc}_0 = α_{max}\, c(w) + c(w + α_{max} Δw),

for every row ``c`` of the barrier problem (defects, ``h``, ``h_N``, ``g + s``, ``g_N + s_N``): replacing the
residuals by ``c^{soc}`` in the right-hand side of the reduced system (:func:`~torchtraj.solvers.ipm.newton.newton_rhs`)
gives the corrected step ``Δw^{soc}`` (its ``Δs``, ``Δz`` by FATROP eq. 8 from the same residuals). Its largest step
to the boundary ``α^{soc}`` is tried with the filter test of the line search; at most ``p_max`` corrections
(``IPOptions.second_order_corrections``, IPOPT's ``max_soc`` = 4), stopped once
``θ(w + α^{soc} Δw^{soc}) > κ_soc θ`` of the previous trial (``soc_decrease`` κ_soc = 0.99). An accepted corrected
step is taken instead of any shorter step of the original direction. The Armijo test of a corrected step uses its
own ``α^{soc}`` times the original slope (W&B use ``α_max``); the corrections reuse the step's factorisation where
the step kept it (eager solves), else the system is factorised again: once for all corrections eager, in each
correction's step with compiled kernels (``IPOptions.compile``), which run the corrections in the kernels of the
iteration's own step, boundary and trial point, each round on the instances still correcting alone.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import param_rows
from ...core.compiled import DYNAMIC_FROM, kernel
from ...core.constraints import Constraints
from ...core.problem import Problem
from ...globalization.filter import Filter
from ...riccati import LQR
from .compaction import gather_laid_out, gather_rows, kernel_rows, laid_out_as, pick, write_rows
from .iterate import Iterate, Model
from .kernels import compiled_kernels
from .line_search import advance, first_round, fraction_to_boundary, trial
from .newton import Direction, direction, factorize_step, newton_direction, newton_rhs
from .options import IPOptions


@dataclass
class Correction:
    """Per instance: a corrected step was accepted ``found (B,)``, its size ``alpha (B,)``, whether it met the
    switching and Armijo conditions ``unfiltered (B,)`` (no filter entry), and the iterate after it ``it``."""

    found: Tensor
    alpha: Tensor
    unfiltered: Tensor
    it: Iterate


def _scaled(alpha: Tensor, value: Tensor) -> Tensor:
    return alpha.reshape(-1, *[1] * (value.dim() - 1)) * value


def second_order_correction(problem: Problem, cons: Constraints, params, it: Iterate, d: Optional[Direction],
                            model: Model, mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor,
                            theta_min: Tensor, need: Tensor, a_max: Tensor, first: tuple, lqr: Optional[LQR],
                            delta: Tensor, x0: Tensor, opts: IPOptions) -> Correction:
    """The corrections (module docstring) of the instances ``need (B,)``, from the residuals ``first`` of the rejected
    trial points (``(B, l, ...)`` each, the full step first) and the system ``lqr`` regularised by ``δ_w`` (``None``
    with compiled kernels, whose Newton step forms it from the model:
    :func:`~torchtraj.solvers.ipm.newton.newton_direction`). Of the iteration's step ``d`` only its kept
    factorisation is read (eager); ``None``: the system is factorised here."""
    knots = model.knots
    tau = torch.clamp(1.0 - mu, min=opts.fraction_to_boundary)
    current = (model.f - it.X[:, 1:], model.h, model.hN, (model.g + it.s) * knots, model.gN + it.sN)
    c_soc = tuple(_scaled(a_max, c) + t[:, 0] for c, t in zip(current, first))
    theta_old = torch.cat([t[:, 0].reshape(t.shape[0], -1).abs() for t in first], -1).sum(-1)
    # compiled kernels (no factorisation kept): each correction's step, its boundary and its trial point in the
    # kernels of the iteration's own step and line search; eager: the step's factorisation, else one made here
    compiled = compiled_kernels(opts, it.X.device)
    kept = None if d is None else d.factor
    factor = None if compiled else kept if kept is not None else factorize_step(lqr, delta, opts)
    found = torch.zeros_like(need)
    # the corrected step of each instance, from the first round's (where none is accepted it is not read)
    alpha, unfiltered, best = torch.zeros_like(mu), torch.zeros_like(need), None
    a_dual = torch.zeros_like(mu)
    active = need
    for _ in range(opts.second_order_corrections):
        if not bool(active.any()):
            break
        defects, h, hN, gs, gsN = c_soc
        values = dict(f=defects + it.X[:, 1:], h=h, hN=hN, g=(gs - it.s) * knots, gN=gsN - it.sN)
        if compiled:  # laid out as the step's own (views of the expansion's rows): the same compiled kernels
            values = {name: laid_out_as(value, getattr(model, name)) for name, value in values.items()}
        corrected = dataclasses.replace(model, **values)
        rows = _round_rows(active) if compiled else None
        if rows is None:
            step, a_soc, a_dual_soc, accept, no_entry, theta_c, *parts = _corrected_trial(
                problem, cons, params, it, corrected, model, mu, phi, slope, filt, theta_max, theta_min, tau, lqr,
                factor, delta, x0, opts)
            ok = step.ok
            new = active & accept & ok
            best = step if best is None else pick(new, step, best)
        else:  # the instances still correcting alone, their results written back (the others' are not read)
            step, a_soc, a_dual_soc, accept, no_entry, theta_c, *parts = _corrected_trial_of_rows(
                problem, cons, params, it, corrected, model, mu, phi, slope, filt, theta_max, theta_min, tau, delta,
                x0, opts, rows)
            new = accept & step.ok
            best = _widened(step, rows, need.shape[0]) if best is None else \
                write_rows(best, rows, pick(new, step, gather_rows(best, rows)))
            new, ok, a_soc, a_dual_soc, no_entry, theta_c, *parts = (_scattered(v, rows, need.shape[0]) for v in (
                new, step.ok, a_soc, a_dual_soc, no_entry, theta_c, *parts))
        found = found | new
        alpha, a_dual = torch.where(new, a_soc, alpha), torch.where(new, a_dual_soc, a_dual)
        unfiltered = torch.where(new, no_entry, unfiltered)
        active = active & ~new & ok & (theta_c <= opts.soc_decrease * theta_old)
        theta_old = theta_c
        c_soc = tuple(_scaled(a_soc, c) + t for c, t in zip(c_soc, parts))
    if best is None:  # no instance needed one
        return Correction(found=found, alpha=alpha, unfiltered=unfiltered, it=it)
    return Correction(found=found, alpha=alpha, unfiltered=unfiltered,
                      it=kernel(advance, compiled)(it, best, alpha, a_dual, mu, knots, opts))


def _corrected_trial(problem: Problem, cons: Constraints, params, it: Iterate, corrected: Model, model: Model,
                     mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor,
                     tau: Tensor, lqr: Optional[LQR], factor, delta: Tensor, x0: Tensor, opts: IPOptions) -> tuple:
    """One correction of the instances given: the step of the ``corrected`` model's residuals, its largest step to
    the boundary and the trial point there. Returns ``(step, α^soc, α_dual, accept, unfiltered, θ, *residuals)``,
    ``(B,)`` each but the step and the residuals ``(B, ...)``. With compiled kernels the step's own kernel
    factorises the system again; eager, ``factor`` (of ``lqr``) solves it."""
    compiled = compiled_kernels(opts, it.X.device)
    step = kernel(newton_direction, True)(corrected, it, mu, x0, delta, opts.sweep, opts.terminal_rows) \
        if compiled else direction(lqr, newton_rhs(corrected, it, mu, x0, it.X.shape[-1]), delta, corrected, it, mu,
                                   None, factor, False, opts.sweep, opts.terminal_rows)
    a_soc, a_dual_soc = kernel(fraction_to_boundary, compiled)(it, step, tau)
    # compiled: the one trial point as many times as the first round has candidates, laid out as a round's step
    # sizes (line_search.line_search, globalization.line_search.backtrack): the later rounds' specialisation of the
    # trial kernel where their size is the first round's, else one of its own (one trial point, not four copies)
    alphas = a_soc.unsqueeze(1).expand(-1, opts.line_search_steps).contiguous()[
        :, :first_round(opts)].contiguous() if compiled else a_soc.unsqueeze(1)
    accept, no_entry, _, theta_c, parts = kernel(trial, compiled)(problem, cons, params, it, step, model, mu, phi,
                                                                  slope, filt, theta_max, theta_min, alphas, opts)
    step = dataclasses.replace(step, K=None)  # a corrected step's gains are not used: not gathered, picked, written
    return step, a_soc, a_dual_soc, accept[:, 0], no_entry[:, 0], theta_c[:, 0], *(t[:, 0] for t in parts)


def _round_rows(active: Tensor) -> Optional[Tensor]:
    """The rows ``(R,)`` of the instances still correcting, with compiled kernels on a batch (a batch of one has
    kernels of its own); ``None`` where every instance is (one read of their count by the host)."""
    if active.shape[0] < DYNAMIC_FROM:
        return None
    rows = active.nonzero().squeeze(-1)
    return None if rows.numel() == active.shape[0] else rows


def _corrected_trial_of_rows(problem: Problem, cons: Constraints, params, it: Iterate, corrected: Model,
                             model: Model, mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor,
                             theta_min: Tensor, tau: Tensor, delta: Tensor, x0: Tensor, opts: IPOptions,
                             rows: Tensor) -> tuple:
    """:func:`_corrected_trial` of the instances ``rows (R,)`` alone, with compiled kernels: their rows gathered laid
    out as the batch's, as many as a kernel takes (:func:`~torchtraj.solvers.ipm.compaction.kernel_rows`), and the
    first ``R`` of the results. A correction's instances end after different numbers of rounds, and those that ended
    are no longer factorised, solved and evaluated. An instance's arithmetic is the same as in the whole batch."""
    index = kernel_rows(rows)
    *taken, delta, x0 = gather_laid_out((it, corrected, model, mu, phi, slope, filt, theta_max, theta_min, tau,
                                         delta, x0), index)  # the fields `corrected` shares with `model` once
    out = _corrected_trial(problem, cons, param_rows(params, index), *taken, None, None, delta, x0, opts)
    return out if index is rows else gather_laid_out(out, torch.arange(rows.numel(), device=rows.device))


def _scattered(value: Tensor, rows: Tensor, batch: int) -> Tensor:
    """``value (R, ...)`` of the instances ``rows (R,)`` in a zero tensor of ``batch`` instances."""
    return value.new_zeros((batch,) + value.shape[1:]).index_copy(0, rows, value)


def _widened(step: Direction, rows: Tensor, batch: int) -> Direction:
    """``step`` of the instances ``rows (R,)`` as a step of ``batch`` instances, laid out as ``step`` (zero in the
    others' rows, which are not read)."""
    return dataclasses.replace(step, **{f.name: laid_out_as(_scattered(getattr(step, f.name), rows, batch),
                                                            getattr(step, f.name))
                                        for f in dataclasses.fields(step) if isinstance(getattr(step, f.name), Tensor)})


def correction_of_rows(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model,
                       mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor,
                       need: Tensor, a_max: Tensor, first: tuple, lqr: LQR, delta: Tensor, x0: Tensor,
                       opts: IPOptions) -> Correction:
    """:func:`second_order_correction` of the instances ``need (B,)`` on their rows alone (eager solves, and compiled
    kernels without CUDA graphs: ``lqr`` None), gathered with their parameters; the others' ``found`` is false.
    Eager, their system is factorised again for them (the step's factorisation is of the whole batch): in a large
    batch a few instances need a correction, and a factorisation or a solve of all would be made for them. Each
    instance's arithmetic is the same."""
    rows = need.nonzero().squeeze(-1)
    compiled = lqr is None  # compiled kernels, which form the system themselves: their rows laid out as the batch's,
    take = gather_laid_out if compiled else gather_rows  # as many as a kernel takes (newton.direction_of_rows)
    if compiled and need.shape[0] >= DYNAMIC_FROM:  # (a batch of one has kernels of its own; a repeated row is
        rows = kernel_rows(rows)  # written back twice, the same values)
    if rows.numel() == need.shape[0]:
        return second_order_correction(problem, cons, params, it, d, model, mu, phi, slope, filt, theta_max,
                                       theta_min, need, a_max, first, lqr, delta, x0, opts)
    # no step `d`: the corrections start from their own (and eager, `d`'s factorisation is the whole batch's)
    sub = second_order_correction(
        problem, cons, param_rows(params, rows), take(it, rows), None, take(model, rows),
        *(take(v, rows) for v in (mu, phi, slope)), take(filt, rows),
        *(take(v, rows) for v in (theta_max, theta_min, need, a_max)), take(first, rows),
        None if compiled else lqr.rows(rows), take(delta, rows), take(x0, rows), opts)
    return Correction(found=torch.zeros_like(need).index_copy(0, rows, sub.found),
                      alpha=torch.zeros_like(mu).index_copy(0, rows, sub.alpha),
                      unfiltered=torch.zeros_like(need).index_copy(0, rows, sub.unfiltered),
                      it=write_rows(it, rows, sub.it))
