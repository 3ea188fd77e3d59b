r"""The end of an interior-point iteration (:func:`~torchtraj.solvers.ipm.solver.run`, step 5): the step taken and
the per-instance counts it moves.

After the line search (or the watchdog's full step, Wächter & Biegler 2006 §3.2) an instance whose system was
factorised and whose search found a step takes it: its iterate, filter and feedback gains, and the ``δ_w`` that gave
a positive definite system (the next iteration's first attempt, W&B Algorithm IC). One whose search failed is
``missed``: it enters the feasibility restoration phase (§3.3) where it is not already feasible to the tolerance,
else its next attempt starts from a larger ``δ_w`` (past ``regularization_max``: ``MAX_REGULARIZATION``). Steps at
round-off whose multiplier step is small too count towards the very small search directions of §3.9
(:mod:`~torchtraj.solvers.ipm.barrier`). The iteration's one read back to the host is the six flags of
:class:`Taken` (restoration entries, tiny steps, whether a watchdog runs, may start, or a filter reset may come at
the next iteration, and whether every instance took its step: then the step's feedback gains are every instance's,
with no selection).

With compiled kernels all of it is one kernel call, :func:`conclude` (the flags' read and the restoration phase
follow it, and where a restoration ran, :func:`settle` again on what it returned), or, where the line search's first
round of step sizes settles the search, part of that round's kernel call (:func:`first_round_concluded`); eager, the
same functions run in turn, the tiny steps' counts only where a step was tiny.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.constraints import Constraints
from ...core.problem import Problem
from ...core.status import Status
from ...globalization.filter import Filter
from .compaction import pick
from .expansion import flat_abs
from .iterate import Iterate, Model
from .line_search import Step, measured_first_round
from .newton import Direction
from .options import IPOptions
from .watchdog import Watchdog, count_steps


@dataclass
class Taken:
    """An iteration's step, per instance: the watchdog's counts after it, the iterate, filter and last ``δ_w`` where
    ``take (B,)``; ``missed (B,)``, the factorised instances whose search found no step, ``entering
    (B,)`` those of them that enter the restoration phase (none without one), the step size ``step_size (B,)`` (0
    where none was taken), and ``flags (6,)``, the one read by the host: restoration entries, tiny steps, a watchdog
    running, one that may start, a filter reset that may come, every instance taking its step."""

    wd: Watchdog
    it: Iterate
    filter: Filter
    last: Tensor
    take: Tensor
    missed: Tensor
    entering: Tensor
    step_size: Tensor
    flags: Tensor


def take_step(wd: Watchdog, ls: Step, d: Direction, it: Iterate, filt: Filter, delta: Tensor, last: Tensor,
              factored: Tensor, watching: Optional[Tensor], primal_error: Tensor, tol: float, opts: IPOptions,
              may_reset: bool, restoring: bool) -> Taken:
    """The step ``ls`` taken by the instances ``factored (B,)`` whose search found one (module docstring), from the
    iterate ``it`` and filter ``filt`` before it, regularised by ``delta (B,)`` (the caller takes the step's gains:
    in the form of a problem with terminal rows they change the kernel's specialisation); the watchdog's counts
    moved unless ``watching`` is None (Mehrotra's steps, which have no line search). ``watching (B,)``: the
    instances whose step was the watchdog's; ``may_reset``, ``restoring``: whether a filter reset may come and
    whether the solve has a restoration phase."""
    stepped = ls.filter
    if watching is not None:
        wd, stepped = count_steps(wd, factored & ls.found, ls, watching, filt, opts, may_reset)
    take = factored & ls.found
    missed = factored & ~ls.found
    # W&B 2006 §3.3: the instances whose line search failed, unless already feasible to the tolerance of the
    # convergence test, ‖c‖_∞ (steps at round-off: those keep the larger-δ_w path)
    entering = missed & (primal_error > tol) if restoring else torch.zeros_like(missed)
    tiny = torch.zeros_like(take) if ls.tiny is None else ls.tiny
    # for the next iteration a superset of what it reads: the restoration and the barrier update only stop
    # watchdogs and leave the counts of blocked steps
    running = wd.running()
    flags = torch.stack([entering.any(), tiny.any(), running.any(),
                         (running | (wd.shortened >= opts.watchdog_trigger)).any(),
                         (wd.blocked >= opts.filter_reset_trigger - 1).any(), take.all()])
    return Taken(wd=wd, it=pick(take, ls.it, it), filter=pick(take, stepped, filt),
                 last=torch.where(take & (delta > 0), delta, last), take=take, missed=missed, entering=entering,
                 step_size=torch.where(take, ls.alpha, 0.0), flags=flags)


def tiny_counts(take: Tensor, tiny: Tensor, d: Direction, tiny_steps: Tensor, opts: IPOptions) -> Tensor:
    """The successive steps at round-off ``(B,)`` (W&B §3.9) after this one: counted where the primal step ``tiny
    (B,)`` and the multiplier step are both, restarted where another step was taken."""
    small = tiny & (flat_abs(d.dlam, d.dnu, d.dnuN, d.dy, d.dyN).amax(-1) < opts.tiny_step_dual)
    return torch.where(take, torch.where(small, tiny_steps + 1, 0), tiny_steps)


def settle(take: Tensor, missed: Tensor, delta: Tensor, floor: Tensor, running: Tensor, ok: Tensor, lost: Tensor,
           status: Tensor, iterations: Tensor, opts: IPOptions) -> tuple:
    """The smallest ``δ_w`` of the next attempt (raised where the search failed, reset where a step was taken),
    ``MAX_REGULARIZATION`` where it passed ``regularization_max`` or no system could be factorised (but for a
    watchdog's lost step ``lost (B,)``, which returns), and the iteration counted. Returns ``(floor, status,
    iterations)``."""
    floor = torch.where(missed, torch.clamp(opts.regularization_increase * torch.maximum(floor, delta),
                                            min=opts.regularization_first), torch.where(take, 0.0, floor))
    blown = running & (~ok | (floor > opts.regularization_max)) & ~lost
    return floor, torch.where(blown, int(Status.MAX_REGULARIZATION), status), iterations + running.long()


def conclude(wd: Watchdog, ls: Step, d: Direction, it: Iterate, filt: Filter, delta: Tensor, last: Tensor,
             factored: Tensor, watching: Tensor, primal_error: Tensor, tol: float, opts: IPOptions, may_reset: bool,
             restoring: bool, tiny_steps: Tensor, floor: Tensor, running: Tensor, lost: Tensor, status: Tensor,
             iterations: Tensor) -> tuple:
    """:func:`take_step`, :func:`tiny_counts` and :func:`settle` in one function (a compiled solve's one kernel
    call; :func:`settle`'s result holds where no instance enters a restoration phase). Returns ``(Taken,
    tiny_steps, (floor, status, iterations))``."""
    taken = take_step(wd, ls, d, it, filt, delta, last, factored, watching, primal_error, tol, opts, may_reset,
                      restoring)
    return taken, tiny_counts(taken.take, ls.tiny, d, tiny_steps, opts), settle(
        taken.take, taken.missed, delta, floor, running, d.ok, lost, status, iterations, opts)


def first_round_concluded(problem: Problem, cons: Constraints, params, it: Iterate, d: Direction, model: Model,
                          mu: Tensor, filt: Filter, theta_max: Tensor, theta_min: Tensor, factored: Tensor,
                          corrects: bool, opts: IPOptions, wd: Watchdog, delta: Tensor, last: Tensor, tol: float,
                          restoring: bool, tiny_steps: Tensor, floor: Tensor, running: Tensor, lost: Tensor,
                          status: Tensor, iterations: Tensor) -> tuple:
    """The line search's first round of step sizes for the instances ``factored (B,)``
    (:func:`~torchtraj.solvers.ipm.line_search.measured_first_round`, no watchdog watching) and :func:`conclude` of
    the step where that round settles the search, in one function: a compiled solve's one kernel call for the
    search and the iteration's end where the round settles it (most iterations). Returns ``((measures, first
    round), settled, step, conclude's result)``: ``settled`` a 0-dim boolean; where it is false, the search goes on
    from the first two (:func:`~torchtraj.solvers.ipm.line_search.line_search`'s ``first``)."""
    measures, opening, settled, step = measured_first_round(problem, cons, params, it, d, model, mu, filt, theta_max,
                                                            theta_min, factored, corrects, opts)
    return (measures, opening), settled, step, conclude(
        wd, step, d, it, filt, delta, last, factored, torch.zeros_like(factored), model.primal_error, tol, opts, True,
        restoring, tiny_steps, floor, running, lost, status, iterations)
