r"""Pseudo-inverses of batches of small matrices by one-sided Jacobi rotations, in elementwise operations alone.

LAPACK-style solvers (``torch.linalg.eigh``, ``svd``, ``pinv``) check their status on the host after every call:
on a GPU that is a copy to the host, which a CUDA graph cannot capture, and the batched eigensolver of cuSOLVER
has failed outright on millions of tiny matrices. This module computes the same pseudo-inverse with the batch in
every operation and no host read, for the range-space method's small matrices (a handful of terminal rows) when
they are on a GPU or in a single instance's compiled kernel, and for the terminal rows themselves in any compiled
kernel (:mod:`~torchtraj.riccati.range_space`).

**Hestenes' one-sided Jacobi method** (Golub & Van Loan, *Matrix Computations*, 4th ed., §8.6.3). The columns
``a_p`` of ``A (r, c)`` are rotated in pairs until they are orthogonal: with ``α = ‖a_p‖²``, ``β = ‖a_q‖²``,
``γ = a_pᵀ a_q`` and ``d = β − α``, the rotation

.. math::  t = \frac{2γ}{d + \operatorname{sign}(d) \sqrt{d^2 + 4γ^2}}, \quad c = \frac{1}{\sqrt{1 + t^2}},
    \quad s = c t, \qquad a_p ← c a_p − s a_q, \quad a_q ← s a_p + c a_q

(the root of ``γ t² + d t − γ = 0`` of modulus at most one) makes them orthogonal, and the same rotations of the
identity's columns give ``V``. After the sweeps ``A V = W`` has orthogonal columns ``w_j = σ_j u_j``, so
``A = W Vᵀ`` and ``A⁺ = V \operatorname{diag}(1/σ_j^2) Wᵀ`` over the ``σ_j`` above ``rtol`` times the largest
(``torch.linalg.pinv``'s rule). A pair of columns is orthogonal after one rotation; for more columns the cyclic
sweeps converge quadratically, and :data:`SWEEPS` of them reach double precision on the few columns used here.
The method computes small singular values to high relative accuracy (Demmel & Veselić 1992), so the rank decision
is LAPACK's to rounding.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.compiled import matmul

#: cyclic sweeps over the column pairs where there are more than two columns (two need one rotation)
SWEEPS = 8


def pinv(A: Tensor, rtol: float) -> Tensor:
    """The pseudo-inverse of ``A (..., r, c)`` (``(..., c, r)``), its singular values below ``rtol`` times the
    largest dropped; the transposed problem where ``A`` is wide, so that the rotations pair the fewer columns."""
    if A.shape[-1] > A.shape[-2]:
        return pinv(A.mT, rtol).mT
    columns = list(A.unbind(-1))
    c = len(columns)
    eye = torch.eye(c, dtype=A.dtype, device=A.device).expand(*A.shape[:-2], c, c)
    v = list(eye.unbind(-1))
    sweeps = 0 if c == 1 else 1 if c == 2 else SWEEPS
    for _ in range(sweeps):
        for p in range(c - 1):
            for q in range(p + 1, c):
                columns[p], columns[q], v[p], v[q] = _rotated(columns[p], columns[q], v[p], v[q])
    W, V = torch.stack(columns, -1), torch.stack(v, -1)
    squares = W.square().sum(-2)  # σ_j²
    largest = squares.amax(-1, keepdim=True)
    keep = squares > (rtol * rtol) * largest  # never a zero column: the right side is at least zero
    weights = torch.where(keep, squares.reciprocal(), torch.zeros_like(squares))
    return matmul(V * weights.unsqueeze(-2), W.mT)


def _rotated(a_p: Tensor, a_q: Tensor, v_p: Tensor, v_q: Tensor) -> tuple:
    """The pair of columns ``a_p, a_q`` made orthogonal by one rotation, and the rotation applied to ``v_p, v_q``
    (module docstring)."""
    alpha, beta, gamma = a_p.square().sum(-1), a_q.square().sum(-1), (a_p * a_q).sum(-1)
    d = beta - alpha
    root = torch.sqrt(d.square() + 4.0 * gamma.square())
    denominator = d + torch.where(d >= 0, root, -root)
    t = torch.where(denominator != 0, 2.0 * gamma / torch.where(denominator != 0, denominator, 1.0), 0.0)
    cos = torch.rsqrt(1.0 + t.square())
    sin = (cos * t).unsqueeze(-1)
    cos = cos.unsqueeze(-1)
    return cos * a_p - sin * a_q, sin * a_p + cos * a_q, cos * v_p - sin * v_q, sin * v_p + cos * v_q
