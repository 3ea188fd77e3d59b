r"""Batched associative scans over the time dimension: O(log N) sequential depth.

For an associative operator ``⊗`` and elements ``e_0, …, e_{N−1}`` (each a tuple of tensors, one block of B
instances), the inclusive scan gives every prefix ``e_0 ⊗ … ⊗ e_k`` and the reverse scan every suffix
``e_k ⊗ … ⊗ e_{N−1}``. Both are computed by recursive doubling (Hillis & Steele, "Data parallel algorithms",
CACM 1986): after the level of span ``d`` each element holds the product of the ``2d`` elements ending (prefix)
or starting (suffix) at it,

.. math::  s^{(2d)}_k = s^{(d)}_{k-d} \otimes s^{(d)}_k \quad (k \ge d), \qquad
           s^{(2d)}_k = s^{(d)}_k \otimes s^{(d)}_{k+d} \quad (k < N - d,\ \text{reverse}),

so ``⌈log₂ N⌉`` levels, each one batched call of the operator on all the pairs of that level (``N − d`` of them,
all instances at once): the number of operator calls grows like ``log N``, the arithmetic like ``N log N``.

:func:`affine_scan` is the scan of affine maps ``x ↦ M x + v`` written as augmented matrices
``[[M, v], [0, 1]]``, whose composition is one matrix product: the forward rollout
``x_{k+1} = M_k x_k + v_k`` and the backward recursions ``p_k = M_k p_{k+1} + v_k`` of the Riccati solve.
"""

from __future__ import annotations

from typing import Callable, Tuple

import torch
from torch import Tensor

from ..core.compiled import matmul as _mm

Elements = Tuple[Tensor, ...]


def associative_scan(elements: Elements, combine: Callable[[Elements, Elements], Elements], stride: int,
                     reverse: bool = False) -> Elements:
    """Every prefix (``reverse``: every suffix) of ``elements`` under ``combine``.

    ``elements``: tensors stored time-major and flattened, ``(N · stride, …)``, element ``k`` the rows
    ``[k · stride, (k+1) · stride)`` (``stride`` the batch size): the pairs of a level are then two contiguous
    blocks of rows, and ``combine(earlier, later)``, which returns ``earlier ⊗ later`` for pieces shaped like
    ``elements``, sees batches of plain matrices (one ``bmm`` a product). Returns the scanned elements."""
    N = elements[0].shape[0] // stride
    span = 1
    while span < N:
        rows = span * stride
        pairs = combine(tuple(e[:-rows] for e in elements), tuple(e[rows:] for e in elements))
        if reverse:  # the last ``span`` suffixes are complete already
            elements = tuple(torch.cat([p, e[-rows:]]) for p, e in zip(pairs, elements))
        else:  # the first ``span`` prefixes are complete already
            elements = tuple(torch.cat([e[:rows], p]) for p, e in zip(pairs, elements))
        span *= 2
    return elements


def _compose_forward(earlier: Elements, later: Elements) -> Elements:
    return (_mm(later[0], earlier[0]),)  # apply the earlier map first


def _compose_backward(earlier: Elements, later: Elements) -> Elements:
    return (_mm(earlier[0], later[0]),)  # the later map acts first: x_k depends on x_{k+1}


def affine_scan(M: Tensor, v: Tensor, start: Tensor, reverse: bool = False) -> Tensor:
    """The affine recursion's values from ``start (B, n, 1)``, with ``M (N·B, n, n)`` and ``v (N·B, n, 1)``
    time-major (:func:`associative_scan`).

    Forward: ``x_0 = start``, ``x_{k+1} = M_k x_k + v_k``, returns ``x_1 … x_N`` as ``(N·B, n, 1)``.
    Reverse: ``x_N = start``, ``x_k = M_k x_{k+1} + v_k``, returns ``x_0 … x_{N−1}`` as ``(N·B, n, 1)``."""
    stride, n = start.shape[0], M.shape[-1]
    pad = torch.nn.functional.pad
    maps = torch.cat([pad(M, (0, 0, 0, 1)), pad(v, (0, 0, 0, 1), value=1.0)], -1)  # [[M, v], [0, 1]]
    (composed,) = associative_scan((maps,), _compose_backward if reverse else _compose_forward, stride, reverse)
    # the composed map's first n rows applied to [start; 1]
    return _mm(composed[:, :n], pad(start, (0, 0, 0, 1), value=1.0).repeat(M.shape[0] // stride, 1, 1))
