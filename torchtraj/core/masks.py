"""Per-instance choices by masks: a batch is never split by a Python branch on a tensor value."""

from __future__ import annotations

import torch
from torch import Tensor


def where_rows(mask: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``a`` for the instances in ``mask (B,)``, ``b`` elsewhere (``a``, ``b``: ``(B, ...)``)."""
    return torch.where(_shaped(mask, a.dim()), a, b)


def _shaped(mask: Tensor, dims: int) -> Tensor:
    """``mask (B,)`` shaped to broadcast against ``(B, ...)`` tensors of ``dims`` dimensions."""
    return mask.reshape(-1, *([1] * (dims - 1)))


class RowPicker:
    """:func:`where_rows` of one ``mask (B,)`` for many pairs of tensors (the fields of a dataclass): the mask is
    shaped once for each number of dimensions met (a reshape is a call of its own), and used as it is for ``(B,)``
    tensors."""

    def __init__(self, mask: Tensor):
        self.mask = mask
        self.shaped = {1: mask} if mask.dim() == 1 else {}

    def __call__(self, a: Tensor, b: Tensor) -> Tensor:
        shaped = self.shaped.get(a.dim())
        if shaped is None:
            shaped = self.shaped[a.dim()] = _shaped(self.mask, a.dim())
        return torch.where(shaped, a, b)


def first_true(mask: Tensor) -> Tensor:
    """Index of the first true entry of each row of ``mask (B, l)`` (``l − 1`` where none is): the smallest index of
    a true entry. Not ``argmax``: compiled for float32 batches shorter than a vector register, inductor (torch 2.13)
    reads the argmax of the loop's remainder uninitialised (``tests/test_compiled.py``); nor a cumulative product of
    the false entries, a library call in a compiled kernel (:mod:`~torchtraj.core.stack_buffers`)."""
    last = mask.shape[-1] - 1
    return torch.where(mask, torch.arange(mask.shape[-1], device=mask.device), last).amin(-1)
