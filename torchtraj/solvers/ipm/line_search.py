r"""The interior-point method's filter line search (Wächter & Biegler 2006 §2.3-2.4, FATROP §III).

**Fraction to boundary**: ``τ = max(τ_min, 1 − μ)``; ``s`` and ``z`` keep a fraction ``1 − τ`` of their distance
to zero: the largest primal step ``α_max`` and, for ``z``, its own step ``α_z``. After the step ``z`` is clipped to
``[μ/(κ_Σ s), κ_Σ μ/s]``.

**Filter line search** on the constraint violation ``θ = ‖c‖₁`` and the barrier objective
``φ = J − μ Σ log s``, over the step sizes ``α_max β^j``: a trial point is acceptable to the
:class:`~torchtraj.globalization.filter.Filter` and below ``θ_max``; under the switching condition

.. math::  ∇φ^T Δ < 0 \quad\text{and}\quad α (−∇φ^T Δ)^{s_φ} > δ\, θ^{s_θ}

with ``θ ≤ θ_min`` it is an f-type step and must meet the Armijo condition ``φ(α) ≤ φ + η_φ α ∇φ^T Δ``; otherwise
it must decrease ``θ`` or ``φ`` sufficiently, ``θ(α) ≤ (1 − γ_θ) θ`` or ``φ(α) ≤ φ − γ_φ θ``. After the step the
filter is augmented with ``((1 − γ_θ) θ, φ − γ_φ θ)`` unless the step met both the switching and the Armijo
condition (W&B 2006 step A-7, whichever of the two tests accepted it: a step of ``θ > θ_min`` that happens to meet
them adds no entry either, as in IPOPT). The step sizes are evaluated in rounds of
``line_search_parallel``, every instance and step size of a round in one batched evaluation (multiple shooting
needs no rollout) by the shared driver :func:`~torchtraj.globalization.line_search.backtrack`; the full step is
usually accepted in the first round, which in a large compiled batch evaluates it alone
(``IPOptions.line_search_first``). With compiled kernels the kernel of that round also makes the step that the
search is where the round settles it (:func:`settled_step`: every instance found a step, none needs a correction),
and the host reads that alone. A step below round-off (IPOPT's tiny step) is taken whole, with no filter entry.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from ...core.batching import param_rows, rows_of
from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...core.one_pass import problem_values
from ...core.problem import Problem
from ...globalization.filter import Filter
from ...globalization.line_search import Accepted, backtrack
from .compaction import gather_laid_out, gather_rows, kernel_rows, pick
from .iterate import Iterate, Model
from .kernels import compiled_kernels, eager_kernels, kernel_of, uses_graphs
from .newton import Direction
from .options import IPOptions


def _max_step(value: Tensor, step: Tensor, tau: Tensor) -> Tensor:
    """Largest ``α ≤ 1`` with ``value + α step ≥ (1 − τ) value`` (fraction to boundary), ``(B,)``."""
    ratio = torch.where(step < 0, -tau.unsqueeze(-1) * value / torch.where(step < 0, step, -1.0), 1.0)
    return torch.cat([ratio, ratio.new_ones(ratio.shape[0], 1)], -1).amin(-1)


def log_barrier(s: Tensor, sN: Tensor, knots: Tensor) -> Tensor:
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


def step_and_round_off(it: Iterate, d: Direction) -> tuple:
    """``(|Δw|∞, 10 ε (1 + |w|∞))``, ``(B,)`` each, of the primal step ``Δw = (ΔX, ΔU)``: a step below the second
    is at round-off (IPOPT's tiny step)."""
    scale = 1.0 + torch.cat([it.X.flatten(1), it.U.flatten(1)], -1).abs().amax(-1)
    size = torch.cat([d.dX.flatten(1), d.dU.flatten(1)], -1).abs().amax(-1)
    return size, 10 * torch.finfo(it.X.dtype).eps * scale


def fraction_to_boundary(it: Iterate, d: Direction, tau: Tensor) -> tuple:
    """The largest primal and dual steps ``(B,)`` that keep ``s`` and ``z`` at least ``1 − τ`` of their distance to
    zero."""
    a_max = _max_step(torch.cat([it.s.flatten(1), it.sN], -1), torch.cat([d.ds.flatten(1), d.dsN], -1), tau)
    a_dual = _max_step(torch.cat([it.z.flatten(1), it.zN], -1), torch.cat([d.dz.flatten(1), d.dzN], -1), tau)
    return a_max, a_dual


#: The batch size from which a compiled solve on a CPU evaluates the full step alone in its first round of step sizes
#: (``IPOptions.line_search_first`` ``None``): there the trial points' evaluation is computation, not overhead, and
#: the few instances that reject the full step cost a further round less than every instance's other candidates.
FULL_STEP_ALONE_FROM = 128


def batch_first_round(opts: IPOptions, B: int, device: torch.device) -> IPOptions:
    """``opts`` with ``line_search_first`` decided once for the batch of ``B`` (the option's docstring; left ``None``,
    :func:`first_round` reads ``line_search_parallel``), so that an instance's rounds do not depend on how many others
    are still iterating."""
    alone = compiled_kernels(opts, device) and device.type == "cpu" and B >= FULL_STEP_ALONE_FROM
    return dataclasses.replace(opts, line_search_first=1) if alone and opts.line_search_first is None else opts


def first_round(opts: IPOptions) -> int:
    """How many step sizes the first round evaluates."""
    return opts.line_search_first or max(1, opts.line_search_parallel)


def step_measures(model: Model, it: Iterate, d: Direction, mu: Tensor, opts: IPOptions):
    """At the current iterate, for the line search (``(B,)`` each): the largest primal and dual steps of the
    fraction-to-boundary rule, ``τ = max(τ_min, 1 − μ)``, the barrier objective ``φ`` and its slope ``∇φ · Δ``;
    whether the step is at round-off (IPOPT's tiny step, :func:`step_and_round_off`), and the candidate step sizes
    ``α_max β^j`` ``(B, line_search_steps)``: in one kernel where the solve's kernels are compiled."""
    a_max, a_dual = fraction_to_boundary(it, d, torch.clamp(1.0 - mu, min=opts.fraction_to_boundary))
    knots = model.knots
    phi = model.J - mu * log_barrier(it.s, it.sN, knots)
    barrier_slope = torch.where(knots > 0, d.ds / it.s, 0.0).flatten(1).sum(-1) + (d.dsN / it.sN).sum(-1)
    slope = _cost_directional(model, it, d) - mu * barrier_slope
    size, round_off = step_and_round_off(it, d)
    powers = opts.line_search_decrease ** torch.arange(opts.line_search_steps, dtype=it.X.dtype, device=it.X.device)
    return a_max, a_dual, phi, slope, size < round_off, a_max.unsqueeze(1) * powers


def trial(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model, mu: Tensor,
          phi: Tensor, slope: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor, alphas: Tensor,
          opts: IPOptions, test_alphas: Optional[Tensor] = None):
    """The filter tests (module docstring) at the step sizes ``alphas (B, l)``, all evaluated at once, from the
    reference barrier objective ``phi``, its slope ``slope`` (:func:`step_measures`) and ``model.theta``; the
    switching and Armijo conditions take ``test_alphas (B, l)`` where given (the watchdog's stored step size).

    Returns ``accept (B, l)``, ``unfiltered (B, l)``: the step met the switching and the Armijo conditions (no
    filter entry is added for those, whether or not ``θ ≤ θ_min`` made it an f-type step), ``blocked (B, l)``:
    rejected by the filter alone (the filter reset heuristic counts those), the candidates' ``θ (B, l)`` and their
    residuals ``(defects, h, hN, g + s, gN + sN)`` (``(B, l, ...)`` each; a second-order correction starts from
    them)."""
    B, L = alphas.shape
    knots = model.knots
    a4 = alphas.reshape(B, L, 1, 1)
    Xc = it.X.unsqueeze(1) + a4 * d.dX.unsqueeze(1)
    Uc = it.U.unsqueeze(1) + a4 * d.dU.unsqueeze(1)
    sc = it.s.unsqueeze(1) + a4 * d.ds.unsqueeze(1)
    sNc = it.sN.unsqueeze(1) + alphas.unsqueeze(-1) * d.dsN.unsqueeze(1)
    values = problem_values(problem, cons, Xc, Uc, params, record=opts.record)
    Jc = values.cost
    defects = values.f - Xc[..., 1:, :]
    parts = (defects, values.h, values.hN, (values.g + sc) * knots, values.gN + sNc)
    theta_c = torch.cat([p.reshape(B, L, -1).abs() for p in parts], -1).sum(-1)
    phi_c = Jc - mu.unsqueeze(1) * log_barrier(sc, sNc, knots)
    theta, phi, slope = model.theta.unsqueeze(1), phi.unsqueeze(1), slope.unsqueeze(1)
    tested = alphas if test_alphas is None else test_alphas
    switching = (slope < 0) & (tested * (-slope).clamp_min(0) ** opts.switching_phi_power
                               > opts.switching * theta ** opts.switching_theta_power)
    f_type = switching & (theta <= theta_min.unsqueeze(1))
    # compared up to ten rounding errors of the reference value (IPOPT's and FATROP's ``compare_le``): near a
    # solution in float32 the predicted decrease falls below one rounding error of φ and the exact tests would
    # refuse every step
    eps = 10 * torch.finfo(phi.dtype).eps
    armijo = phi_c - (phi + opts.armijo * tested * slope) <= eps * phi.abs()
    decrease = (theta_c - (1.0 - opts.filter_theta) * theta <= eps * theta) \
        | (phi_c - (phi - opts.filter_phi * theta) <= eps * phi.abs())
    finite = torch.isfinite(theta_c) & torch.isfinite(phi_c)
    sufficient = finite & (theta_c <= theta_max.unsqueeze(1)) & torch.where(f_type, armijo, decrease)
    acceptable = filt.acceptable(theta_c, phi_c)
    # no filter entry after a step that met the switching and Armijo conditions, whichever test accepted it (W&B
    # 2006 step A-7 and IPOPT's UpdateForNextIteration: the θ ≤ θ_min of an f-type step does not enter)
    return sufficient & acceptable, switching & armijo, sufficient & ~acceptable, theta_c, parts


def measured_first_round(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model,
                         mu: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor, pending: Tensor,
                         corrects: bool, opts: IPOptions) -> tuple:
    """:func:`step_measures`, the :func:`trial` of the first round of step sizes (the first ``line_search_parallel``
    candidates) and the :class:`Step` where that round settles the line search (:func:`settled_step`) in one
    function: a compiled solve's one kernel call for all three, where it was three kernel calls and some fifty eager
    ones (the backtracking's bookkeeping, the filter's entry, the step). Returns ``(measures, first round, settled,
    step)``, the first two the tuples their functions return."""
    measures = step_measures(model, it, d, mu, opts)
    _, _, phi, slope, _, candidates = measures
    alphas = candidates[:, :first_round(opts)].contiguous()
    opening = trial(problem, cons, params, it, d, model, mu, phi, slope, filt, theta_max, theta_min, alphas, opts)
    return (measures, opening, *settled_step(it, d, model, mu, filt, measures, alphas, opening, pending, corrects,
                                             opts))


def _start(measures: tuple) -> Accepted:
    """The backtracking's start (:func:`~torchtraj.globalization.line_search.backtrack`) from the :func:`step_measures`:
    the tiny steps found, taken whole with no filter entry (``(unfiltered, blocked)`` the values it keeps)."""
    a_max, _, _, _, tiny, _ = measures
    return Accepted(found=tiny, alpha=torch.where(tiny, a_max, 0.0), values=(tiny, torch.zeros_like(tiny)))


def settled_step(it: Iterate, d: Direction, model: Model, mu: Tensor, filt: Filter, measures: tuple, alphas: Tensor,
                 opening: tuple, pending: Tensor, corrects: bool, opts: IPOptions) -> tuple:
    """The outcome of :func:`line_search` where its first round of step sizes ``alphas (B, l)``, with the trial
    points ``opening`` (:func:`trial`), settles it: every ``pending`` instance takes a tiny step or accepts one of
    the round's candidates, and none needs a second-order correction (``corrects``: the search makes them). The
    same values as the search's :func:`~torchtraj.globalization.line_search.backtrack` (its first round alone,
    which reads nothing back) and its end. Returns ``(settled, step)``: a 0-dim boolean, whether the round settles
    the search for every instance, and the :class:`Step` that it is then."""
    a_max, a_dual, phi, _, tiny, _ = measures
    accept, unfiltered, blocked, theta_c, _ = opening
    before = torch.cat([torch.zeros_like(blocked[:, :1]), blocked[:, :-1]], 1)  # each candidate's predecessor
    steps = backtrack(alphas, alphas.shape[1], lambda _: (accept, (unfiltered, before)), pending, _start(measures))
    found, alpha, (unfiltered, blocked) = steps.found, steps.alpha, steps.values
    open_rows = pending & ~found
    if corrects:  # line_search's `need`: the full step rejected with θ not below the current one
        open_rows = open_rows | (pending & ~tiny & ~accept[:, 0] & (theta_c[:, 0] >= model.theta))
    filt = filt.add(found & ~unfiltered, (1.0 - opts.filter_theta) * model.theta, phi - opts.filter_phi * model.theta)
    step = Step(advance(it, d, alpha, a_dual, mu, model.knots, opts), alpha, found, filt,
                shortened=found & ~tiny & (alpha < a_max), blocked=found & blocked, tiny=pending & tiny)
    return ~open_rows.any(), step


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
    """The outcome of a line search: the new iterate ``it``, the primal step size ``alpha (B,)``, whether one was
    found ``(B,)``, and the filter after it; for the watchdog (:mod:`~torchtraj.solvers.ipm.watchdog`), ``shortened
    (B,)``: the first trial point was rejected and the step taken is a shorter one of the same direction; for the
    filter reset heuristic, ``blocked (B,)``: the last trial point rejected before the step taken was rejected by
    the filter alone; ``tiny (B,)``: the step was at round-off (IPOPT's tiny step, taken whole)."""

    it: Iterate
    alpha: Tensor
    found: Tensor
    filter: Filter
    shortened: Optional[Tensor] = None
    blocked: Optional[Tensor] = None
    tiny: Optional[Tensor] = None


def line_search(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model, mu: Tensor,
                filt: Filter, theta_max: Tensor, theta_min: Tensor, pending: Tensor, opts: IPOptions,
                correct: Optional[Callable] = None, first: Optional[tuple] = None) -> Step:
    """Backtracking over ``α_max β^j``, ``line_search_parallel`` step sizes per batched evaluation (the first round
    :func:`first_round`'s); a further round only while a ``pending`` instance has found no acceptable step.
    ``correct(need, α_max, φ, ∇φ·Δ, residuals)``: the second-order correction (:mod:`~torchtraj.solvers.ipm.soc`)
    of the instances ``need (B,)`` whose first trial point was rejected with ``θ`` not below the current one; where
    it finds a step, that step is taken instead of a shorter one (W&B 2006 §2.3). ``first``: the measures and the
    first round's trial points of a compiled solve where its kernel has made them already, and the round did not
    settle the search (:func:`~torchtraj.solvers.ipm.conclusion.first_round_concluded`)."""
    # compiled kernels: the measures, the first round's trial points and the step where that round settles the
    # search, in one kernel call (evaluated even where every instance took a tiny step: the answers are the same)
    ready = []  # the first round, evaluated with the measures
    if first is not None:
        measures, opening = first
        ready.append(opening)
    elif compiled_kernels(opts, it.X.device):
        measures, opening, settled, step = kernel_of(measured_first_round, opts, it.X.device)(
            problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, pending, correct is not None, opts)
        if bool(settled):
            return step
        ready.append(opening)
    else:
        measures = kernel_of(step_measures, opts, it.X.device)(model, it, d, mu, opts)
    a_max, a_dual, phi, slope, tiny, candidates = measures  # tiny: IPOPT's tiny step, whole, no filter entry

    first = []  # the first round's rejected full steps, for the second-order correction
    previous = [torch.zeros_like(pending)]  # was the last candidate of the previous round blocked by the filter

    def acceptable(alphas, rows=None):  # `rows`: a later round's instances still looking, alone (not with graphs)
        if rows is None:
            accept, unfiltered, blocked, theta_c, parts = ready.pop() if ready else kernel_of(
                trial, opts, it.X.device)(problem, cons, params, it, d, model, mu, phi, slope, filt, theta_max,
                                          theta_min, alphas, opts)
            last = previous[0]
        else:  # the rows alone; compiled, laid out as the batch's and as many as a kernel takes (direction_of_rows)
            index, take = (rows, gather_rows) if eager else (kernel_rows(rows), gather_laid_out)
            R = rows.numel()
            if alphas.dim() == 2 and index is not rows:  # the step sizes of the rows repeated as the rows are
                alphas = alphas.repeat(index.numel() // R, 1)
            out = kernel_of(trial, opts, it.X.device)(
                problem, cons, param_rows(params, index), *(take(v, index) for v in (it, d, model, mu, phi, slope, filt,
                                                                                    theta_max, theta_min)),
                alphas, opts)
            if index is not rows:  # the first R, each row once
                out = rows_of(out, torch.arange(R, device=rows.device))
            accept, unfiltered, blocked, theta_c, parts = out
            last = previous[0][rows]
        if not first:
            first.append((accept[:, 0], theta_c[:, 0], parts, blocked[:, 0]))
        before = torch.cat([last.unsqueeze(1), blocked[:, :-1]], 1)  # each candidate's predecessor
        previous[0] = blocked[:, -1] if rows is None else previous[0].index_copy(0, rows, blocked[:, -1])
        return accept, (unfiltered, before)

    eager = eager_kernels(opts, it.X.device)

    # asked before the first round too: where every pending instance took a tiny step, no candidate is evaluated
    steps = backtrack(candidates, max(1, opts.line_search_parallel), acceptable, pending, _start(measures),
                      sync_first=True,
                      by_rows=not uses_graphs(opts, it.X.device),  # graphs keep the batch's shape
                      first_round=first_round(opts))
    found, alpha, (unfiltered, blocked) = steps.found, steps.alpha, steps.values
    shortened = found & ~tiny & (alpha < a_max)
    corrected = None
    if correct is not None and first:
        accepted, theta_first, parts, blocked_first = first[0]
        need = pending & ~tiny & ~accepted & (theta_first >= model.theta)
        if bool(need.any()):
            corrected = correct(need, a_max, phi, slope, parts)
            alpha = torch.where(corrected.found, corrected.alpha, alpha)
            unfiltered = torch.where(corrected.found, corrected.unfiltered, unfiltered)
            blocked = torch.where(corrected.found, blocked_first, blocked)
            shortened = shortened & ~corrected.found
            found = found | corrected.found
    filt = filt.add(found & ~unfiltered, (1.0 - opts.filter_theta) * model.theta, phi - opts.filter_phi * model.theta)
    new_it = kernel_of(advance, opts, it.X.device)(it, d, alpha, a_dual, mu, model.knots, opts)
    if corrected is not None:
        new_it = pick(corrected.found, corrected.it, new_it)
    return Step(new_it, alpha, found, filt, shortened=shortened, blocked=found & blocked, tiny=pending & tiny)
