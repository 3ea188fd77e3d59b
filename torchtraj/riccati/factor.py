r"""The factorised recursion and its solves: one right-hand side costs one backward and one forward sweep.

A :class:`RiccatiFactor` holds the matrix part of the recursion (:func:`~torchtraj.riccati.factorize`): gains
``K_k``, value-function Hessians ``P_k`` and the stage Q-functions' ``Q_uu``, ``Q_ux``. For a right-hand side
(:class:`~torchtraj.riccati.LQRVectors`) the backward sweep over vectors is, unconstrained (ALTRO eqs. 14-16),

.. math::

    v &= P_{k+1} c_k + p_{k+1},\quad Q_x = q_k + A_k^T v,\quad Q_u = r_k + B_k^T v,\\
    k_k &= -(Q_{uu} + \rho I)^{-1} Q_u,\quad
    p_k = Q_x + K_k^T (Q_{uu} k_k + Q_u) + Q_{ux}^T k_k,\quad p_N = q_N,

with the expected change of the quadratic model ``ΔV(α) = α Σ k_kᵀ Q_u + ½ α² Σ k_kᵀ Q_uu k_k``; constrained, the
feedforward comes from the rows (:mod:`~torchtraj.riccati.propagation`, :mod:`~torchtraj.riccati.bounds`). The
forward sweep rolls the step out, ``δu_k = K_k δx_k + k_k``, ``δx_{k+1} = A_k δx_k + B_k δu_k + c_k``.

Multipliers, when asked for: the constraint rows' ``ν`` by a forward sweep, then the costates backward from the
x-stationarity of the Lagrangian (Horizon eILQR, Laurenzi et al. eq. 5a),

.. math::  \lambda_N = Q_N \delta x_N + q_N + C_N^T \nu_N,\quad
           \lambda_k = Q_k \delta x_k + S_k^T \delta u_k + q_k + A_k^T \lambda_{k+1} + C_k^T \nu_k,

which, where the gains minimise every stage's Q-function exactly (no ``ρ``, no rows), are the value function's
gradients ``λ_k = P_k δx_k + p_k``: one product instead of a sweep.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import matvec as _mv
from .bounds import _bound_multipliers, _held_feedforward, _held_values
from .linalg import _cholesky_solve, _mT
from .lqr import LQR, LQRSolution, LQRVectors
from .propagation import _Constraint, _propagated_feedforward, _propagated_multipliers, _terminal_rhs


@dataclass
class RiccatiFactor:
    """Matrix part of the recursion, reusable for any right-hand side.

    ``K (B, N, nu, nx)`` feedback gains, ``P (B, N+1, nx, nx)`` value-function Hessians,
    ``ok (B,)`` whether every stage's reduced Hessian was positive definite.
    """

    lqr: LQR
    K: Tensor
    P: Tensor
    ok: Tensor
    Quu: Tensor
    Qux: Tensor
    chol: Tensor
    free: Optional[Tensor]  # (B, N, nu, nu) V_f
    stage: Optional[list]  # list of _Constraint per stage k
    terminal: Optional[_Constraint]
    #: the gains minimise every stage's Q-function exactly (no ``ρ``, no constraint rows): the costates are
    #: the value function's gradients ``λ_k = P_k δx_k + p_k``
    exact: bool = False
    #: ``(B, N, nu)``: 1 on the controls that active ``bounds`` rows hold (``None`` without declared bounds)
    fixed: Optional[Tensor] = None

    def solve(self, rhs: LQRVectors, multipliers: bool = False, initial_multiplier: Optional[Tensor] = None
              ) -> LQRSolution:
        """Solve the LQR problem for the right-hand side ``rhs`` (one backward and one forward sweep).

        ``initial_multiplier``: ``η_0 (B, nx)``, the multipliers of the rows ``G_0 δx_0 + g_0 = 0`` left at the
        initial state (:attr:`LQRSolution.g0`). With ``δx_0`` fixed any value solves the KKT conditions and the
        default is zero; where ``δx_0`` is optimised (Horizon eILQR §II-D) it is the one its stage-0 system gives."""
        lqr = self.lqr
        Bsz, N = lqr.B.shape[0], lqr.B.shape[1]
        constrained = lqr.propagated
        p_next = rhs.qN
        g_next = None
        ks, ps = [None] * N, [None] * (N + 1)
        Qus, Quuks = [None] * N, [None] * N
        ps[N] = p_next
        if constrained:
            g_next = _terminal_rhs(self.terminal, lqr, rhs)
        held = _held_values(self.fixed, lqr, rhs)
        for t in range(N - 1, -1, -1):
            A, Bu, P_next = lqr.A[:, t], lqr.B[:, t], self.P[:, t + 1]
            c = rhs.c[:, t]
            v = _mv(P_next, c) + p_next
            Qx = rhs.q[:, t] + _mv(_mT(A), v)
            Qu = rhs.r[:, t] + _mv(_mT(Bu), v)
            Quu, Qux, K = self.Quu[:, t], self.Qux[:, t], self.K[:, t]
            if constrained:
                e = rhs.e[:, t] * lqr.mask[:, t] if rhs.e is not None else Qu.new_zeros(Bsz, 0)
                G_after = self.stage[t + 1].G if t + 1 < N else self.terminal.G
                k, g_next = _propagated_feedforward(self.stage[t], G_after, self.free[:, t], self.chol[:, t], Quu, Qu,
                                                    e, c, g_next)
            elif held is not None:
                k = _held_feedforward(Qu, Quu, self.fixed[:, t], held[:, t], self.chol[:, t])
            else:
                k = -_cholesky_solve(Qu.unsqueeze(-1), self.chol[:, t]).squeeze(-1)
            Quuk = _mv(Quu, k)
            p_next = Qx + _mv(_mT(K), Quuk + Qu) + _mv(_mT(Qux), k)
            ks[t], ps[t], Qus[t], Quuks[t] = k, p_next, Qu, Quuk
        k_all = torch.stack(ks, 1)
        p_all = torch.stack(ps, 1)
        # the sums over stages once, after the sweep: seven operations a stage fewer
        Qu_all = torch.stack(Qus, 1)
        dV1 = (k_all * Qu_all).sum((1, 2))
        dV2 = 0.5 * (k_all * torch.stack(Quuks, 1)).sum((1, 2))
        dx, du = self._forward(rhs, k_all)
        out = LQRSolution(dx=dx, du=du, k=k_all, p=p_all, dV1=dV1, dV2=dV2, g0=g_next)
        if multipliers:
            self._multipliers(rhs, out, Qu_all, initial_multiplier)
        return out

    # ------------------------------------------------------------------ helpers
    def _forward(self, rhs: LQRVectors, k: Tensor):
        """The step ``(δx (B, N+1, nx), δu (B, N, nu))`` rolled out from ``x0`` with the feedforward ``k``."""
        lqr = self.lqr
        N = lqr.A.shape[1]
        x = rhs.x0
        xs, us = [x], []
        for t in range(N):
            u = _mv(self.K[:, t], x) + k[:, t]
            x = _mv(lqr.A[:, t], x) + _mv(lqr.B[:, t], u) + rhs.c[:, t]
            xs.append(x)
            us.append(u)
        return torch.stack(xs, 1), torch.stack(us, 1)

    def _multipliers(self, rhs: LQRVectors, out: LQRSolution, Qu: Tensor,
                     initial_multiplier: Optional[Tensor] = None) -> None:
        """Recover ν (forward, from the u-stationarity of each stage) and λ (backward)."""
        lqr = self.lqr
        N = lqr.A.shape[1]
        dx, du = out.dx, out.du
        nus = [None] * N
        nuN = None
        if self.fixed is not None:
            out.nu = _bound_multipliers(lqr, self.fixed, self.Quu, self.Qux, dx, du, Qu)
        if lqr.propagated:
            nus, nuN = _propagated_multipliers(self.lqr, self.stage, self.terminal, self.Quu, self.Qux, dx, du, Qu,
                                               initial_multiplier)
        if self.exact:  # ∇V_k at δx_k: one product for all stages instead of a backward sweep
            out.costate = (self.P @ dx.unsqueeze(-1)).squeeze(-1) + out.p
            return
        lam = _mv(lqr.QN, dx[:, N]) + rhs.qN
        if nuN is not None and lqr.CN is not None:
            lam = lam + _mv(_mT(lqr.CN * lqr.maskN.unsqueeze(-1)), nuN)
        lams = [None] * (N + 1)
        lams[N] = lam
        for t in range(N - 1, -1, -1):
            lam = (
                _mv(lqr.Q[:, t], dx[:, t]) + _mv(_mT(lqr.S[:, t]), du[:, t]) + rhs.q[:, t]
                + _mv(_mT(lqr.A[:, t]), lam)
            )
            if lqr.C is not None and nus[t] is not None:
                lam = lam + _mv(_mT(lqr.C[:, t] * lqr.mask[:, t].unsqueeze(-1)), nus[t])
            lams[t] = lam
        out.costate = torch.stack(lams, 1)
        if lqr.propagated and lqr.C is not None:
            out.nu = torch.stack(nus, 1)
        if lqr.CN is not None:
            out.nuN = nuN
