r"""The inequality multipliers of an RLB iterate, corrected along its Newton step; the stationarity they leave.

The barrier's implied multiplier of a row, ``P' = ψ / z`` (``z = −g``), is exact only at the barrier problem's
minimiser, and near an active row it is as sensitive as ``z`` is small: an error ``e`` of the slack changes it by
``P' e / z``. In float32 the slack of an active row is known to ``ε |g|`` (``6e-8`` for a bound of ``0.5``) while
``z = ψ / P'`` is ``1e-5`` or less at the barrier's final weight, so ``P'`` carries errors of several percent and
the KKT residual with it stays far above any tolerance (``5e-2`` on the double integrator of the tests, at every
``ψ_min`` the complementarity tolerance allows).

The primal-dual estimate takes the multiplier's first-order change along the Newton step ``δw`` of the barrier
problem, whose linearised rows change by ``δg = G δw``:

.. math::  z^+ = \max\left(0,\ P' + P''\, δg\right) = \max\left(0,\ \frac{ψ}{z}\left(1 - \frac{δz}{z}\right)\right)

(the multiplier a primal-dual interior point's Newton step would reach from the barrier's point). With ``z⁺`` in
place of ``P'`` the Lagrangian's gradient is that of the model after the step less the part of the step the
barrier's curvature ``G^T P'' G`` took up: what remains is the cost's curvature times ``δw``, small where ``δw`` is,
whatever the curvature ``ψ / z²`` of the active rows. The exit test measures stationarity with ``z⁺``, and a
converged solution reports ``z⁺`` (an instance in the AL stage keeps its estimate ``max(0, λ + μ g)``).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...core.compiled import matvec
from .objective import InequalityRows


def stepped_multipliers(rows: InequalityRows, dx: Tensor, du: Tensor, rlb: Tensor) -> tuple:
    """``z⁺ (B, N, mi)`` and ``z_N⁺ (B, miN)`` (``None`` without rows) of the step ``δx (B, N+1, nx)``,
    ``δu (B, N, nu)`` where ``rlb (B,)``; ``P'`` elsewhere."""
    z = zN = None
    if rows.Cz is not None:
        dg = matvec(rows.Cz, torch.cat([dx[:, :-1], du], -1))
        z = torch.where(rlb.reshape(-1, 1, 1), (rows.d1 + rows.d2 * dg).clamp_min(0), rows.d1)
    if rows.CN is not None:
        dgN = matvec(rows.CN, dx[:, -1])
        zN = torch.where(rlb.reshape(-1, 1), (rows.d1N + rows.d2N * dgN).clamp_min(0), rows.d1N)
    return z, zN


def with_multipliers(rhs, rows: InequalityRows, nx: int, z, zN):
    """The right-hand side ``rhs`` (the objective's gradient, ``P'`` in it) with the multipliers ``z``, ``zN``."""
    q, r, qN = rhs.q, rhs.r, rhs.qN
    if z is not None:
        change = matvec(rows.Cz.transpose(-1, -2), z - rows.d1)
        q, r = q + change[..., :nx], r + change[..., nx:]
    if zN is not None:
        qN = qN + matvec(rows.CN.transpose(-1, -2), zN - rows.d1N)
    return dataclasses.replace(rhs, q=q, r=r, qN=qN)
