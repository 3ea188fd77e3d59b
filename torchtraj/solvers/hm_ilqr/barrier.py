r"""The RLB stage of HM-iLQR (§III-B, Algorithm 3, eqs. 17-18): the relaxed log barrier and its parameter update.

For an inequality row ``g ≤ 0``, with ``z = −g``,

.. math::

    B(g; \psi, \delta) = \begin{cases} -\psi \ln z, & z \ge \delta \\ \psi\,\beta(z; \delta), & z < \delta \end{cases},
    \qquad \beta(z; \delta) = \tfrac12\left(\left(\frac{z - 2\delta}{\delta}\right)^2 - 1\right) - \ln \delta,

the quadratic extension of Hauser & Saccon, which joins the logarithm at ``z = δ`` with equal value, slope
``−1/δ`` and curvature ``1/δ²``: the barrier is twice differentiable and defined at infeasible points, which the
feedback term of the forward pass may reach (the paper's footnote 1). Its derivatives in ``g`` are

.. math::

    B' = \psi / z \ \text{(log)},\quad \psi (2\delta - z) / \delta^2 \ \text{(extension)};\qquad
    B'' = \psi / z^2 \ \text{(log)},\quad \psi / \delta^2 \ \text{(extension)},

and ``B' ≥ 0`` is the row's implied multiplier (``ψ / (−g)`` on the log branch). The M-iLQR model takes the
Gauss-Newton expansion ``Q_z += g_zᵀ B'``, ``Q_zz += g_zᵀ B'' g_z`` as for the AL terms. Between iterations
``ψ ← max(ψ_min, ω_1 ψ)`` (18a) and ``δ ← max(δ_min, ω_2 δ)`` (18b).

Equality rows (the goal ``x_N = x_g``) cannot be barriered; they are held as the Riccati core's stagewise
equalities in both stages (:mod:`~torchtraj.solvers.hm_ilqr.objective` says why).
"""

from __future__ import annotations

import torch
from torch import Tensor


def relaxed_log_barrier(g: Tensor, psi: Tensor, delta: Tensor, derivatives: bool = True) -> tuple:
    """Value, first and second derivative in ``g`` of ``B(g; ψ, δ)`` (all broadcast together); ``(value,)`` alone
    without ``derivatives`` (a line search's trial points)."""
    z = -g
    log = z >= delta
    z_log = torch.where(log, z, torch.ones_like(z))  # the logarithm only where it is taken
    ext = (z - 2 * delta) / delta
    value = torch.where(log, -torch.log(z_log), 0.5 * (ext * ext - 1) - torch.log(delta))
    if not derivatives:
        return (psi * value,)
    d1 = torch.where(log, 1 / z_log, (2 * delta - z) / (delta * delta))
    d2 = torch.where(log, 1 / (z_log * z_log), 1 / (delta * delta))
    return psi * value, psi * d1, psi * d2


def updated_barrier(psi: Tensor, delta: Tensor, opts, tol) -> tuple:
    """Eqs. (18a-b): ``(ψ, δ) ← (max(ψ_min, ω_1 ψ), max(δ_min, ω_2 δ))``, the floors ``tol.barrier``,
    ``tol.relaxation`` of the dtype (:meth:`~torchtraj.solvers.hm_ilqr.options.HMILQROptions.tolerances`)."""
    return ((psi * opts.barrier_decrease).clamp_min(tol.barrier),
            (delta * opts.relaxation_decrease).clamp_min(tol.relaxation))
