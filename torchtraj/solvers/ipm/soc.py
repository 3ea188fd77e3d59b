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
correction's step with compiled kernels (``IPOptions.compile``). A round is the corrected step (compiled: the
kernel of the iteration's own step) and one function of the rest (:func:`correction_round`: compiled, one kernel):
its boundary, its trial point, the iterate after it and the next round's right-hand sides. The rounds run on the
instances that needed a correction (:func:`correction_of_rows` gathers them): eager, those that stopped masked;
compiled on a batch, a later round on the instances still correcting alone. Compiled, the first round of a call
whose every instance corrects is one kernel call with the start (:func:`started_round`).
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
from .line_search import advance, fraction_to_boundary, trial
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


@dataclass
class Rounds:
    """The corrections between two rounds, per instance: the right-hand sides ``c_soc`` of the next one (the five
    row blocks), the violation ``θ`` of the last trial point ``theta_old (B,)``, the instances still correcting
    ``active (B,)``, the fraction to the boundary ``tau (B,)``, and what :class:`Correction` reports so far but its
    iterate."""

    c_soc: tuple
    theta_old: Tensor
    active: Tensor
    tau: Tensor
    found: Tensor
    alpha: Tensor
    unfiltered: Tensor


def corrected_values(model: Model, it: Iterate, c_soc: tuple) -> dict:
    """The model's residual fields whose barrier-problem rows are the right-hand sides ``c_soc``: the model of which
    the Newton step is the corrected step."""
    defects, h, hN, gs, gsN = c_soc
    return dict(f=defects + it.X[:, 1:], h=h, hN=hN, g=(gs - it.s) * model.knots, gN=gsN - it.sN)


def correction_start(model: Model, it: Iterate, need: Tensor, first: tuple, a_max: Tensor, mu: Tensor,
                     opts: IPOptions) -> tuple:
    """The first round's right-hand sides ``c^soc_0 = α_max c(w) + c(w + α_max Δw)`` of the instances ``need (B,)``,
    from the residuals ``first`` of the rejected trial points (``(B, l, ...)`` each, the full step first). Returns
    ``(Rounds, corrected values)`` (:func:`corrected_values`)."""
    knots = model.knots
    current = (model.f - it.X[:, 1:], model.h, model.hN, (model.g + it.s) * knots, model.gN + it.sN)
    c_soc = tuple(_scaled(a_max, c) + t[:, 0] for c, t in zip(current, first))
    theta_old = torch.cat([t[:, 0].reshape(t.shape[0], -1).abs() for t in first], -1).sum(-1)
    zero = torch.zeros_like(mu)
    rounds = Rounds(c_soc=c_soc, theta_old=theta_old, active=need,
                    tau=torch.clamp(1.0 - mu, min=opts.fraction_to_boundary), found=torch.zeros_like(need),
                    alpha=zero, unfiltered=torch.zeros_like(need))
    return rounds, corrected_values(model, it, c_soc)


def correction_round(problem: Problem, cons: Constraints, params, it: Iterate, step: Direction, model: Model,
                     mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor,
                     rounds: Rounds, opts: IPOptions) -> tuple:
    """One round of the corrections, from the corrected ``step``: its largest step to the boundary ``α^soc``, the
    filter test of the trial point there, the iterate after it where accepted, and the next round's right-hand sides
    ``c^soc_{p+1} = α^soc_p c^soc_p + c(w + α^soc_p Δw^soc_p)`` of the instances still correcting (stopped once
    ``θ`` does not decrease by ``κ_soc``). Returns ``(Rounds, corrected values, accepted (B,), iterate)``, the iterate
    after this round's step of every instance (read where accepted): with compiled kernels, one kernel call a round
    besides the step's."""
    a_soc, a_dual = fraction_to_boundary(it, step, rounds.tau)
    accept, no_entry, _, theta_c, parts = trial(problem, cons, params, it, step, model, mu, phi, slope, filt,
                                                theta_max, theta_min, a_soc.unsqueeze(1), opts)
    new = rounds.active & accept[:, 0] & step.ok
    moved = advance(it, step, a_soc, a_dual, mu, model.knots, opts)
    c_soc = tuple(_scaled(a_soc, c) + t[:, 0] for c, t in zip(rounds.c_soc, parts))
    theta = theta_c[:, 0]
    next_rounds = Rounds(c_soc=c_soc, theta_old=theta,
                         active=rounds.active & ~new & step.ok & (theta <= opts.soc_decrease * rounds.theta_old),
                         tau=rounds.tau, found=rounds.found | new, alpha=torch.where(new, a_soc, rounds.alpha),
                         unfiltered=torch.where(new, no_entry[:, 0], rounds.unfiltered))
    return next_rounds, corrected_values(model, it, c_soc), new, moved


def started_round(problem: Problem, cons: Constraints, params, it: Iterate, model: Model, mu: Tensor, phi: Tensor,
                  slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor, need: Tensor, a_max: Tensor,
                  first: tuple, delta: Tensor, x0: Tensor, opts: IPOptions) -> tuple:
    """:func:`correction_start`, the first corrected step (:func:`~torchtraj.solvers.ipm.newton.newton_direction`,
    regularised by ``δ_w`` ``delta (B,)``) and its :func:`correction_round` in one function: with compiled kernels
    the first round's one kernel call where every instance of the call corrects (three calls before). Returns
    :func:`correction_round`'s result."""
    rounds, values = correction_start(model, it, need, first, a_max, mu, opts)
    step = newton_direction(dataclasses.replace(model, **values), it, mu, x0, delta, opts.sweep, opts.terminal_rows)
    return correction_round(problem, cons, params, it, dataclasses.replace(step, K=None), model, mu, phi, slope, filt,
                            theta_max, theta_min, rounds, opts)


def second_order_correction(problem: Problem, cons: Constraints, params, it: Iterate, d: Optional[Direction],
                            model: Model, mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor,
                            theta_min: Tensor, need: Tensor, a_max: Tensor, first: tuple, lqr: Optional[LQR],
                            delta: Tensor, x0: Tensor, opts: IPOptions) -> Correction:
    """The corrections (module docstring) of the instances ``need (B,)``, from the residuals ``first`` of the rejected
    trial points (``(B, l, ...)`` each, the full step first) and the system ``lqr`` regularised by ``δ_w`` (``None``
    with compiled kernels, whose Newton step forms it from the model:
    :func:`~torchtraj.solvers.ipm.newton.newton_direction`). Of the iteration's step ``d`` only its kept
    factorisation is read (eager); ``None``: the system is factorised here. Eager, each round runs on every instance
    of the call, those that stopped masked; compiled on a batch, a round after some stopped runs on the others alone
    (:func:`_round_of_rows`)."""
    compiled = compiled_kernels(opts, it.X.device)
    kept = None if d is None else d.factor
    factor = None if compiled else kept if kept is not None else factorize_step(lqr, delta, opts)
    started = 0  # compiled, where every instance of the call corrects: the first round with the start, one kernel
    if compiled and opts.second_order_corrections > 0 and _round_rows(need) is None:
        rounds, values, _, best = kernel(started_round, True)(problem, cons, params, it, model, mu, phi, slope, filt,
                                                              theta_max, theta_min, need, a_max, first, delta, x0, opts)
        started = 1
    else:
        rounds, values = kernel(correction_start, compiled)(model, it, need, first, a_max, mu, opts)
        best = it  # the iterate after each instance's accepted step (where none is accepted it is not read)
    for _ in range(opts.second_order_corrections - started):
        if not bool(rounds.active.any()):
            break
        if compiled:  # the step's kernel forms the system; the residuals laid out as the model's own (views of the
            # expansion's rows): the same specialisation as the iteration's step
            corrected = dataclasses.replace(model, **{name: laid_out_as(value, getattr(model, name))
                                                      for name, value in values.items()})
            rows = _round_rows(rounds.active)
            if rows is not None:  # the instances still correcting alone, their results written back
                rounds, values, best = _round_of_rows(problem, cons, params, it, corrected, model, mu, phi, slope,
                                                      filt, theta_max, theta_min, rounds, best, delta, x0, opts, rows)
                continue
            step = kernel(newton_direction, True)(corrected, it, mu, x0, delta, opts.sweep, opts.terminal_rows)
        else:
            corrected = dataclasses.replace(model, **values)
            step = direction(lqr, newton_rhs(corrected, it, mu, x0, it.X.shape[-1]), delta, corrected, it, mu, None,
                             factor, False, opts.sweep, opts.terminal_rows)
        starting = best is it
        rounds, values, new, moved = kernel(correction_round, compiled)(
            problem, cons, params, it, dataclasses.replace(step, K=None), model, mu, phi, slope, filt, theta_max,
            theta_min, rounds, opts)
        best = moved if starting else pick(new, moved, best)  # an instance accepts in one round at most
    return Correction(found=rounds.found, alpha=rounds.alpha, unfiltered=rounds.unfiltered, it=best)


def _round_rows(active: Tensor) -> Optional[Tensor]:
    """The rows ``(R,)`` of the instances still correcting, with compiled kernels on a batch (a batch of one has
    kernels of its own); ``None`` where every instance is (one read of their count by the host)."""
    if active.shape[0] < DYNAMIC_FROM:
        return None
    rows = active.nonzero().squeeze(-1)
    return None if rows.numel() == active.shape[0] else rows


def _round_of_rows(problem: Problem, cons: Constraints, params, it: Iterate, corrected: Model, model: Model,
                   mu: Tensor, phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor,
                   rounds: Rounds, best: Iterate, delta: Tensor, x0: Tensor, opts: IPOptions, rows: Tensor) -> tuple:
    """A compiled round of the instances ``rows (R,)`` alone: their rows gathered laid out as the batch's, as many
    as a kernel takes (:func:`~torchtraj.solvers.ipm.compaction.kernel_rows`), and the first ``R`` of the results
    written back. A correction's instances end after different numbers of rounds, and those that ended are no longer
    factorised, solved and evaluated; an instance's arithmetic is the same as in the whole call. Returns ``(Rounds,
    corrected values, best iterate)`` of every instance."""
    index = kernel_rows(rows)
    it_r, corrected_r, model_r, *taken = gather_laid_out(
        (it, corrected, model, mu, phi, slope, filt, theta_max, theta_min, delta, x0), index)
    mu_r, phi_r, slope_r, filt_r, theta_max_r, theta_min_r, delta_r, x0_r = taken
    step = kernel(newton_direction, True)(corrected_r, it_r, mu_r, x0_r, delta_r, opts.sweep, opts.terminal_rows)
    part, values, new, moved = kernel(correction_round, True)(
        problem, cons, param_rows(params, index), it_r, dataclasses.replace(step, K=None), model_r, mu_r, phi_r,
        slope_r, filt_r, theta_max_r, theta_min_r, gather_laid_out(rounds, index), opts)
    kept = pick(new, moved, gather_rows(best, index))
    full_values = {name: getattr(model, name) for name in values}  # rows of ended instances are not read
    return _written(rounds, rows, part), _written(full_values, rows, values), _written(best, rows, kept)


def _written(full, rows: Tensor, part):
    """``full`` (a tensor, or a tuple, dict or dataclass of tensors) with its rows ``rows (R,)`` replaced by the
    first ``R`` rows of ``part``."""
    if isinstance(full, Tensor):
        return full.index_copy(0, rows, part[:rows.numel()])
    if isinstance(full, tuple):
        return tuple(_written(f, rows, p) for f, p in zip(full, part))
    if isinstance(full, dict):
        return {name: _written(value, rows, part[name]) for name, value in full.items()}
    return type(full)(**{f.name: _written(getattr(full, f.name), rows, getattr(part, f.name))
                         for f in dataclasses.fields(full)})


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
