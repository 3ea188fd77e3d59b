r"""Non-finite instances swapped for a benign problem before a sweep.

LAPACK's SVD and Cholesky routines may fail for a whole batch when one instance holds a NaN or an infinity. An
instance with any non-finite matrix entry is therefore replaced, before the factorisation, by
``A = 0, B = 0, C = D = 0, Q = R = Q_N = I`` (no cross terms), whose factorisation is trivially well defined; the
other instances' answers are unchanged, and the mask ``finite (B,)`` returned with the cleaned problem marks the
replaced ones as failed (``RiccatiFactor.ok``). One failed instance never changes the answer of another.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .linalg import _mT
from .lqr import LQR


def all_finite(values: list) -> Tensor:
    """``(B,)``: whether every entry of an instance is finite in each of ``values`` (batch-first tensors or None),
    ``None`` where none has entries.

    Read from one sum per instance of each tensor, added over the tensors: a NaN or an infinity makes the sum
    NaN or infinite. Three calls a tensor fewer than testing the extremes (``amax``, ``amin``), and at large batches
    faster: an ``amax`` over the inner dimensions of a time-major block read batch-first is many times slower than
    the sum (``docs/benchmarks.md``, design choices). A sum of finite entries can itself overflow, where they come
    within a factor of their count of the float's largest value; that instance is then reported not finite,
    whose products in a sweep would overflow as well."""
    total = None
    for value in values:
        if value is not None and value.shape[1:].numel():
            part = value.sum(tuple(range(1, value.dim())))
            total = part if total is None else total + part
    return None if total is None else torch.isfinite(total)


def _clean(value: Optional[Tensor], finite: Tensor, eye: bool = False) -> Optional[Tensor]:
    """``value`` where ``finite``, else zero (``eye``: the identity)."""
    if value is None:
        return None
    keep = finite.reshape(-1, *([1] * (value.dim() - 1)))
    if eye:
        return torch.where(keep, value, torch.eye(value.shape[-1], dtype=value.dtype, device=value.device))
    return torch.where(keep, value, value.new_zeros(()))  # not zeros_like: seven times dearer


_OTHER_FIELDS = ("QN", "C", "D", "mask", "CN", "maskN", "root", "rootN")


def _sanitize(lqr: LQR):
    """Replace the matrices of instances with non-finite entries by a benign problem.

    LAPACK's SVD may fail for a whole batch when one instance holds a NaN; swapping such an
    instance for ``A = 0, B = 0, Q = R = I`` keeps the others' answers unchanged, and the
    returned mask ``finite (B,)`` marks it as failed."""
    finite = all_finite([lqr.A, lqr.B, lqr.Q, lqr.R, lqr.S, lqr.QN, lqr.C, lqr.D, lqr.CN])
    fields = {name: _clean(getattr(lqr, name), finite, eye=name in ("Q", "R", "QN"))
              for name in ("A", "B", "Q", "R", "S") + _OTHER_FIELDS}
    return LQR(bounds=lqr.bounds, **fields), finite


def _sanitize_stacked(lqr: LQR, shift: Optional[Tensor] = None):
    """:func:`_sanitize` and the stage blocks stacked over ``z = (δx, δu)``, stored time-major:
    ``W = [A B] (N, B, nx, nx+nu)`` and ``Hs = [[Q, Sᵀ], [S, R]] (N, B, nx+nu, nx+nu)``, of which the cleaned
    ``A, B, Q, R, S`` are (batch-first) views. A sweep reads one stage of every instance at a time: stored
    time-major, that stage is one contiguous block (see :func:`~torchtraj.riccati.linalg._time_major`).

    The cost is in memory: the blocks are checked and cleaned once stacked (not as five, often strided,
    views of one Hessian), in place, and ``Hs`` is filled block by block: every new buffer of megabytes
    costs its page faults (about half the time of :func:`_sanitize` alone at B = 256). Given already stacked
    (:meth:`LQR.from_blocks`), each is one copy whose rows are contiguous. ``shift (B,)`` is added to the diagonal
    of every Hessian block and of ``QN``."""
    Bsz, N, nx, nu = lqr.B.shape
    n = nx + nu
    tm = lambda a: a.transpose(0, 1)  # noqa: E731
    W = lqr.A.new_empty(N, Bsz, nx, n)
    Hs = lqr.Q.new_empty(N, Bsz, n, n)
    if lqr.W is not None:
        W.copy_(tm(lqr.W))
        Hs.copy_(tm(lqr.H))
    else:
        W[..., :nx], W[..., nx:] = tm(lqr.A), tm(lqr.B)
        Hs[..., :nx, :nx], Hs[..., :nx, nx:], Hs[..., nx:, :nx], Hs[..., nx:, nx:] = \
            tm(lqr.Q), tm(_mT(lqr.S)), tm(lqr.S), tm(lqr.R)
    QN = lqr.QN
    if shift is not None:
        Hs.diagonal(dim1=-2, dim2=-1).add_(shift.reshape(1, Bsz, 1))
        QN = QN + shift.reshape(Bsz, 1, 1) * torch.eye(nx, dtype=QN.dtype, device=QN.device)
    finite = all_finite([tm(W), tm(Hs), QN, lqr.C, lqr.D, lqr.CN])
    drop = ~finite.reshape(1, -1, 1, 1)
    W.masked_fill_(drop, 0.0)
    Hs.masked_fill_(drop, 0.0)
    Hs.diagonal(dim1=-2, dim2=-1).masked_fill_(drop[..., 0], 1.0)
    fields = {name: _clean(QN if name == "QN" else getattr(lqr, name), finite, eye=name == "QN")
              for name in _OTHER_FIELDS}
    cleaned = LQR(A=tm(W[..., :nx]), B=tm(W[..., nx:]), Q=tm(Hs[..., :nx, :nx]), R=tm(Hs[..., nx:, nx:]),
                  S=tm(Hs[..., nx:, :nx]), bounds=lqr.bounds, **fields)
    return cleaned, finite, W, Hs
