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
from .bounds import _bound_multipliers, _held_values
from .linalg import _mT
from .lqr import LQR, LQRSolution, LQRVectors
from .propagation import _Constraint
from .rows import multipliers_rows, solve_rows
from .sweep import costate_stages, expected_change, forward_stages, solve_stages


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
    #: ``(B, N, nx, nx+nu)``: the stage blocks ``[A_k B_k]`` of ``lqr`` (``None``: stacked when solving)
    W: Optional[Tensor] = None
    #: the stacked matrices of the sweep with back-propagated rows (:func:`~torchtraj.riccati.rows.factorize_rows`)
    rows: Optional[dict] = None

    def solve(self, rhs: LQRVectors, multipliers: bool = False, forward: bool = True,
              initial_multiplier: Optional[Tensor] = None) -> LQRSolution:
        """Solve the LQR problem for the right-hand side ``rhs`` (one backward and one forward sweep).

        ``forward=False`` skips the forward sweep (``dx``, ``du`` are ``None``): a caller that rolls out the
        nonlinear dynamics with the gains and feedforward, as iLQR's line search, has no use for it.
        ``initial_multiplier``: ``η_0 (B, nx)``, the multipliers of the rows ``G_0 δx_0 + g_0 = 0`` left at the
        initial state (:attr:`LQRSolution.g0`). With ``δx_0`` fixed any value solves the KKT conditions and the
        default is zero; where ``δx_0`` is optimised (Horizon eILQR §II-D) it is the one its stage-0 system gives."""
        lqr = self.lqr
        W = self.W if self.W is not None else torch.cat([lqr.A, lqr.B], -1)
        g0 = None
        if lqr.propagated:
            k, p, Qu, g0 = solve_rows(lqr, self.rows, self.terminal, W, self.P, self.K, self.Quu, self.Qux, rhs)
        else:
            held = _held_values(self.fixed, lqr, rhs)
            k, p, Qu = solve_stages(W, self.P, self.K, self.Quu, self.Qux, self.chol, rhs.q, rhs.r, rhs.qN, rhs.c,
                                    self.fixed, held)
        dV1, dV2 = expected_change(k, Qu, self.Quu)
        dx, du = forward_stages(W, self.K, k, rhs.c, rhs.x0) if forward or multipliers else (None, None)
        out = LQRSolution(dx=dx, du=du, k=k, p=p, dV1=dV1, dV2=dV2, g0=g0)
        if multipliers:
            self._multipliers(rhs, out, Qu, initial_multiplier)
        return out

    # ------------------------------------------------------------------ helpers
    def _multipliers(self, rhs: LQRVectors, out: LQRSolution, Qu: Tensor,
                     initial_multiplier: Optional[Tensor] = None) -> None:
        """Recover ν (forward, from the u-stationarity of each stage) and λ (backward)."""
        lqr = self.lqr
        N = lqr.A.shape[1]
        dx, du = out.dx, out.du
        nus = nuN = None
        if self.fixed is not None:
            out.nu = _bound_multipliers(lqr, self.fixed, self.Quu, self.Qux, dx, du, Qu)
        if lqr.propagated:
            nus, nuN = multipliers_rows(lqr, self.rows, self.terminal, self.Quu, self.Qux, dx, du, Qu,
                                        initial_multiplier)
        if self.exact:  # ∇V_k at δx_k: one product for all stages instead of a backward sweep
            out.costate = (self.P @ dx.unsqueeze(-1)).squeeze(-1) + out.p
            return
        lam = _mv(lqr.QN, dx[:, N]) + rhs.qN
        if nuN is not None and lqr.CN is not None:
            lam = lam + _mv(_mT(lqr.CN * lqr.maskN.unsqueeze(-1)), nuN)
        # the x-stationarity's terms that do not depend on the recursion, for all stages at once
        local = _mv(lqr.Q, dx[:, :-1]) + _mv(_mT(lqr.S), du) + rhs.q
        if lqr.C is not None and lqr.propagated:
            local = local + _mv(_mT(lqr.C * lqr.mask.unsqueeze(-1)), nus)
        out.costate = costate_stages(lqr.A, local, lam)
        if lqr.propagated and lqr.C is not None:
            out.nu = nus
        if lqr.CN is not None:
            out.nuN = nuN
