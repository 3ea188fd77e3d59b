r"""One globalised step of eILQR (Horizon §II-F): the step truncated to the barrier's domain, its second-order
correction, then backtracking.

**Fraction to the boundary** (Wächter & Biegler 2006 §2.2, eq. (15); Nocedal & Wright 2006 §19.2, eq. (19.9)). The
Newton model of a log barrier is a quadratic that does not see the barrier's boundary ``t = 0``: in a stage with a
small weight the step runs through an active row and the merit, whose barrier is infinite there (its relaxed
extension stiff, ``w/δ²``), refuses every step size above the crossing. The step is first scaled by

.. math::  α_{\max} = \max\{α ∈ (0, 1] : t + α\,δt \ge (1 − τ)\,t\},\qquad δt = −G\,δz,\ τ = \max(τ_{\min}, 1 − w)

over the rows in the log region (``t ≥ δ``; the relaxed region below is quadratic, it has no boundary), the rows
linearised (exact for bounds). The multipliers move the same fraction, ``y ← y + α_max (y⁺ − y)``.

**Second-order correction at every trial step** (Nocedal & Wright 2006 §18.3, the correction of the Maratos effect;
IPOPT applies it at the first trial, Wächter & Biegler 2006 §2.4). The linearised dynamics leave a second-order defect
along the step, which ``γ ‖C‖₁`` charges more than the step gains: on the cart-pole's late iterations the merit rose at
every ``α ≥ 1/8`` of the step and the steps were cut to ``α = 1/16`` for hundreds of iterations, the defects rising at
each. Each trial ``α`` of ``p̄ = α_max p`` that the merit refuses is corrected once before the next is tried: the same
factorised KKT system (one vector solve; a refactorisation with the same ``ε`` where the inertia correction mixed
factorisations) gives ``q`` with ``∇c q = −r``, ``r = c(w + α p̄) − (1 − α) c(w)`` the constraints' departure from
their linearisation (at ``α = 1`` IPOPT's ``c(w) + c(w + p)`` system), and ``α p̄ + q`` is taken if it passes the Armijo
test of ``α`` (for the first ``second_order_trials`` trials; the shorter steps are tried plain in batched rounds,
:func:`~torchtraj.solvers.eilqr.merit.line_search`): a backtracking along the corrected arc ``α ↦ α p̄ + q(α)``,
whose defects are third order in ``α``. The first corrected trial the merit accepted was ``α = 1/2`` on the
cart-pole without bounds, where the plain step needed ``1/16`` and gained 25 times less.
Before the truncation and the correction at every trial, the correction was tried
only at ``α = 1``, which on the cart-pole crossed a control bound in most iterations of its last stages.
The multipliers of a corrected trial are the corrected system's, ``y + α α_max (ŷ⁺ − y)``.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...core.batching import param_rows
from ...core.compiled import kernel
from ...globalization.line_search import Accepted
from .initial_state import InitialRows
from .merit import armijo_bound, constraint_values, line_search, merit_at, slope, trial_steps, weighed
from .model import Iterate, Model
from .newton import Direction, direction, direction_alone, instances, pick_direction, resolve, write_direction

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


def corrected_step(problem, cons, params, model, it, x0, initial, d, p, alpha, eps, terminal_rows):
    """The second-order correction of the trial step ``p = α d`` (``alpha (B,)``): ``p + q`` with ``q`` the
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
    if d.factor is not None:
        soc = resolve(d, corrected, it, x0)
    else:
        soc = direction(corrected, it, x0, eps, terminal_rows)
    step = truncated(soc, it, alpha)
    return dataclasses.replace(step, dX=p.dX + soc.dX - d.dX, dU=p.dU + soc.dU - d.dU, ok=soc.ok)


def corrected_choice(problem, cons, params, model, it, x0, initial, d, step, m, bound, passed, need, a, alpha_max,
                     eps, gamma, weights, chosen, opts) -> tuple:
    """The correction of the trial ``a`` (a 0-d tensor) of the truncated step ``α_max d`` for the whole batch, in one
    function (a compiled solve's one kernel): :func:`corrected_step`, its merit, :func:`_judged` and
    :func:`chosen_step`. Returns ``(step, merit, passed, choice)``."""
    soc = corrected_step(problem, cons, params, model, it, x0, initial, d, step, a * alpha_max, eps,
                         opts.terminal_rows)
    ms = merit_at(problem, cons, params, it.X + soc.dX, it.U + soc.dU, x0, initial, gamma, weights, opts.record)
    step, m, passed = _judged(soc, ms, step, m, bound, passed, need)
    return step, m, passed, chosen_step(passed, step, it, a.expand(m.shape), chosen)


def _judged(soc, ms, step, m, bound, passed, need) -> tuple:
    """``(step, merit, passed)`` with the corrected step ``soc`` and its merit ``ms`` taken where a ``need`` instance
    (one whose plain trial failed) passes the Armijo ``bound`` with it."""
    taken = need & soc.ok & torch.isfinite(ms) & (ms <= bound)
    return pick_direction(taken, soc, step), torch.where(taken, ms, m), passed | taken


def _corrected(problem, cons, params, model, it, x0, initial, d, step, m, bound, passed, need, a, alpha_max, eps, gamma,
               weights, chosen, opts) -> tuple:
    """:func:`corrected_choice` for the ``need (B,)`` instances, those whose trial failed (the others keep their
    trial). Where ``d`` kept no factorisation (the inertia correction mixed them, or a compiled kernel made it) the
    corrected system is factorised again, for the instances that need it alone (a fixed start; one read of their
    count by the host): each instance's arithmetic is the same."""
    rows = _correction_rows(d, initial, need)
    whole = rows is None or rows.numel() == need.shape[0]
    if whole and opts.compile:
        return kernel(corrected_choice, True)(problem, cons, params, model, it, x0, initial, d, step, m, bound,
                                              passed, need, a, alpha_max, eps, gamma, weights, chosen, opts)
    corrected_k, merit_k = kernel(corrected_step, opts.compile), kernel(merit_at, opts.compile)
    alpha = a * alpha_max
    if whole:
        soc = corrected_k(problem, cons, params, model, it, x0, initial, d, step, alpha, eps, opts.terminal_rows)
        ms = merit_k(problem, cons, params, it.X + soc.dX, it.U + soc.dU, x0, initial, gamma, weights, opts.record)
    else:
        at_rows, it_rows, params_rows = instances(model, rows), instances(it, rows), param_rows(params, rows)
        soc = corrected_k(problem, cons, params_rows, at_rows, it_rows, x0[rows], None, instances(d, rows),
                          instances(step, rows), alpha[rows], eps[rows], opts.terminal_rows)
        merit = merit_k(problem, cons, params_rows, it_rows.X + soc.dX, it_rows.U + soc.dU, x0[rows], None,
                        gamma[rows], instances(weights, rows), opts.record)
        soc, ms = write_direction(step, rows, soc), torch.zeros_like(gamma).index_copy(0, rows, merit)
    step, m, passed = _judged(soc, ms, step, m, bound, passed, need)
    return step, m, passed, kernel(chosen_step, opts.compile)(passed, step, it, torch.full_like(m, float(a)), chosen)


def _correction_rows(d: Direction, initial, need: Tensor):
    """The instances ``need (B,)`` as indices ``(R,)`` where their correction is factorised again on their rows alone
    (:func:`_corrected`), None where the batch's is made (``d`` kept its factorisation, or a free start)."""
    return None if d.factor is not None or initial is not None else need.nonzero().squeeze(-1)


def _through(step: Direction, it: Iterate, alpha: Tensor) -> Direction:
    """The direction ``D`` whose move by ``alpha (B,)`` (``X + α D``, ``y + α (D_y − y)``) is ``step`` itself."""
    def inverse(t):
        return t / alpha.reshape(-1, *([1] * (t.dim() - 1)))

    moved = {name: getattr(it, name) + inverse(getattr(step, name) - getattr(it, name)) for name in _MULTIPLIERS}
    return dataclasses.replace(step, dX=inverse(step.dX), dU=inverse(step.dU), **moved)


def step_bound(model, d, it, weights, gamma: Tensor, l1: Tensor, tau_min, truncate: bool) -> tuple:
    """``(α_max, D m)`` ``(B,)``: the fraction to the boundary of ``d`` (1 where ``truncate`` is off) and the merit's
    directional derivative along the truncated step."""
    alpha_max = boundary_fraction(model, d, weights.weight, weights.delta, tau_min) if truncate \
        else torch.ones_like(gamma)
    return alpha_max, slope(model, truncated(d, it, alpha_max), gamma, l1)


def trial_point(problem, cons, params, d, it, alpha, x0, initial, gamma, weights, record):
    """The truncated step ``α d`` (``alpha (B,)``) and the merit ``(B,)`` at its point."""
    step = truncated(d, it, alpha)
    return step, merit_at(problem, cons, params, it.X + step.dX, it.U + step.dU, x0, initial, gamma, weights, record)


def chosen_step(passed: Tensor, step: Direction, it: Iterate, alpha: Tensor, chosen: Direction) -> Direction:
    """The direction whose move by ``alpha (B,)`` is ``step``, for the instances of ``passed (B,)``; ``chosen``
    elsewhere."""
    return pick_direction(passed, _through(step, it, alpha), chosen)


def tried(problem, cons, params, d, it, alpha_max, a, x0, initial, gamma, weights, reference, derivative, waiting,
          chosen, opts) -> tuple:
    """The trial ``a`` (a 0-d tensor) of the truncated step ``α_max d``: ``(step, merit, Armijo bound, passed,
    choice)``, ``passed (B,)`` where a ``waiting`` instance's merit is finite and within the bound from its
    ``reference`` and slope ``derivative``, and the choice :func:`chosen_step` of ``passed`` over ``chosen`` (the
    one a trial takes where no instance's step is corrected)."""
    step, m = trial_point(problem, cons, params, d, it, a * alpha_max, x0, initial, gamma, weights, opts.record)
    bound = armijo_bound(reference, derivative, a.reshape(1), opts)[:, 0]
    passed = waiting & torch.isfinite(m) & (m <= bound)
    return step, m, bound, passed, chosen_step(passed, step, it, a.expand(m.shape), chosen)


def first_tried(problem, cons, params, model, d, it, a, x0, initial, gamma, l1, weights, memory, pending, opts,
                truncate: bool) -> tuple:
    """The merit's weight (:func:`~torchtraj.solvers.eilqr.merit.weighed`), :func:`step_bound`, then :func:`tried`
    of the first trial ``a`` for the ``pending`` instances: ``(γ, memory, m(w), reference, α_max, D m, *trial, need,
    found, α, m)``, ``need (B,)`` the pending instances the trial failed, and the line search's ``found``, ``α`` and
    merit where no instance needs a correction (then every pending instance passed: the search ends here)."""
    gamma, memory, merit0, reference = weighed(d, gamma, pending, initial is not None, model.J, l1, memory, opts)
    alpha_max, derivative = step_bound(model, d, it, weights, gamma, l1, opts.boundary_fraction, truncate)
    trial = tried(problem, cons, params, d, it, alpha_max, a, x0, initial, gamma, weights, reference, derivative,
                  pending, d, opts)
    step, m, bound, passed, picked = trial
    return (gamma, memory, merit0, reference, alpha_max, derivative, *trial, pending & ~passed,
            *_recorded(~pending, torch.zeros_like(m), merit0, a, passed, m))


def _recorded(found, alpha, value, a, passed, m) -> tuple:
    """The line search's ``(found, α, merit)`` ``(B,)`` after the trial ``a`` that the instances ``passed`` took, at
    the merit ``m``."""
    return found | passed, torch.where(passed, a, alpha), torch.where(passed, m, value)


def first_trial_ahead(opts) -> bool:
    """Whether a solve makes its first trial point in its Newton step's kernel (:func:`direction_and_first_trial`):
    with compiled kernels, where :func:`globalized_step` corrects its first trial."""
    return bool(opts.compile and opts.globalization and opts.second_order_correction
                and min(opts.second_order_trials, opts.line_search_steps) > 0)


def _truncates(opts) -> bool:
    # with the paper's fixed weight the relaxed barrier is the problem (its rows may end in the quadratic branch):
    # no domain to stay in, and the minimum-time double integrator's fixed-weight solve then ended MAX_REGULARIZATION
    return opts.boundary_fraction is not None and opts.barrier_continuation


def direction_and_first_trial(model, it, x0, eps, problem, cons, params, initial, gamma, l1, weights, memory,
                              running, opts) -> tuple:
    """The Newton step of :func:`~torchtraj.solvers.eilqr.newton.direction` without its factorisation, and
    :func:`first_tried` of it for the ``running (B,)`` instances it factorised (``ok``), in one compiled kernel: one
    compiled call an iteration fewer. Where the inertia correction attempts some instances again, the step changes
    and the loop makes the first trial anew (:func:`globalized_step`); each instance's arithmetic is the same."""
    d = direction_alone(model, it, x0, eps, opts.terminal_rows)
    first = first_tried(problem, cons, params, model, d, it, trial_steps(opts, l1)[0], x0, initial, gamma, l1,
                        weights, memory, running & d.ok, opts, _truncates(opts))
    return d, first


def globalized_step(problem, cons, params, model, it, x0, initial, d, eps, gamma, l1, pending, opts, weights,
                    memory, first_trial=None):
    """The accepted step of the ``pending (B,)`` instances from the direction ``d`` (computed with ``eps (B,)``):
    ``(direction, Accepted, merit0 (B,), γ (B,), memory)``: the accepted ``α`` moves the iterate by the direction
    returned to the accepted point (the truncated step ``α α_max p``, or its correction ``α α_max p + q``). The
    merit's weight ``γ`` is updated from ``d``'s multipliers and the ``memory`` records the iterate
    (:func:`~torchtraj.solvers.eilqr.merit.weighed`); the Armijo test starts from the nonmonotone reference (the
    largest merit the memory holds, :class:`~torchtraj.solvers.eilqr.merit.MeritMemory`). ``first_trial``: the
    outputs of :func:`first_tried` for ``d``, ``pending`` and these ``gamma`` and ``memory``, where its Newton step's
    kernel made them (:func:`direction_and_first_trial`)."""
    weigh = (d, gamma, pending, initial is not None, model.J, l1, memory, opts)
    if not opts.globalization:
        gamma, memory, merit0, _ = weighed(*weigh)
        ls = line_search(problem, cons, params, it.X, it.U, x0, initial, d, merit0, slope(model, d, gamma, l1),
                         gamma, pending, trial_steps(opts, merit0), opts, weights)
        return d, ls, merit0, gamma, memory
    truncate = _truncates(opts)
    steps = trial_steps(opts, l1)
    corrected_trials = min(opts.second_order_trials, steps.shape[0]) if opts.second_order_correction else 0
    alpha_max = derivative = first = None
    if corrected_trials and bool(pending.any()):  # the weight and the step's bound in the first trial's kernel
        gamma, memory, merit0, reference, alpha_max, derivative, *first = first_trial if first_trial is not None \
            else kernel(first_tried, opts.compile)(problem, cons, params, model, d, it, steps[0], x0, initial, gamma,
                                                   l1, weights, memory, pending, opts, truncate)
    else:
        gamma, memory, merit0, reference = weighed(*weigh)
    found, alpha, value, chosen = ~pending, torch.zeros_like(merit0), merit0, d
    for a in steps[:corrected_trials] if first is not None else ():  # at most two host reads a trial
        if first is not None:  # the first trial, made with the weight and the bound
            (step, m, bound, passed, picked, need, *after), first = first, None
            if not bool(need.any()):  # every pending instance passed it: the search ends here
                found, alpha, value = after
                return picked, Accepted(found=found, alpha=alpha, values=(value,)), merit0, gamma, memory
        else:
            waiting = pending & ~found
            if not bool(waiting.any()):
                break
            step, m, bound, passed, picked = kernel(tried, opts.compile)(
                problem, cons, params, d, it, alpha_max, a, x0, initial, gamma, weights, reference, derivative,
                waiting, chosen, opts)
            need = waiting & ~passed
        if bool(need.any()):
            step, m, passed, picked = _corrected(problem, cons, params, model, it, x0, initial, d, step, m, bound,
                                                 passed, need, a, alpha_max, eps, gamma, weights, chosen, opts)
        chosen = picked
        found, alpha, value = _recorded(found, alpha, value, a, passed, m)
    refused = pending & ~found
    if steps.shape[0] > corrected_trials and bool(refused.any()):  # the shorter steps plain, in batched rounds
        if alpha_max is None:  # no trial was corrected
            alpha_max, derivative = kernel(step_bound, opts.compile)(model, d, it, weights, gamma, l1,
                                                                     opts.boundary_fraction, truncate)
        p = truncated(d, it, alpha_max)
        rest = line_search(problem, cons, params, it.X, it.U, x0, initial, p, reference, derivative, gamma, refused,
                           steps[corrected_trials:], opts, weights)
        chosen = pick_direction(refused & rest.found, p, chosen)
        found, alpha = found | rest.found, torch.where(refused, rest.alpha, alpha)
        value = torch.where(refused & rest.found, rest.values[0], value)
    return chosen, Accepted(found=found, alpha=alpha, values=(value,)), merit0, gamma, memory
