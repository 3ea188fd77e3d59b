r"""Least-squares initial multipliers (Wächter & Biegler 2006 §3.6), on the Riccati core.

IPOPT starts the slacks at ``max(−g, κ_1)`` (``bound_push`` κ_1 = 10⁻², the one-sided bound ``s ≥ 0``: IPOPT's push
``min(κ_1 max(1, |s_L|), κ_2 (s_U − s_L))`` is ``κ_1`` there; :func:`~torchtraj.solvers.ipm.expansion.initial_iterate`),
their bound multipliers ``z`` at 1 (``bound_mult_init_val``), and the constraint multipliers at the least-squares
estimate, the solution of

.. math::

    \begin{bmatrix} I & J^T \\ J & 0 \end{bmatrix} \begin{bmatrix} w \\ y \end{bmatrix}
    = − \begin{bmatrix} ∇_w J − z_w \\ 0 \end{bmatrix},

over the primal variables ``(X, U, s)`` and every constraint of the barrier problem: the dynamics (costates ``λ``),
``h``, ``h_N`` (``ν``) and ``g + s = 0`` (``y``). The objective does not depend on ``s`` and ``z`` is the bound
multiplier of ``s``; eliminating ``w_s = −G w_x`` leaves the LQR problem of the Riccati core

.. math::  \min_{w_x} \tfrac12 w_x^T (I + G^T G) w_x + (∇J + G^T z)^T w_x \ \text{s.t. the linearised dynamics and
           equality rows with zero right-hand sides},

whose costates and row multipliers are ``λ`` and ``ν``, and ``y = z + G w_x``. Where the estimate's largest entry
exceeds ``λ_max`` (``constr_mult_init_max`` = 1000), or the system is not positive definite, the multipliers stay
at zero (W&B §3.6).

**Two-sided bounds.** A variable bounded on both sides, ``l ≤ v ≤ u``, is two rows here (``v − u + s_u = 0`` and
``l − v + s_l = 0``, each with its slack), but one row of the NLP that IPOPT solves (``d(w) = v`` with one slack
``l ≤ s ≤ u``, as the problem set's references pose every bound): one multiplier and one slack direction
``w_s = D w_x``, so its term in the least-squares Hessian is ``Dᵀ D``, not the two rows' ``2 Dᵀ D``. Each such row
therefore enters with its share ``ω = ½`` (:attr:`~torchtraj.core.constraints.Constraints.ineq_share`):
``I + Gᵀ Ω G`` and ``y = z + Ω G w_x``, whose force ``Dᵀ (y_u − y_l) = Dᵀ D w_x`` is that row's multiplier. The
gradient term ``Gᵀ z`` is IPOPT's (its two bound multipliers at 1 cancel, as the two rows' do). With the two rows'
estimate the first step on ``quadrotor2d`` was 30 % longer than IPOPT's at the first stages and the solve reached
another local optimum (21.59 against IPOPT's 26.64); with the shares it is IPOPT's to 1e-6
(``tests/test_ipm_scaling.py``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...kkt import newton as kkt_newton
from ...riccati import all_finite
from .compaction import pick
from .expansion import flat_abs
from .iterate import Iterate, Model
from .newton import factorize_step
from .options import IPOptions


def least_squares_multipliers(cons: Constraints, model: Model, it: Iterate, running: Tensor,
                              opts: IPOptions) -> Iterate:
    """``it`` with ``λ``, ``ν``, ``ν_N``, ``y``, ``y_N`` at the least-squares estimate (module docstring), where it is
    at most ``opts.multiplier_init_max`` and the instance is ``running (B,)``; ``model`` is its expansion with zero
    multipliers (so ``model.Lz`` is the cost gradient), ``cons`` its rows' layout (their shares, module docstring)."""
    B, N, nz = model.Lz.shape
    nx = model.LNx.shape[-1]
    knots = model.knots
    G, GN = model.Gz, model.GN
    Gt = G.transpose(-1, -2)
    share = cons.ineq_share.unsqueeze(-1)
    H = torch.eye(nz, dtype=G.dtype, device=G.device) + Gt @ (share * G)
    HN = torch.eye(nx, dtype=G.dtype, device=G.device) + GN.transpose(-1, -2) @ GN
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    lqr = kkt_newton.held_lqr(model.fz, H, HN, rows=model.Hz if me else None, rowsN=model.HN if meN else None)
    grad = model.Lz + _mv(Gt, it.z * knots)
    gradN = model.LNx + _mv(GN.transpose(-1, -2), it.zN)
    rhs = kkt_newton.newton_rhs(grad, gradN, torch.zeros_like(model.f), torch.zeros_like(it.X[:, 0]),
                                torch.zeros_like(model.h) if me else None, torch.zeros_like(model.hN) if meN else None)
    factor = factorize_step(lqr, torch.zeros_like(model.J), opts)
    sol = factor.solve(rhs, multipliers=True)
    dw = torch.cat([sol.dx[:, :-1], sol.du], -1)
    nu = sol.nu if sol.nu is not None else torch.zeros_like(it.nu)
    nuN = sol.nuN if sol.nuN is not None else torch.zeros_like(it.nuN)
    y = (it.z + share.squeeze(-1) * _mv(G, dw)) * knots
    estimate = Iterate(X=it.X, U=it.U, s=it.s, sN=it.sN, z=it.z, zN=it.zN, y=y, yN=it.zN + _mv(GN, sol.dx[:, -1]),
                       lam=sol.costate, nu=nu, nuN=nuN)
    size = flat_abs(estimate.lam, estimate.nu, estimate.nuN, estimate.y, estimate.yN).amax(-1)
    use = running & factor.ok & all_finite([sol.costate, dw]) & (size <= opts.multiplier_init_max)
    return pick(use, estimate, it)
