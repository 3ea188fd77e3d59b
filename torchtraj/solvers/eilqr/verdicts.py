r"""An eILQR iteration's per-instance decisions (:func:`~torchtraj.solvers.eilqr.solver.solve_eilqr`), as functions of
tensors alone: the tests of the iterate after its expansion, and the move with the bookkeeping after the line search.

Each is joined to a kernel (:func:`expanded`: the expansion and its tests; :func:`advanced`: the move and the
regularisation's schedule; :func:`advanced_expanded`: both, from one iteration's step to the next one's tests;
:func:`advanced_ahead`: with them the barrier's next weight (:func:`reweighted`) and the next iteration's Newton step
and first trial point, a compiled solve's one kernel from one step to the next), so that a compiled solve
(``EILQROptions.compile``) makes them part of one kernel call instead of some sixty eager calls each between kernels;
an eager solve runs the same functions but the last. Every decision is a mask on the batch: an instance's verdicts
read its own values alone.

**After the expansion** (:func:`examined`): an instance with a non-finite model stops ``NON_FINITE``; at the
barrier's last weight one whose KKT error is below the tolerance (or whose last full step the dtype could not resolve)
has ``CONVERGED``; at an earlier weight the same test ends the stage (``advance``: the barrier continuation,
:mod:`~torchtraj.solvers.eilqr.continuation`); an iterate past ``max_state`` has ``DIVERGED``.

**After the line search** (:func:`advanced`): the accepted ``α`` moves the instances that took a step, and Fig. 5's
adaptive ``ε_reg`` sets the next iteration's regularisation floor (:mod:`~torchtraj.solvers.eilqr.solver`'s
docstring); a floor past ``regularization_max`` stops the instance ``MAX_REGULARIZATION``.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...core.masks import RowPicker, where_rows
from ...core.status import Status
from .continuation import next_weight, stage_done, weights_for
from .globalization import direction_and_first_trial
from .merit import model_infeasibility
from .model import Iterate, Model, expand, with_weight
from .newton import Direction

#: A full Newton step of at most this many rounding errors of the iterate (``ε (1 + max(|X|∞, |U|∞))``) ends the
#: solve as converged at the dtype's resolution (the solver's docstring).
RESOLVED = 10.0


def examined(model: Model, X: Tensor, x0: Tensor, status: Tensor, weight: Tensor, final: float, tol: float,
             unresolved: Tensor, opts) -> tuple:
    """The tests of the expanded iterate (module docstring): ``(status, advance, ‖C‖₁, max |defect|, ‖(h, h_N)‖∞)``,
    ``(B,)`` each, from the ``model`` at the states ``X``, the ``status`` before, the barrier's ``weight (B,)`` and
    its ``final`` one, and where the last full step was ``unresolved``."""
    # compared with an int: traced in this kernel, ``status == Status.RUNNING`` gave a Python ``False`` (PyTorch 2.13)
    running = status == int(Status.RUNNING)
    status = torch.where(running & ~model.finite, int(Status.NON_FINITE), status)
    last_stage = weight <= final
    # the paper's fixed weight solves the soft problem, whose stationarity takes the barrier's multipliers
    # w s(t): the primal-dual z must be them to the tolerance (the t-scaled complementarity lets them differ
    # by tol / t, 1e-5 / 1e-5 = 1 at an active row in float32)
    error = model.error if opts.barrier_continuation else torch.maximum(model.error, model.barrier_gap)
    status = torch.where(running & model.finite & last_stage & ((error <= tol) | unresolved),
                         int(Status.CONVERGED), status)
    # the barrier continuation: a stage whose KKT error is within κ_ε w (or whose step the dtype no longer
    # resolves) ends, the next weight's model differs only in the barrier's terms
    advance = running & model.finite & ~last_stage & (stage_done(model.error, weight, opts) | unresolved)
    diverged = running & (X.abs().flatten(1).amax(-1) > opts.max_state)
    status = torch.where(diverged & (status == int(Status.RUNNING)), int(Status.DIVERGED), status)
    return (status, advance, model_infeasibility(model, x0, X), model.defects.abs().flatten(1).amax(-1),
            _equality(model))


def expanded(problem, cons, params, it: Iterate, x0: Tensor, rows, weights, record, status: Tensor, final: float,
             tol: float, unresolved: Tensor, opts) -> tuple:
    """:func:`~torchtraj.solvers.eilqr.model.expand` at ``it`` and :func:`examined` of its model:
    ``(model, *tests)``."""
    model = expand(problem, cons, params, it, x0, rows, weights, record)
    return (model, *examined(model, it.X, x0, status, weights.weight, final, tol, unresolved, opts))


def step(it: Iterate, d: Direction, alpha: Tensor, take: Tensor) -> Iterate:
    """``it`` moved by ``α`` along ``d`` where ``take (B,)``: the primal step and ``y ← y + α (y⁺ − y)``."""
    def move(x, dx):
        return where_rows(take, x + alpha.reshape(-1, *([1] * (x.dim() - 1))) * dx, x)

    return Iterate(X=move(it.X, d.dX), U=move(it.U, d.dU), lam=move(it.lam, d.lam - it.lam),
                   nu=move(it.nu, d.nu - it.nu), nuN=move(it.nuN, d.nuN - it.nuN), mu0=move(it.mu0, d.mu0 - it.mu0),
                   z=move(it.z, d.z - it.z), zN=move(it.zN, d.zN - it.zN))


def advanced(it: Iterate, d: Direction, alpha: Tensor, found: Tensor, factored: Tensor, running: Tensor,
             eps: Tensor, floor: Tensor, last: Tensor, status: Tensor, iterations: Tensor, opts) -> tuple:
    """The move and the bookkeeping after the line search (module docstring), from the accepted ``alpha (B,)``
    (``found`` where one was), the instances ``factored`` and ``running``, the step's regularisation ``eps``, the
    last ``floor`` and nonzero ``last`` one: ``(iterate, take, unresolved, floor, last, status, iterations, step
    size)``, ``take`` where a step was taken, the step size 0 elsewhere."""
    take = factored & found
    # a full step below the dtype's resolution of the iterate: it cannot move any further in this dtype
    unresolved = take & (alpha == 1.0) & (_largest(d.dX, d.dU) <= RESOLVED * torch.finfo(it.X.dtype).eps
                                          * (1 + _largest(it.X, it.U)))
    moved = step(it, d, alpha, take)
    last = torch.where(take & (eps > 0), eps, last)
    # Fig. 5's adaptive ε_reg: a step the merit refuses or cuts short asks for more regularisation (a shorter,
    # more gradient-like step) at the next iteration, a full one for less, down to none
    # an instance whose inertia correction ran out of attempts below ``regularization_max`` keeps its iterate and
    # starts the next iteration's correction above the largest ε tried (IPOPT's correction goes on up to
    # δ_w^max; one iteration's attempts from a carried ε of 1e-20 reach only about 1e-9)
    short = (factored & (~found | (alpha < opts.short_step))) | (running & ~factored)
    larger = torch.clamp(opts.regularization_increase * torch.maximum(floor, eps), min=opts.regularization_first)
    smaller = opts.regularization_decrease * eps
    smaller = torch.where(smaller < opts.regularization_min, 0.0, smaller)
    full = take & (alpha == 1.0)
    # a step cut to α ≥ short_step: the model held over α of the step only; the regularised step's length goes
    # as 1/ε where ε dominates the reduced Hessian's smallest eigenvalue, so ε/α (at most ×κ_w^+) asks for
    # a step about as long as the accepted one (a trust region's radius set from the accepted step)
    growth = torch.clamp(1.0 / torch.clamp(alpha, min=opts.short_step), max=opts.regularization_increase)
    partial = eps * growth if opts.regularization_partial else eps
    floor = torch.where(short, larger, torch.where(full, smaller, torch.where(take, partial, floor)))
    blown = running & (floor > opts.regularization_max)
    status = torch.where(blown, int(Status.MAX_REGULARIZATION), status)
    return (moved, take, unresolved, floor, last, status, iterations + running.long(),
            torch.where(take, alpha, 0.0))


def advanced_expanded(problem, cons, params, x0: Tensor, rows, weights, record, final: float, tol: float,
                      it: Iterate, d: Direction, alpha: Tensor, found: Tensor, factored: Tensor, running: Tensor,
                      eps: Tensor, floor: Tensor, last: Tensor, status: Tensor, iterations: Tensor, opts) -> tuple:
    """:func:`advanced`, then :func:`expanded` at the iterate it reached (the next iteration's start), in one call:
    ``(iterate, take, unresolved, floor, last, iterations, step size, (model, status, *tests))``."""
    moved, take, unresolved, floor, last, status, iterations, size = advanced(
        it, d, alpha, found, factored, running, eps, floor, last, status, iterations, opts)
    return (moved, take, unresolved, floor, last, iterations, size,
            expanded(problem, cons, params, moved, x0, rows, weights, record, status, final, tol, unresolved, opts))


def reweighted(model: Model, it: Iterate, weights, memory, advance: Tensor, final: float, opts) -> tuple:
    """What the tests of an expanded iterate ask of the next iteration: ``(iterate, weights, model, memory)``, the
    iterate with the model's safeguarded multipliers, and where a stage ended (``advance (B,)``) the barrier's next
    weight, the model with it (:func:`~torchtraj.solvers.eilqr.model.with_weight`) and the merit memory emptied (its
    merits were of another weight); the other instances keep their own."""
    it = dataclasses.replace(it, z=model.z, zN=model.zN)
    weights = weights_for(torch.where(advance, next_weight(weights.weight, final, opts), weights.weight), opts)
    new, pick = with_weight(model, weights), RowPicker(advance)
    model = dataclasses.replace(model, **{name: pick(getattr(new, name), getattr(model, name)) for name in _WEIGHED})
    return it, weights, model, memory.forget(advance)


def advanced_ahead(problem, cons, params, x0: Tensor, rows, weights, record, final: float, tol: float, it: Iterate,
                   d: Direction, alpha: Tensor, found: Tensor, factored: Tensor, running: Tensor, eps: Tensor,
                   floor: Tensor, last: Tensor, status: Tensor, iterations: Tensor, gamma: Tensor, memory,
                   opts) -> tuple:
    """:func:`advanced_expanded`, :func:`reweighted` and the next iteration's first attempt, the Newton step from
    ``floor`` and its first trial point
    (:func:`~torchtraj.solvers.eilqr.globalization.direction_and_first_trial`, with the merit's weight ``gamma`` and
    ``memory`` of this iteration's line search), in one call: a compiled solve's one kernel from one iteration's step
    to the next one's first trial. An instance the tests stop has a step made that is never taken. Returns
    ``(iterate, take, unresolved, floor, last, iterations, step size, (model, status, *tests), weights, memory,
    (direction, first trial))``."""
    moved, take, unresolved, floor, last, iterations, size, tests = advanced_expanded(
        problem, cons, params, x0, rows, weights, record, final, tol, it, d, alpha, found, factored, running, eps,
        floor, last, status, iterations, opts)
    model, status, advance, l1 = tests[:4]
    moved, weights, model, memory = reweighted(model, moved, weights, memory, advance, final, opts)
    ahead = direction_and_first_trial(model, moved, x0, floor, problem, cons, params, rows, gamma, l1, weights,
                                      memory, status == int(Status.RUNNING), opts)
    return (moved, take, unresolved, floor, last, iterations, size, (model, *tests[1:]), weights, memory, ahead)


#: the fields of a :class:`~torchtraj.solvers.eilqr.model.Model` that the barrier's weight sets
_WEIGHED = ("J", "lz", "lNx", "Lzz", "LNxx", "zw", "zwN", "sigma", "sigmaN", "complementarity", "error", "barrier_gap")


def _largest(X: Tensor, U: Tensor) -> Tensor:
    """``max(|X|∞, |U|∞)`` per instance ``(B,)``."""
    return torch.cat([X.flatten(1), U.flatten(1)], -1).abs().amax(-1)


def _equality(model: Model) -> Tensor:
    """``‖(h, h_N)‖∞ (B,)`` of the model."""
    B = model.J.shape[0]
    return torch.cat([model.h.reshape(B, -1).abs(), model.hN.abs(), model.J.new_zeros(B, 1)], -1).amax(-1)
