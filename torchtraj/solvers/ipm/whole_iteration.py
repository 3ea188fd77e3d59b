r"""A compiled interior-point iteration in one kernel call, where none of its host reads changes its course.

Between its kernels an iteration of :func:`~torchtraj.solvers.ipm.solver.run` asks the host three things: how many
instances still run (whether the loop ends, and whether finished instances leave the batch), whether the first
attempt of the inertia correction (Wächter & Biegler 2006 §3.1, at the floor ``δ_w``) factorised the system of every
running instance, and whether the line search's first round of step sizes settles the search (§2.3; every pending
instance found a step and none needs a second-order correction). In most iterations the answers are the common
ones: instances still run and stay, the first attempt holds, the round settles the search. :func:`whole_iteration`
is then the iteration, in one function (a compiled solve's one kernel call, where it was three):

1. its start (:func:`~torchtraj.solvers.ipm.opening.opened`: the expansion, the tests that end an instance, the
   barrier update);
2. the Newton step of the first attempt, at the floor ``δ_w`` (:func:`~torchtraj.solvers.ipm.newton.newton_direction`);
3. the line search's first round and the iteration's end where the round settles the search
   (:func:`~torchtraj.solvers.ipm.conclusion.first_round_concluded`).

The host reads the answers as before, and where one is not the common one the loop goes on from the part that
holds: finished instances left behind, the barrier update and all after it made again on the rows that stay; a
failed first attempt, the inertia correction's further attempts from it and the line search's round made again; an
unsettled round, the search goes on from it. Where a watchdog runs or may start, the loop takes its own path (the
watchdog's step and its return need their host reads). Each instance's arithmetic is that of the three calls.

For a batch, the loop makes this call only after an iteration whose first attempt held for every running instance.
In a large batch some instance's first attempt fails in most iterations, and the call's line-search round would be
thrown away and made again for the whole batch; the answer of the last iteration is the host's best guess of this
one's. A single instance takes the call in every iteration: its round made again costs less than the calls saved.
"""

from __future__ import annotations

from typing import Optional

from torch import Tensor

from ...core.compiled import batched_options
from ...core.constraints import Constraints
from ...core.problem import Problem
from ...globalization.filter import Filter
from .conclusion import first_round_concluded
from .expansion import Base, expand
from .iterate import Iterate
from .newton import newton_direction
from .opening import opened
from .options import IPOptions
from .watchdog import Watchdog


@batched_options(expand.batched_options)  # as its start's kernel (opening.opened)
def whole_iteration(problem: Problem, cons: Constraints, params, it: Iterate, opts: IPOptions, base: Optional[Base],
                    status: Tensor, iterations: Tensor, budget: Tensor, budgeted: bool, tol: float, mu: Tensor,
                    tiny_steps: Tensor, filt: Filter, x0: Tensor, floor: Tensor, wd: Watchdog, last: Tensor,
                    theta_max: Tensor, theta_min: Tensor, restoring: bool, corrects: bool) -> tuple:
    """The iteration from the iterate ``it`` (module docstring): :func:`~torchtraj.solvers.ipm.opening.opened`'s
    arguments, then the initial ``x0 (B, nx)``, the floor ``δ_w`` ``(B,)`` of the first attempt, the watchdog's
    counts before the barrier update, the last ``δ_w`` that gave a positive definite system ``(B,)``, the filter's
    bounds ``θ_max``, ``θ_min`` ``(B,)``, whether the solve has a restoration phase and takes second-order
    corrections. Returns ``(opening, (step, round))``: ``opened``'s result, the Newton step at the floor, and
    :func:`~torchtraj.solvers.ipm.conclusion.first_round_concluded`'s result in its own order, ``(first round,
    settled, None, conclusion)``, the step of the settled search left out (the conclusion holds it)."""
    opening = opened(problem, cons, params, it, opts, base, status, iterations, budget, budgeted, tol, mu, tiny_steps,
                     filt)
    model, _, _, (mu, filt, status, running, tiny_steps, changed) = opening
    wd = wd.stop(changed)  # as the loop's, after the barrier update
    d = newton_direction(model, it, mu, x0, floor, opts.sweep, opts.terminal_rows)
    factored = running & d.ok
    lost = running & ~d.ok & wd.running()
    first, settled, _, concluded = first_round_concluded(
        problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, factored, corrects, opts, wd, floor,
        last, tol, restoring, tiny_steps, floor, running, lost, status, iterations)
    return opening, (d, (first, settled, None, concluded))
