r"""The AL stage of HM-iLQR (§III-A, Algorithm 2, eqs. 13-16): the penalty terms and the multiplier update.

For an inequality row ``g ≤ 0`` with multiplier ``λ ≥ 0`` and penalty ``μ`` the term is the smooth augmented
Lagrangian (Powell-Hestenes-Rockafellar)

.. math::

    P(g) = \frac{1}{2\mu}\left(\max(0, \lambda + \mu g)^2 - \lambda^2\right),\qquad
    P'(g) = \max(0, \lambda + \mu g),\qquad P''(g) = \mu\,[\lambda + \mu g > 0],

which is the paper's ``λᵀh + μ/2 ‖h‖²``, ``h = max(0, g)`` (eq. 13), wherever ``g ≥ 0``, and differs from it only in
the band ``−λ/μ < g < 0``, where it keeps the multiplier's pull. It is the term whose minimiser makes eq. (15),
``λ ← max(0, λ + μ g)``, the first-order multiplier estimate, and it is differentiable. Its Gauss-Newton expansion
with the linearised rows gives eq. (14): ``Q_z += g_zᵀ P'``, ``Q_zz += g_zᵀ P'' g_z``. An equality row ``h = 0`` has
``λ h + μ/2 h²`` (ALTRO's form, ``λ ← λ + μ h``) in this stage; the RLB stage holds those rows in the Riccati core
instead (:mod:`~torchtraj.solvers.hm_ilqr.objective`). After every iteration (one inner M-iLQR
iteration per update, as the issue asks) the penalty grows, ``μ ← min(φ μ, μ_max)`` (eq. 16).
"""

from __future__ import annotations

import torch
from torch import Tensor


def al_inequality(g: Tensor, lam: Tensor, mu: Tensor, derivatives: bool = True) -> tuple:
    """Value, first and second derivative of the PHR term of rows ``g`` (all broadcast together); ``(value,)`` alone
    without ``derivatives``."""
    t = (lam + mu * g).clamp_min(0)
    value = (t * t - lam * lam) / (2 * mu)
    if not derivatives:
        return (value,)
    return value, t, torch.where(lam + mu * g > 0, mu, torch.zeros_like(t))


def al_equality(h: Tensor, lam: Tensor, mu: Tensor) -> tuple:
    """Value, first and second derivative of ``λ h + μ/2 h²`` (all broadcast together)."""
    d1 = lam + mu * h
    return lam * h + 0.5 * mu * h * h, d1, mu * torch.ones_like(h)


def updated_multipliers(g: Tensor, lam: Tensor, mu: Tensor, dual_max: float) -> Tensor:
    """Eq. (15), ``λ ← max(0, λ + μ g)``, clipped to ``dual_max``."""
    return (lam + mu * g).clamp(0, dual_max)


def increased_penalty(mu: Tensor, scaling: float, maximum: float) -> Tensor:
    """Eq. (16), ``μ ← min(φ μ, μ_max)``."""
    return (mu * scaling).clamp_max(maximum)
