r"""Constraint back-propagation: the equality rows of the generalised Riccati recursion.

Equality constraints are handled by the generalised Riccati recursion with constraint back-propagation (Horizon
eILQR, Laurenzi et al. §II-B/C; FATROP, Vanroye et al. 2023, its reference [30]). At stage k the stage rows
and the rows propagated from stage k+1,

.. math::  M_x \delta x + M_u \delta u + m = 0,\quad
           M = \begin{bmatrix} C_k & D_k \\ G_{k+1} A_k & G_{k+1} B_k \end{bmatrix},
           \quad m = \begin{bmatrix} e_k \\ G_{k+1} c_k + g_{k+1} \end{bmatrix},

are rotated by the SVD ``M_u = U Σ Vᵀ``. Directions with a singular value above a relative tolerance
(:func:`default_rank_tolerance` times the magnitude of ``M``) fix the matching components of ``δu``,
``δu = K_c δx + k_c + V_f w`` with ``K_c = −V Σ⁺ Uᵀ M_x``, ``k_c = −V Σ⁺ Uᵀ m``; the remaining rows involve ``δx``
only and are compressed (a second SVD, :func:`_compress`) into at most ``nx`` rows ``G_k δx + g_k = 0`` passed to
stage k-1. Rows below the tolerance are round-off of an elimination and dropped, so that the ranks, decided per
instance, never change a tensor's shape: rows are masked and padded instead. The free control directions ``V_f``
minimise the stage's Q-function:

.. math::  \delta u = K \delta x + k,\quad K = K_c + V_f K_w,\quad
           K_w = -(V_f^T (Q_{uu} + \rho I) V_f + \Pi_{fixed})^{-1} V_f^T (Q_{ux} + Q_{uu} K_c).

The multipliers follow by a forward sweep: on the fixing directions the rotated rows' multipliers are
``−Σ⁻¹ Vᵀ ∇_u`` of the stage's Q-function (its u-stationarity), on the others the multipliers ``η_k`` of the
compressed rows ``G_k``; rotated back by ``U``, they split into the stage rows' ``ν_k`` and the ``η_{k+1}`` of the
rows handed to stage k+1. The rows ``G_0`` have no earlier stage: the initial condition absorbs them (``η_0 = 0``).

This module holds the rows' data (:class:`_Constraint`), the terminal rows' compression and the rank tolerance;
the sweeps themselves are written stage-lean in :mod:`~torchtraj.riccati.rows`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..core.compiled import matvec as _mv
from .linalg import _mT, _pad_cols, _pad_rows
from .lqr import LQR, LQRVectors


def default_rank_tolerance(dtype: torch.dtype) -> float:
    """Relative singular-value threshold that separates satisfiable from back-propagated rows."""
    return float(torch.finfo(dtype).eps) ** 0.75


@dataclass
class _Constraint:
    """Per-stage data of the constraint back-propagation (all batched over B)."""

    U: Tensor  # (B, mt, mt) left singular vectors of M_u
    inv_s: Tensor  # (B, nu) 1/σ on fixed directions, 0 elsewhere
    V: Tensor  # (B, nu, nu) right singular vectors of M_u
    rest: Tensor  # (B, mt) rows left for earlier stages
    U2: Tensor  # (B, mt, nx) left singular vectors of the propagated rows (padded)
    gmask: Tensor  # (B, nx) propagated rows that are kept
    G: Tensor  # (B, nx, nx) propagated constraint matrix on δx_k


def _compress(R: Tensor, nx: int, tol: float, scale: Tensor):
    """Rows ``R (B, mt, nx)`` acting on δx compressed to ``G (B, nx, nx)`` by an SVD.

    Rows with a singular value below ``tol * scale`` (``scale (B,)``: the magnitude of the
    constraint rows before elimination) are round-off and dropped.
    Returns ``(U2 (B, mt, nx), gmask (B, nx), G)`` with ``G = diag(σ) V2ᵀ`` on kept rows."""
    if R.shape[-2] == 0:  # no rows: nothing to propagate (a shape, not a value, decides)
        zeros = R.new_zeros(R.shape[0], nx)
        return R.new_zeros(R.shape[0], 0, nx), zeros, R.new_zeros(R.shape[0], nx, nx)
    U2, s2, V2h = torch.linalg.svd(R, full_matrices=True)
    r = s2.shape[-1]
    s_pad = _pad_rows(s2.unsqueeze(-1), nx).squeeze(-1)
    gmask = (s_pad > tol * scale.unsqueeze(-1)).to(R.dtype)
    G = _pad_rows(s2.unsqueeze(-1) * V2h[..., :r, :], nx) * gmask.unsqueeze(-1)
    return _pad_cols(U2, nx), gmask, G


def _terminal_constraint(lqr: LQR, tol: float) -> _Constraint:
    """The terminal rows ``C_N δx_N + e_N = 0`` (masked) compressed: the rows ``G_N`` that stage N-1 sees."""
    Bsz, nx = lqr.A.shape[0], lqr.A.shape[-1]
    dtype = lqr.A.dtype
    CN = lqr.CN * lqr.maskN.unsqueeze(-1) if lqr.CN is not None else lqr.A.new_zeros(Bsz, 0, nx)
    scale = CN.abs().amax(dim=(-1, -2)) if CN.shape[1] else CN.new_zeros(Bsz)
    U2, gmask, G = _compress(CN, nx, tol, scale.clamp_min(torch.finfo(dtype).tiny))
    return _Constraint(U=None, inv_s=None, V=None, rest=None, U2=U2, gmask=gmask, G=G)


def _stage_rows(lqr: LQR) -> Tensor:
    """``(B, N, m, nx+nu)``: the active stage rows ``[C_k D_k]`` (masked; a missing block is zero)."""
    Bsz, N, nx, nu = lqr.B.shape[0], lqr.B.shape[1], lqr.A.shape[-1], lqr.B.shape[-1]
    if lqr.C is not None or lqr.D is not None:
        C = lqr.C if lqr.C is not None else lqr.A.new_zeros(Bsz, N, lqr.D.shape[2], nx)
        D = lqr.D if lqr.D is not None else lqr.A.new_zeros(Bsz, N, C.shape[2], nu)
        return torch.cat([C, D], -1) * lqr.mask.unsqueeze(-1)
    return lqr.A.new_zeros(Bsz, N, 0, nx + nu)


def _terminal_rhs(terminal: _Constraint, lqr: LQR, rhs: LQRVectors) -> Tensor:
    """``g_N (B, nx)``: the right-hand side of the compressed terminal rows."""
    eN = rhs.eN * lqr.maskN if rhs.eN is not None else rhs.qN.new_zeros(rhs.qN.shape[0], 0)
    return _mv(_mT(terminal.U2), eN) * terminal.gmask
