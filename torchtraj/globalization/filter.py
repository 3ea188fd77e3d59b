r"""The filter of a filter line search (Wächter & Biegler 2006 §2.3; Fletcher & Leyffer 2002), one per instance.

A trial point with constraint violation ``θ`` and objective ``φ`` is acceptable to the filter when, for every
entry ``(θ_j, φ_j)``, it improves one of the two: ``θ < θ_j`` or ``φ < φ_j``. After a step that was not an
f-type step (one that met the Armijo condition under the switching condition), the caller adds the entry
``((1 − γ_θ) θ, φ − γ_φ θ)`` of the point it left. This one keeps the last ``F`` entries of each instance in a ring
(``+∞`` where empty), so that the batch's filters are one tensor and a step is the same arithmetic for every
instance; the barrier update resets an instance's filter.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class Filter:
    """Per-instance filter: ``entries (B, F, 2)`` of ``(θ, φ)`` (``+inf`` where empty) and the next slot ``(B,)``."""

    entries: Tensor
    slot: Tensor

    @classmethod
    def empty(cls, batch: int, size: int, like: Tensor) -> "Filter":
        return cls(like.new_full((batch, size, 2), float("inf")),
                   torch.zeros(batch, dtype=torch.long, device=like.device))

    def reset(self, mask: Tensor) -> "Filter":
        """The filters of the instances in ``mask (B,)`` emptied."""
        return Filter(torch.where(mask.reshape(-1, 1, 1), float("inf"), self.entries), torch.where(mask, 0, self.slot))

    def reset_before(self, mask: Tensor, before: "Filter") -> "Filter":
        """The filters of the instances in ``mask (B,)`` emptied of the entries they held at ``before`` (this filter
        before its last :meth:`add`), keeping the entry added since: IPOPT's filter reset heuristic empties the filter
        when it accepts the trial point, before the filter is augmented with the point the step leaves."""
        size = self.entries.shape[1]
        added = self.slot > before.slot
        newest = _slot_mask((self.slot - 1) % size, size) & added.unsqueeze(-1)
        clear = mask.unsqueeze(-1) & ~newest
        return Filter(torch.where(clear.unsqueeze(-1), float("inf"), self.entries), self.slot)

    def acceptable(self, theta: Tensor, phi: Tensor) -> Tensor:
        """Candidates ``(B, L)`` not dominated by an entry."""
        t, p = self.entries[..., 0].unsqueeze(1), self.entries[..., 1].unsqueeze(1)
        return ((theta.unsqueeze(-1) < t) | (phi.unsqueeze(-1) < p)).all(-1)

    def add(self, mask: Tensor, theta: Tensor, phi: Tensor) -> "Filter":
        """The entry ``(θ, φ)`` (``(B,)`` each) added where ``mask (B,)``, over the oldest one when the ring is full."""
        size = self.entries.shape[1]
        slot = _slot_mask(self.slot % size, size) & mask.unsqueeze(-1)
        entry = torch.stack([theta, phi], -1).unsqueeze(1)
        return Filter(torch.where(slot.unsqueeze(-1), entry, self.entries), self.slot + mask.long())


def _slot_mask(slot: Tensor, size: int) -> Tensor:
    """``(B, size)``: true at each instance's ``slot (B,)``. A comparison with the slots' indices, not ``one_hot``,
    which checks its input's range with two reductions read by the host."""
    return torch.arange(size, device=slot.device) == slot.unsqueeze(-1)
