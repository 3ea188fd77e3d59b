r"""Small dense linear algebra for the batched Riccati sweeps.

Every stage of a sweep factorises and solves with tiny matrices (``nu × nu`` Hessians, ``(nx+nu) × (nx+nu)``
blocks) for a whole batch at once: a Cholesky factorisation ``H = L Lᵀ`` that marks, per instance, where ``H`` is
not positive definite (``info > 0``) and puts the identity there, so that one failed instance never disturbs the
others; the solves ``L Lᵀ x = b`` that go with it; and the zero-padding that keeps the ranks of the constraint
back-propagation out of the tensor shapes (:mod:`torchtraj.riccati.propagation`).

Eager, LAPACK's batched routines are the cheapest; traced by torch.compile, or captured in a CUDA graph, the
same factorisations and solves are written out elementwise for the smallest sizes (:func:`_elementwise`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.compiled import matmul as _mm
from ..core.graphs import capturing


def _mT(a: Tensor) -> Tensor:
    return a.transpose(-1, -2)


def _sym(a: Tensor) -> Tensor:
    return 0.5 * (a + _mT(a))


# Cholesky factorisations and solves of the small (nu × nu) Hessians. Eager, LAPACK's batched routines
# are the cheapest for nu ≥ 2 (measured on CPU: several times faster than the elementwise formulas below;
# docs/benchmarks.md, design choices). torch.compile fuses the elementwise formulas into its loops instead
# (up to _SMALL), and a 1 × 1 factor is a square root.
_SMALL = 4


def _elementwise(n: int) -> bool:
    """Whether the ``n × n`` factorisation and solves use the elementwise formulas: while traced, and while a
    CUDA graph is captured (MAGMA's batched routines, behind some of the LAPACK-like calls, cannot be)."""
    if n > _SMALL:
        return False
    return torch.compiler.is_compiling() or capturing()


def _cholesky(H: Tensor):
    """Lower Cholesky factor of ``H (..., n, n)`` and ``info (...)`` (0 where positive definite).

    Where ``H`` is not positive definite the returned factor is the identity."""
    n = H.shape[-1]
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    if n == 1:
        positive = H > 0
        return torch.where(positive, H, eye).sqrt(), (~positive[..., 0, 0]).to(torch.int32)
    if not _elementwise(n):
        L, info = torch.linalg.cholesky_ex(H)
        return torch.where((info == 0).unsqueeze(-1).unsqueeze(-1), L, eye), info
    cols = [[None] * n for _ in range(n)]
    ok = torch.ones(H.shape[:-2], dtype=torch.bool, device=H.device)
    for j in range(n):
        pivot = H[..., j, j]
        for k in range(j):
            pivot = pivot - cols[j][k] * cols[j][k]
        ok = ok & (pivot > 0)
        d = torch.sqrt(torch.where(pivot > 0, pivot, torch.ones_like(pivot)))
        cols[j][j] = d
        for i in range(j + 1, n):
            v = H[..., i, j]
            for k in range(j):
                v = v - cols[i][k] * cols[j][k]
            cols[i][j] = v / d
    zero = torch.zeros_like(H[..., 0, 0])
    L = torch.stack([torch.stack([cols[i][j] if j <= i else zero for j in range(n)], -1) for i in range(n)], -2)
    L = torch.where(ok.unsqueeze(-1).unsqueeze(-1), L, eye)
    return L, (~ok).to(torch.int32)


def _cholesky_solve(b: Tensor, L: Tensor) -> Tensor:
    """Solve ``L Lᵀ x = b`` for ``b (..., n, m)`` with the factor of :func:`_cholesky`."""
    n = L.shape[-1]
    if n == 1:
        return b / L / L
    if not _elementwise(n):
        return torch.cholesky_solve(b, L)
    y = [None] * n
    for i in range(n):
        v = b[..., i, :]
        for k in range(i):
            v = v - L[..., i, k].unsqueeze(-1) * y[k]
        y[i] = v / L[..., i, i].unsqueeze(-1)
    x = [None] * n
    for i in range(n - 1, -1, -1):
        v = y[i]
        for k in range(i + 1, n):
            v = v - L[..., k, i].unsqueeze(-1) * x[k]
        x[i] = v / L[..., i, i].unsqueeze(-1)
    return torch.stack(x, -2)


def _factored_solve(H: Tensor, L: Tensor, info: Tensor, b: Tensor) -> Tensor:
    """``_cholesky_solve(b, L)`` for the factor ``L, info`` of ``H`` by :func:`_cholesky`.

    Eager, an LU solve of ``H`` (the identity where ``info > 0``, as ``L``) is the cheaper LAPACK call for
    a matrix right-hand side (about half the time of ``torch.cholesky_solve`` at B = 256, nu = 4)."""
    n = H.shape[-1]
    if n == 1 or _elementwise(n):
        return _cholesky_solve(b, L)
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    return torch.linalg.solve_ex(torch.where((info == 0).unsqueeze(-1).unsqueeze(-1), H, eye), b)[0]


def _solve(M: Tensor, R: Tensor) -> Tensor:
    """``M⁻¹ R`` for ``M (..., n, n)`` and ``R (..., n, m)``: ``torch.linalg.solve_ex`` eager (an instance whose
    ``M`` is singular gets what LAPACK leaves, never an error), or, for the smallest sizes while traced or captured
    (:func:`_elementwise`), Gaussian elimination with partial pivoting written out elementwise (a pivot row is the
    one of largest magnitude in its column, the rows exchanged by selections)."""
    n = M.shape[-1]
    if not _elementwise(n):
        return torch.linalg.solve_ex(M, R)[0]
    rows = list(torch.cat([M, R], -1).unbind(-2))
    for k in range(n):
        for i in range(k + 1, n):
            larger = (rows[i][..., k].abs() > rows[k][..., k].abs()).unsqueeze(-1)
            rows[k], rows[i] = torch.where(larger, rows[i], rows[k]), torch.where(larger, rows[k], rows[i])
        for i in range(k + 1, n):
            rows[i] = rows[i] - rows[i][..., k:k + 1] / rows[k][..., k:k + 1] * rows[k]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        v = rows[i][..., n:]
        for j in range(i + 1, n):
            v = v - rows[i][..., j:j + 1] * x[j]
        x[i] = v / rows[i][..., i:i + 1]
    return torch.stack(x, -2)


def _mm_stacked(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for the blocks stacked over ``(δx, δu)``: as :func:`torchtraj.core.compiled.matmul`, but written
    as a broadcast sum when traced whatever the contraction ``nx + nu``, so that the congruence
    ``Eᵀ H E`` of :func:`~torchtraj.riccati.factorize` stays in inductor's loops as its unstacked products did."""
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return _mm(a, b)


def _pad_rows(a: Tensor, rows: int) -> Tensor:
    """Truncate or zero-pad the second-to-last dimension of ``a`` to ``rows``."""
    n = a.shape[-2]
    if n >= rows:
        return a[..., :rows, :]
    pad = a.new_zeros(*a.shape[:-2], rows - n, a.shape[-1])
    return torch.cat([a, pad], -2)


def _pad_cols(a: Tensor, cols: int) -> Tensor:
    return _mT(_pad_rows(_mT(a), cols))


def _time_major(stages: list) -> Tensor:
    """The per-stage tensors ``(B, ...)`` of a sweep as one batch-first ``(B, len, ...)`` view of a time-major
    buffer. A later sweep reads ``[:, t]``: one contiguous block, where a batch-first buffer would give B
    pieces a stage apart: the small products are bound by memory, not arithmetic, and read time-major they take
    less than half the time of batch-first ones."""
    return torch.stack(stages, 0).transpose(0, 1)


def _batch_first(x: Tensor, B: int) -> Tensor:
    """``x (N·B, …)`` time-major as a batch-first ``(B, N, …)`` view; a column stack loses its last dimension."""
    if x.shape[-1] == 1 and x.dim() == 3:
        x = x.squeeze(-1)
    return x.unflatten(0, (-1, B)).transpose(0, 1)
