r"""One batched backtracking driver for every line search of the library.

A backtracking line search tries the step sizes ``α_0 > α_1 > …`` (``α_max β^j``) and takes, per instance, the
first one its acceptance test passes. On a batch the candidates are evaluated together: the step sizes are cut
into rounds of ``per_round``, and one call of the caller's ``evaluate`` simulates every instance at every step
size of a round (a batched rollout for iLQR, a batched evaluation of the multiple-shooting point for the IPM). A
further round is evaluated only while an instance that is ``pending`` has found no acceptable step: that question
is the one host synchronisation per round (``bool(...any())``); the full step is usually accepted in the first
round. The acceptance test stays with the caller (iLQR's ratio of actual to expected decrease, ALTRO §II-A; the
IPM's filter, Wächter & Biegler 2006 §2.3; ALTRO's projection's decrease of the violation, Algorithm 3), as do the
values it keeps of the accepted candidate.

A single round of all the step sizes (``per_round = L``) makes no host synchronisation at all: that is how a
compiled kernel keeps one graph, and how ALTRO's projection evaluates its ``α ∈ {1, γ, γ², …}`` with
``accept = v(α) < v``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from ..core.masks import RowPicker, first_true, where_rows


@dataclass
class Accepted:
    """Per instance: whether a step was accepted, ``found (B,)``; its size, ``alpha (B,)``; and the caller's values
    of the accepted candidate, ``values`` (a tuple of batch-first tensors). Given to :func:`backtrack` as its start,
    the values an instance keeps where it accepts no step (and ``found`` the instances that need none)."""

    found: Tensor
    alpha: Tensor
    values: tuple = ()


def backtrack(steps: Tensor, per_round: int, evaluate: Callable[..., tuple], pending: Tensor, start: Accepted,
              sync_first: bool = False, by_rows: bool = False, first_round: Optional[int] = None) -> Accepted:
    """The first accepted of the step sizes ``steps`` (``(L,)``, shared by the batch, or ``(B, L)``) per instance.

    ``evaluate(alphas)`` takes a round's step sizes (``steps[..., j:j + per_round]``, ``(l,)`` or ``(B, l)``) and
    returns ``(accept (B, l), values)``, ``values`` a tuple of ``(B, l, ...)`` per-candidate tensors matching
    ``start.values``. A round is evaluated only while some instance of ``pending (B,)`` has found no step; before
    the first round that is asked only with ``sync_first`` (a compiled caller that wants one graph leaves it off).
    An instance already ``found`` at the start keeps its start; the others take their first accepted candidate of
    the first round that has one (the largest step there). ``by_rows``: a round after the first evaluates only the
    pending instances that found no step yet, ``evaluate(alphas, rows)`` on the rows ``rows (R,)`` of the batch
    (``alphas`` of those rows where per instance), returning ``(R, l)``-shaped results: in a large batch most
    instances take the full step, and the others' further rounds would evaluate the whole batch again.
    ``first_round``: the first round's count, where it differs from ``per_round`` (one candidate, the full step,
    where evaluating the others for every instance costs more than a further round for the few that need it). The
    same candidates are evaluated for the instances that read them, in the same order, whatever the rounds. Returns
    the :class:`Accepted` steps."""
    L = steps.shape[-1]
    shared = steps.dim() == 1
    rows = torch.arange(pending.shape[0], device=steps.device)
    found, alpha, values = start.found, start.alpha, start.values
    opening = min(L, first_round or per_round)
    for first in [0, *range(opening, L, per_round)]:
        if (first > 0 or sync_first) and not bool((pending & ~found).any()):
            break
        size = opening if first == 0 else per_round
        alphas = steps[..., first:first + size].contiguous()  # a kernel sees the strides of a fresh tensor
        if by_rows and first > 0:
            looking = (pending & ~found).nonzero().squeeze(-1)
            if looking.shape[0] < pending.shape[0]:
                found, alpha, values = _round_of_rows(evaluate, alphas if shared else alphas[looking], looking, found,
                                                      alpha, values)
                continue
        accept, candidates = evaluate(alphas)
        idx = first_true(accept)  # the first (largest) accepted step of the round
        new = accept.any(1) & ~found
        taken = RowPicker(new)
        values = tuple(taken(c[rows, idx], v) for c, v in zip(candidates, values))
        alpha = torch.where(new, alphas[idx] if shared else alphas[rows, idx], alpha)
        found = found | new
    return Accepted(found, alpha, values)


def _round_of_rows(evaluate: Callable[..., tuple], alphas: Tensor, looking: Tensor, found: Tensor, alpha: Tensor,
                   values: tuple) -> tuple:
    """One round of :func:`backtrack` on the rows ``looking (R,)`` alone (none of them ``found``): ``(found, alpha,
    values)`` with those rows updated."""
    accept, candidates = evaluate(alphas, looking)
    idx = first_true(accept)
    new = accept.any(1)
    rows = torch.arange(looking.shape[0], device=looking.device)
    values = tuple(v.index_copy(0, looking, where_rows(new, c[rows, idx], v[looking]))
                   for c, v in zip(candidates, values))
    taken = alphas[idx] if alphas.dim() == 1 else alphas[rows, idx]
    return (found.index_copy(0, looking, new), alpha.index_copy(0, looking, torch.where(new, taken, alpha[looking])),
            values)
