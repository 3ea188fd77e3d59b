r"""Declared simple bounds: stage rows that hold controls, solved without the constraint back-propagation.

``LQR.bounds (m, nu)`` declares the stage rows ``D_k δu_k + e_k = 0`` (``C_k = 0``, no terminal rows) simple
bounds: each row is ``±1`` on one control, ``±δu_i + e = 0``. An active row (``mask``) then holds its control at
``δu_i = ∓e``, and the recursion fixes those controls instead of rotating and back-propagating rows (no SVD,
:mod:`torchtraj.riccati.propagation`). With ``F = diag(f)``, ``f`` the free controls of the stage,

.. math::  K = -(F (Q_{uu} + \rho I) F + I - F)^{-1} F Q_{ux},\qquad
           k = h - (F (Q_{uu} + \rho I) F + I - F)^{-1} F (Q_u + Q_{uu} h),

where ``h`` holds the held controls' values (zero on the free ones): the free controls minimise the stage's
Q-function given the held ones. A held control's row has the multiplier of its stationarity residual,
``ν = −bounds_i (Q_{uu} δu + Q_{ux} δx + Q_u)``, zero on inactive rows. Two active rows on one control depend on
each other.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .lqr import LQR, LQRVectors


def _held_controls(lqr: LQR, dtype: torch.dtype) -> Tensor:
    """``(B, N, nu)``: 1 on the controls that the active ``bounds`` rows hold, 0 on the free ones."""
    if lqr.CN is not None:
        raise ValueError("LQR.bounds declares the stage rows simple bounds: no terminal rows go with them")
    return (lqr.mask @ lqr.bounds.abs().to(dtype)).clamp(max=1.0)


def _held_values(fixed: Optional[Tensor], lqr: LQR, rhs: LQRVectors) -> Optional[Tensor]:
    """``(B, N, nu)``: the values ``δu_i = ∓e`` at which the active ``bounds`` rows hold their controls
    (``fixed``: :func:`_held_controls`, ``None`` without declared bounds)."""
    if fixed is None:
        return None
    if rhs.e is None:
        return torch.zeros_like(fixed)
    return -(rhs.e * lqr.mask) @ lqr.bounds.to(rhs.e.dtype)


def _bound_multipliers(lqr: LQR, fixed: Tensor, Quu: Tensor, Qux: Tensor, dx: Tensor, du: Tensor,
                       Qu: Tensor) -> Tensor:
    """``ν (B, N, m)``: a held control's stationarity residual, on the rows that hold it.

    ``Quu (B, N, nu, nu)``, ``Qux (B, N, nu, nx)``, ``Qu (B, N, nu)`` the Q-functions, ``dx (B, N+1, nx)`` and
    ``du (B, N, nu)`` the step."""
    grad_u = (Quu @ du.unsqueeze(-1) + Qux @ dx[:, :-1].unsqueeze(-1)).squeeze(-1) \
        + Qu
    return ((-grad_u * fixed) @ lqr.bounds.T.to(grad_u.dtype)) * lqr.mask
