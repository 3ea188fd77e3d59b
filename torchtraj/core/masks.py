"""Per-instance choices by masks: a batch is never split by a Python branch on a tensor value."""

from __future__ import annotations

import torch
from torch import Tensor


def where_rows(mask: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``a`` for the instances in ``mask (B,)``, ``b`` elsewhere (``a``, ``b``: ``(B, ...)``)."""
    return torch.where(mask.reshape(-1, *([1] * (a.dim() - 1))), a, b)


def first_true(mask: Tensor) -> Tensor:
    """Index of the first true entry of each row of ``mask (B, l)`` (``l − 1`` where none is): the count of
    leading false entries. Not ``argmax``: compiled for float32 batches shorter than a vector register, inductor
    (torch 2.13) reads the argmax of the loop's remainder uninitialised (``tests/test_compiled.py``)."""
    leading = (~mask).to(torch.long).cumprod(-1).sum(-1)
    return leading.clamp(max=mask.shape[-1] - 1)
