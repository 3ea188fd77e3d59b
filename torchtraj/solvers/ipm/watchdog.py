r"""The watchdog procedure and the filter reset heuristic (Wächter & Biegler 2006 §3.2), per instance.

**Watchdog.** Near a curved constraint the filter may cut step after step (the Maratos effect that the
second-order corrections do not cure), and the iteration crawls. Where the first trial point ``α_max`` of the line
search was rejected in ``l_w`` successive iterations (``IPOptions.watchdog_trigger``, IPOPT's
``watchdog_shortened_iter_trigger`` = 10), the watchdog starts: the iterate ``w^W`` is stored with its barrier
objective ``φ^W``, slope ``∇φ^{W T} Δ^W``, ``θ^W`` and step ``α^W_max``, and for up to ``watchdog_trials``
iterations (``watchdog_trial_iter_max`` = 3) the full step ``α_max`` (fraction to boundary) is taken *without* a
line search. At each of them the trial point is tested against the stored point (the switching, Armijo and
sufficient-decrease conditions with ``θ^W``, ``φ^W``, ``α^W_max`` and its slope, and the filter): where it passes,
the step is accepted as a regular one (the filter is augmented with ``w^W``'s entry unless it met the switching and
Armijo conditions) and the watchdog ends. Where none of them passes, the iterate returns to ``w^W``, whose next
iteration backtracks along its direction (recomputed there: it is the stored one but for ``δ_w``, which may have
moved; IPOPT backtracks within the same iteration). A barrier update ends a watchdog where it stands (its reference
``φ^W`` belongs to the old ``μ``), as does a trial point that is not finite, or one where no Newton step is found
(back to ``w^W``: the full steps of a swing-up can run off in three iterations, cartpole_unconstrained from one of
its ``sample_x0`` starts).

**Filter reset heuristic** (W&B §3.2's companion in IPOPT: ``filter_reset_trigger`` = 5, ``max_filter_resets``
= 5): where, in ``filter_reset_trigger`` successive iterations, the last trial point rejected before the step
taken passed the sufficient-decrease (or Armijo) test and was rejected by the filter alone, the filter holds
entries that block progress that the barrier problem would accept: it is emptied, at most ``filter_resets``
times per instance. As in IPOPT's code (``FilterLSAcceptor``), the reset comes when the trial point is accepted,
before the filter is augmented with the point the step leaves, so that entry stays. IPOPT's code never counts its
resets (its ``n_filter_resets_`` stays 0, so ``max_filter_resets`` does not bind); this one caps them as the
option's documentation says.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ...core.problem import Problem
from ...globalization.filter import Filter
from .compaction import pick
from .iterate import Iterate, Model
from .kernels import kernel_of
from .line_search import Step, advance, step_measures, trial
from .newton import Direction
from .options import IPOptions


@dataclass
class Watchdog:
    """Per instance: ``shortened (B,)`` successive iterations whose first trial point was rejected, ``trials (B,)``
    watchdog iterations taken (0: none running), the stored point ``it`` and its ``phi``, ``slope``, ``theta`` and
    ``alpha (B,)``, and the last ``δ_w`` there, ``last (B,)`` (restored with it, so that the direction recomputed
    there is the stored one); for the filter reset, ``blocked (B,)`` successive iterations whose last rejected trial
    point the filter alone refused and ``resets (B,)`` done."""

    shortened: Tensor
    trials: Tensor
    it: Iterate
    phi: Tensor
    slope: Tensor
    theta: Tensor
    alpha: Tensor
    last: Tensor
    blocked: Tensor
    resets: Tensor

    @classmethod
    def start(cls, it: Iterate) -> "Watchdog":
        # a tensor for each field: a compiled kernel's graph is specialised to which of its inputs are one tensor
        def count():
            return torch.zeros(it.X.shape[0], dtype=torch.long, device=it.X.device)

        def zero():
            return it.X.new_zeros(it.X.shape[0])

        return cls(shortened=count(), trials=count(), it=it, phi=zero(), slope=zero(), theta=zero(), alpha=zero(),
                   last=zero(), blocked=count(), resets=count())

    def running(self) -> Tensor:
        return self.trials > 0

    def stop(self, mask: Tensor) -> "Watchdog":
        """The watchdogs of ``mask (B,)`` ended (and their counts of shortened steps restarted)."""
        return replace(self, trials=torch.where(mask, 0, self.trials), shortened=torch.where(mask, 0, self.shortened))


def watched_step(problem: Problem, cons, params, it: Iterate, d: Direction, model: Model, mu: Tensor, filt: Filter,
                 theta_max: Tensor, theta_min: Tensor, wd: Watchdog, watching: Tensor, last: Tensor,
                 opts: IPOptions) -> tuple:
    """The watchdog iteration (module docstring) of the instances ``watching (B,)``; those whose watchdog starts now
    (``wd.trials == 0``) store the current point and its last ``δ_w``, ``last (B,)``, first. Returns ``(step,
    watchdog, returned (B,))``: ``step.found`` where the full step was taken (accepted or not), ``step.it`` its
    iterate, or ``w^W`` where the watchdog gave up (``returned``)."""
    a_max, a_dual, phi, slope, _, _ = kernel_of(step_measures, opts, it.X.device)(model, it, d, mu, opts)
    starting = watching & (wd.trials == 0)
    wd = replace(wd, it=pick(starting, it, wd.it), phi=torch.where(starting, phi, wd.phi),
                 slope=torch.where(starting, slope, wd.slope), theta=torch.where(starting, model.theta, wd.theta),
                 alpha=torch.where(starting, a_max, wd.alpha), last=torch.where(starting, last, wd.last))
    reference = replace(model, theta=wd.theta)
    accept, unfiltered, _, theta_c, _ = trial(problem, cons, params, it, d, reference, mu, wd.phi, wd.slope, filt,
                                        theta_max, theta_min, a_max.unsqueeze(1), opts, wd.alpha.unsqueeze(1))
    accepted = watching & accept[:, 0]
    trials = wd.trials + watching.long()
    finite = torch.isfinite(theta_c[:, 0])
    give_up = watching & ~accepted & ((trials > opts.watchdog_trials) | ~finite)
    filt = filt.add(accepted & ~unfiltered[:, 0], (1.0 - opts.filter_theta) * wd.theta,
                    wd.phi - opts.filter_phi * wd.theta)
    moved = advance(it, d, a_max, a_dual, mu, model.knots, opts)
    new_it = pick(give_up, wd.it, moved)
    wd = replace(wd, trials=torch.where(watching, trials, wd.trials)).stop(accepted | give_up)
    step = Step(new_it, torch.where(watching & ~give_up, a_max, 0.0), watching, filt,
                shortened=torch.zeros_like(watching), blocked=torch.zeros_like(watching),
                tiny=torch.zeros_like(watching))
    return step, wd, give_up


def count_steps(wd: Watchdog, taken: Tensor, step: Step, watching: Tensor, before: Filter, opts: IPOptions,
                may_reset: bool = True) -> tuple:
    """After the line search: the counts of shortened steps and of steps the filter blocked of the instances that
    ``taken (B,)`` a regular step, and the filter reset where the latter reaches ``filter_reset_trigger`` (at most
    ``filter_resets`` times): ``step.filter`` emptied of the entries of ``before``, the filter the line search
    started from (IPOPT resets it on accepting the trial point, then adds the entry of the point the step leaves).
    ``may_reset``: false where no instance's count can reach the trigger at this step (the caller knows it from
    the counts before it: they grow by one at most). Returns ``(watchdog, filter)``."""
    regular = taken & ~watching
    shortened = torch.where(regular, torch.where(step.shortened, wd.shortened + 1, 0), wd.shortened)
    blocked = torch.where(regular, torch.where(step.blocked, wd.blocked + 1, 0), wd.blocked)
    if not may_reset:
        return replace(wd, shortened=shortened, blocked=blocked), step.filter
    reset = (blocked >= opts.filter_reset_trigger) & (wd.resets < opts.filter_resets)
    return replace(wd, shortened=shortened, blocked=torch.where(reset, 0, blocked),
                   resets=wd.resets + reset.long()), step.filter.reset_before(reset, before)


def merge_steps(mask: Tensor, a: Step, b: Step) -> Step:
    """The :class:`Step` ``a`` where ``mask (B,)``, else ``b``."""
    return Step(pick(mask, a.it, b.it), torch.where(mask, a.alpha, b.alpha), torch.where(mask, a.found, b.found),
                pick(mask, a.filter, b.filter), shortened=torch.where(mask, a.shortened, b.shortened),
                blocked=torch.where(mask, a.blocked, b.blocked), tiny=torch.where(mask, a.tiny, b.tiny))
