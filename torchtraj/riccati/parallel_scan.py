r"""Batched associative scans over the time dimension: O(log N) sequential depth.

For an associative operator ``⊗`` and elements ``e_0, …, e_{N−1}`` (each a tuple of tensors shaped
``(B, N, …)``), the inclusive scan gives every prefix ``e_0 ⊗ … ⊗ e_k`` and the reverse scan every suffix
``e_k ⊗ … ⊗ e_{N−1}``. Both are computed by recursive doubling (Hillis & Steele 1986, the form used by Särkkä and
García-Fernández, "Temporal parallelization of Bayesian smoothers", IEEE TAC 2021, and their LQ-control sequel):
after the level of span ``d`` each element holds the product of the ``2d`` elements ending (prefix) or starting
(suffix) at it,

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


def associative_scan(elements: Elements, combine: Callable[[Elements, Elements], Elements],
                     reverse: bool = False) -> Elements:
    """Every prefix (``reverse``: every suffix) of ``elements`` under ``combine``.

    ``elements``: tensors shaped ``(B, N, …)``, element ``k`` the slices ``[:, k]``. ``combine(earlier, later)``
    returns ``earlier ⊗ later`` for batched pieces shaped ``(B, n, …)`` and must be associative. Returns the
    tensors of the scanned elements, shaped as ``elements``."""
    N = elements[0].shape[1]
    span = 1
    while span < N:
        earlier = tuple(e[:, :-span] for e in elements)
        later = tuple(e[:, span:] for e in elements)
        pairs = combine(earlier, later)
        if reverse:  # the last ``span`` suffixes are complete already
            elements = tuple(torch.cat([p, e[:, -span:]], 1) for p, e in zip(pairs, elements))
        else:  # the first ``span`` prefixes are complete already
            elements = tuple(torch.cat([e[:, :span], p], 1) for p, e in zip(pairs, elements))
        span *= 2
    return elements


def _compose_forward(earlier: Elements, later: Elements) -> Elements:
    return (_mm(later[0], earlier[0]),)  # apply the earlier map first


def _compose_backward(earlier: Elements, later: Elements) -> Elements:
    return (_mm(earlier[0], later[0]),)  # the later map acts first: p_k depends on p_{k+1}


def augmented(M: Tensor, v: Tensor) -> Tensor:
    """``[[M, v], [0, 1]] (…, n+1, n+1)`` for ``M (…, n, n)`` and ``v (…, n)``."""
    top = torch.cat([M, v.unsqueeze(-1)], -1)
    bottom = torch.nn.functional.pad(torch.ones_like(v[..., :1]), (M.shape[-1], 0)).unsqueeze(-2)
    return torch.cat([top, bottom], -2)


def affine_scan(M: Tensor, v: Tensor, start: Tensor, reverse: bool = False) -> Tensor:
    """The affine recursion's values from ``start (B, n)``, ``M (B, N, n, n)``, ``v (B, N, n)``.

    Forward: ``x_0 = start``, ``x_{k+1} = M_k x_k + v_k``, returns ``x_1 … x_N (B, N, n)``.
    Reverse: ``x_N = start``, ``x_k = M_k x_{k+1} + v_k``, returns ``x_0 … x_{N−1} (B, N, n)``."""
    n = M.shape[-1]
    maps = augmented(M, v)
    (composed,) = associative_scan((maps,), _compose_backward if reverse else _compose_forward, reverse)
    # the composed map's last row is [0, 1]: apply its first n rows to [start; 1]
    return _mm(composed[..., :n, :n], start.unsqueeze(1).unsqueeze(-1)).squeeze(-1) + composed[..., :n, n]
