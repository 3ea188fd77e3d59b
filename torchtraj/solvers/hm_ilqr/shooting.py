r"""Multiple-shooting M-iLQR (§II-B, Algorithm 1; Giftthaler et al.'s GNMS, the paper's [10]).

The horizon is cut into ``M`` segments of ``L = ⌈N / M⌉`` steps (the last one may be shorter); the segment starts
``k = 0, L, 2L, …`` are the *nodes*, decision variables of their own. The defects

.. math::  d_k = f(x_k, u_k) - x_{k+1}

are nonzero only where ``x_{k+1}`` is a node; the linearised dynamics become ``δx_{k+1} = A_k δx_k + B_k δu_k + d_k``
(eq. 8), which the shared Riccati core takes as its affine terms ``c`` (``LQRVectors.c``): its value-function
gradient is then ``V_x^+ = V_x + V_xx d_k`` (eq. 10).

**Forward pass.** The LQR solution ``(δx, δu)`` gives the node update ``x̂_n = x_n + α δx_n`` (eq. 11, the linear
model's prediction; with ``α`` the step of the whole multiple-shooting point, so that the defects shrink to
``(1 − α) d`` up to second order), and every segment is re-integrated from its updated node under the policy of
eq. (19), ``û_k = u_k + α k_k + K_k (x̂_k − x_k)``. The ``M`` segments roll out together, one loop over the ``L`` steps
of a segment: the sequential depth of a forward pass is ``L``, not ``N``. Every step size of a line-search round is
simulated in the same batched rollout.

**Expected change** (§III-C-1). Along the step the quadratic model changes the objective by
``α ΔV_1 + α²/2 ΔV_2`` with ``ΔV_1 = Σ (q_kᵀ δx_k + r_kᵀ δu_k) + q_Nᵀ δx_N`` and ``ΔV_2 = Σ δz_kᵀ H_k δz_k +
δx_Nᵀ Q_N δx_N`` (which are ``Σ k_ffᵀ Q_u`` and ``Σ k_ffᵀ Q_uu k_ff`` when the defects are zero), and the merit
``J_[·] + w Σ dᵀd`` by ``ΔV(α) = α ΔV_1 + α²/2 ΔV_2 − w (1 − (1 − α)²) Σ dᵀd``: the defect term of the paper,
taken as the decrease of the merit's defect part that the model predicts. Where closing the defects costs more
objective than ``w Σ dᵀd`` pays for, ``w`` is raised for the iteration to ``w + max(0, ΔV_1 + ΔV_2/2) / Σ dᵀd``
(the penalty-parameter rule of SQP merit functions), so that the model always predicts a decrease; with
``monotone_defect_weight`` it is never lowered again within a stage (a merit that changes from one iteration to
the next lets the iterates cycle, :class:`~torchtraj.solvers.hm_ilqr.options.HMILQROptions`). A step is
accepted where the ratio of the actual to the expected change lies in ``[z_lo, z_hi]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import stage_mapper
from ...core.compiled import matvec
from ...riccati.sweep import costate_stages


@dataclass(frozen=True)
class Segments:
    """``M`` segments of ``L`` steps over a horizon of ``N``: ``starts (M,)`` the nodes ``i L``."""

    N: int
    L: int
    M: int
    starts: Tensor

    @classmethod
    def of(cls, N: int, segments: int, device=None) -> "Segments":
        if segments < 1:
            raise ValueError(f"segments must be a positive int, got {segments!r}")
        L = math.ceil(N / min(segments, N))
        M = math.ceil(N / L)
        return cls(N=N, L=L, M=M, starts=torch.arange(M, device=device) * L)

    @property
    def last_length(self) -> int:
        return self.N - (self.M - 1) * self.L

    def node_mask(self, like: Tensor) -> Tensor:
        """``(N,)``: 1 at the steps ``k`` whose successor ``x_{k+1}`` is a node (where a defect may be)."""
        mask = torch.zeros(self.N, dtype=like.dtype, device=like.device)
        mask[self.starts[1:] - 1] = 1.0
        return mask


def defects(f: Tensor, X: Tensor, segments: Segments) -> Tensor:
    """``d_k = f(x_k, u_k) − x_{k+1}`` ``(B, N, nx)``, zero inside the segments."""
    return (f - X[:, 1:]) * segments.node_mask(X).unsqueeze(-1)


def rollout_segments(dynamics, params, nodes: Tensor, U: Tensor, segments: Segments, X_ref=None, K=None,
                     feedforward=None, record: Optional[bool] = False):
    """Integrate every segment from its node under ``u_k = U_k + feedforward_k + K_k (x_k − X_ref_k)``.

    ``nodes (B, *E, M, nx)`` (node 0 is ``x_0``), ``U (B, N, nu)``, ``feedforward (B, *E, N, nu)`` (the
    ``α k_ff`` of each candidate), ``X_ref (B, N+1, nx)``, ``K (B, N, nu, nx)``; without ``K`` the controls are
    ``U`` (Algorithm 1's initial forward pass). Returns ``X (B, *E, N+1, nx)``, the applied ``U (B, *E, N, nu)``
    and the sum of squared defects ``Σ dᵀd`` ``(B, *E)`` between each segment's end and the next node. ``record``:
    each step replayed from its recorded graph (:func:`~torchtraj.core.batching.stage_mapper`).
    """
    L, M, N = segments.L, segments.M, segments.N
    lead = nodes.shape[:-2]
    extra = len(lead) - 1
    x = nodes
    xs, us = [x], []
    step = stage_mapper(dynamics, params, record)
    for j in range(L):  # all segments at once: the sequential depth is L
        k = (segments.starts + j).clamp(max=N - 1)  # steps past N (a shorter last segment) are discarded below
        u = U[:, k].reshape(U.shape[0], *([1] * extra), M, U.shape[-1])
        if feedforward is not None:
            u = u + feedforward[..., k, :]
        if K is not None:
            Kk = K[:, k].reshape(K.shape[0], *([1] * extra), M, *K.shape[2:])
            Xr = X_ref[:, k].reshape(X_ref.shape[0], *([1] * extra), M, X_ref.shape[-1])
            u = u + matvec(Kk, x - Xr)
        u = u.expand(*lead, M, U.shape[-1])
        x = step(x, u)
        xs.append(x)
        us.append(u)
    states = torch.stack(xs, -2)  # (B, *E, M, L+1, nx)
    controls = torch.stack(us, -2)  # (B, *E, M, L, nu)
    nx, nu = states.shape[-1], controls.shape[-1]
    X = states[..., :L, :].reshape(*lead, M * L, nx)[..., :N, :]
    X = torch.cat([X, states[..., M - 1, segments.last_length, :].unsqueeze(-2)], -2)
    Uout = controls.reshape(*lead, M * L, nu)[..., :N, :]
    gaps = states[..., :-1, L, :] - states[..., 1:, 0, :]  # (B, *E, M-1, nx)
    return X, Uout, (gaps * gaps).sum((-1, -2))


def model_change(lqr, rhs, dx: Tensor, du: Tensor) -> tuple:
    """``(ΔV_1, ΔV_2)`` ``(B,)`` of the module docstring: the LQR model's linear and quadratic parts along the
    full step ``δx (B, N+1, nx)``, ``δu (B, N, nu)``."""
    x, xN = dx[:, :-1], dx[:, -1]
    dV1 = (rhs.q * x).sum((1, 2)) + (rhs.r * du).sum((1, 2)) + (rhs.qN * xN).sum(-1)
    Qx = matvec(lqr.Q, x) + matvec(lqr.S.transpose(-1, -2), du)
    Ru = matvec(lqr.S, x) + matvec(lqr.R, du)
    dV2 = (x * Qx).sum((1, 2)) + (du * Ru).sum((1, 2)) + (xN * matvec(lqr.QN, xN)).sum(-1)
    return dV1, dV2


def merit_weight(dV1: Tensor, dV2: Tensor, D: Tensor, w: float) -> Tensor:
    """The defect weight of the iteration ``(B,)``: ``w``, raised so that the model predicts a decrease."""
    return w + (dV1 + 0.5 * dV2).clamp_min(0) / D.clamp_min(torch.finfo(D.dtype).tiny)


def expected_change(alphas: Tensor, dV1: Tensor, dV2: Tensor, D: Tensor, weight: Tensor) -> Tensor:
    """``ΔV(α)`` ``(B, l)`` for the step sizes ``alphas (l,)``."""
    a = alphas.unsqueeze(0)
    closed = 1 - (1 - a) ** 2
    return a * dV1.unsqueeze(1) + 0.5 * a * a * dV2.unsqueeze(1) - closed * (weight * D).unsqueeze(1)


def stationarity(lqr, rhs, nu=None, nuN=None) -> Tensor:
    """``max_k |r_k + B_kᵀ λ_{k+1} + D_kᵀ ν_k|∞`` ``(B,)``: the residual of the objective's Lagrangian in the
    controls at the expansion point, with the costates of its stationarity in the states, ``λ_N = q_N + C_Nᵀ ν_N``,
    ``λ_k = q_k + A_kᵀ λ_{k+1} + C_kᵀ ν_k`` (the KKT certificate's, :mod:`torchtraj.kkt.certificate`, for the
    multipliers ``P'`` that ``q``, ``r`` hold), and the held rows' multipliers ``ν``, ``ν_N`` of an LQR step."""
    lam = costates(lqr, rhs, nu, nuN)
    reduced = rhs.r
    if nu is not None and lqr.C is not None and nu.shape[-1]:
        reduced = reduced + matvec(lqr.D.transpose(-1, -2), nu * lqr.mask)
    reduced = reduced + matvec(lqr.B.transpose(-1, -2), lam[:, 1:])
    return reduced.abs().flatten(1).amax(-1)


def costates(lqr, rhs, nu=None, nuN=None) -> Tensor:
    """``λ (B, N+1, nx)`` that make the objective's Lagrangian stationary in the states at the expansion point:
    ``λ_N = q_N + C_Nᵀ ν_N``, ``λ_k = q_k + A_kᵀ λ_{k+1} + C_kᵀ ν_k`` (the held rows' ``ν``, ``ν_N``; none: 0)."""
    last, local = rhs.qN, rhs.q
    if nuN is not None and lqr.CN is not None and nuN.shape[-1]:
        last = last + matvec((lqr.CN * lqr.maskN.unsqueeze(-1)).transpose(-1, -2), nuN)
    if nu is not None and lqr.C is not None and nu.shape[-1]:
        local = local + matvec(lqr.C.transpose(-1, -2), nu * lqr.mask)
    return costate_stages(lqr.A, local, last)
