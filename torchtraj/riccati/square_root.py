r"""ALTRO's square-root backward pass (Howell et al. 2019 §III-A, eqs. 19-29).

Instead of the value-function Hessians ``P_k`` the recursion carries upper-triangular factors
``S_k`` with ``P_k = S_kᵀ S_k``; every sum of squares is formed by a QR factorisation of stacked rows
(``√(A+B) ← QR((√A, √B))``, §II-B), so the squared condition number of ``P`` never appears:

.. math::

    S_N &\leftarrow \mathrm{QR}\big((\sqrt{\ell_{N,xx}},\ \sqrt{I_{\mu_N}} c_{N,x})\big)            \quad (19)\\
    Z_{xx} &\leftarrow \mathrm{QR}\big((\sqrt{\ell_{xx}},\ S' A,\ \sqrt{I_\mu} c_x)\big)           \quad (20)\\
    Z_{uu} &\leftarrow \mathrm{QR}\big((\sqrt{\ell_{uu}},\ S' B,\ \sqrt{I_\mu} c_u,\ \sqrt\rho I)\big) \quad (21)\\
    K &= -Z_{uu}^{-1} Z_{uu}^{-T} Q_{ux}                                                         \quad (22)\\
    S &\leftarrow \mathrm{QR}\Big(\big(Z_{xx} + Z_{xx}^{-T} Q_{xu} K,\
          \mathrm{DD}(Z_{uu}, Z_{xx}^{-T} Q_{xu}) K\big)\Big)                                     \quad (29)

where ``DD(R, C)`` applies one rank-one Cholesky downdate per row of ``C`` (hyperbolic rotations),
giving ``√(RᵀR − CᵀC)``. The square roots of the cost Hessians come as stacked rows
(``LQR.root``/``LQR.rootN``: cost-Hessian root and ``√I_μ c_z`` from the augmented Lagrangian), or,
when absent, from a symmetric eigen-decomposition of ``[[Q, Sᵀ], [S, R]]``.

The result is a :class:`~torchtraj.riccati.RiccatiFactor` (``P = SᵀS``, Cholesky factor ``Z_uuᵀ``),
so right-hand sides are solved by the same :meth:`~torchtraj.riccati.RiccatiFactor.solve`
(eqs. 23-25). Stagewise equality constraints are not supported by this pass (ALTRO's inner iLQR has
none: they live in the augmented Lagrangian).
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .factor import RiccatiFactor
from .linalg import _mT
from .lqr import LQR
from .sanitize import _sanitize


def psd_root(H: Tensor) -> Tensor:
    """Rows ``W`` with ``WᵀW = H`` for symmetric positive semi-definite ``H (..., n, n)``."""
    w, V = torch.linalg.eigh(0.5 * (H + _mT(H)))
    return w.clamp_min(0).sqrt().unsqueeze(-1) * _mT(V)


def _qr_r(rows: Tensor) -> Tensor:
    """Upper-triangular ``R`` with ``RᵀR = rowsᵀ rows`` (the ``QR`` of §II-B).

    Householder reflections written with batched tensor operations: on a batch of the tiny matrices of a
    trajectory problem they cost a small fraction of a call of LAPACK's ``geqrf``."""
    F = rows
    r, n = F.shape[-2], F.shape[-1]
    idx = torch.arange(r, device=F.device).unsqueeze(-1)
    for j in range(min(n, r)):
        x = torch.where(idx >= j, F[..., j:j + 1], torch.zeros_like(F[..., j:j + 1]))  # (..., r, 1)
        norm = x.square().sum(-2, keepdim=True).sqrt()
        xj = F[..., j:j + 1, j:j + 1]
        alpha = -torch.where(xj >= 0, norm, -norm)
        v = x - torch.where(idx == j, alpha, torch.zeros_like(alpha))
        vv = v.square().sum(-2, keepdim=True)
        reflect = vv > 0
        w = torch.where(reflect, v / torch.where(reflect, vv, torch.ones_like(vv)).sqrt(), torch.zeros_like(v))
        F = F - 2.0 * w @ (w.transpose(-1, -2) @ F)
    upper = (torch.arange(n, device=F.device).unsqueeze(-1) <= torch.arange(n, device=F.device)).to(F.dtype)
    R = F[..., :n, :]
    if r < n:
        R = torch.cat([R, R.new_zeros(*R.shape[:-2], n - r, n)], -2)
    return R * upper


def downdate(R: Tensor, C: Tensor):
    """``DD(R, C)``: upper ``R⁺`` with ``R⁺ᵀR⁺ = RᵀR − CᵀC`` by successive rank-one downdates.

    ``R (B, n, n)`` upper triangular, ``C (B, r, n)``. Returns ``(R⁺, ok)``; ``ok (B,)`` is false where
    the difference is not positive definite.
    """
    n = R.shape[-1]
    rows = [R[..., i, :] for i in range(n)]
    ok = torch.ones(R.shape[0], dtype=torch.bool, device=R.device)
    cols = torch.arange(n, device=R.device)
    for j in range(C.shape[-2]):
        x = C[..., j, :]
        for k in range(n):
            rkk = rows[k][..., k]
            xk = x[..., k]
            d2 = rkk * rkk - xk * xk
            ok = ok & (d2 > 0)
            r = torch.sqrt(torch.where(d2 > 0, d2, torch.ones_like(d2)))
            safe = torch.where(rkk != 0, rkk, torch.ones_like(rkk))
            c, s = (r / safe).unsqueeze(-1), (xk / safe).unsqueeze(-1)
            tail = cols > k
            new_row = torch.where(tail, (rows[k] - s * x) / c, rows[k])
            new_row = torch.where(cols == k, r.unsqueeze(-1), new_row)
            x = torch.where(tail, c * x - s * new_row, torch.zeros_like(x))
            rows[k] = new_row
    return torch.stack(rows, -2), ok


def factorize_sqrt(lqr: LQR, regularization: Optional[Tensor] = None) -> RiccatiFactor:
    """Square-root backward sweep over the (unconstrained) matrices of ``lqr``; see the module docstring."""
    if lqr.constrained:
        raise ValueError("the square-root backward pass takes no stagewise equality constraints")
    lqr, finite = _sanitize(lqr)
    Bsz, N, nx, nu = lqr.B.shape[0], lqr.B.shape[1], lqr.A.shape[-1], lqr.B.shape[-1]
    dtype, device = lqr.A.dtype, lqr.A.device
    rho = lqr.A.new_zeros(Bsz) if regularization is None else regularization
    eye_u = torch.eye(nu, dtype=dtype, device=device)
    if lqr.root is not None:
        root = lqr.root
    else:
        top = torch.cat([lqr.Q, _mT(lqr.S)], -1)
        bottom = torch.cat([lqr.S, lqr.R], -1)
        root = psd_root(torch.cat([top, bottom], -2))
    rootN = lqr.rootN if lqr.rootN is not None else psd_root(lqr.QN)
    S = _qr_r(torch.cat([rootN, torch.zeros(Bsz, max(0, nx - rootN.shape[-2]), nx, dtype=dtype, device=device)], -2))
    Ps, Ks, Quus, Quxs, chols = [None] * (N + 1), [None] * N, [None] * N, [None] * N, [None] * N
    Ps[N] = _mT(S) @ S
    ok = finite
    sqrt_rho = rho.clamp_min(0).sqrt().reshape(Bsz, 1, 1) * eye_u
    for t in range(N - 1, -1, -1):
        A, Bu = lqr.A[:, t], lqr.B[:, t]
        W = root[:, t]
        Wx, Wu = W[..., :nx], W[..., nx:]
        SA, SB = S @ A, S @ Bu
        Zxx = _qr_r(torch.cat([Wx, SA], -2))  # (20)
        Zuu = _qr_r(torch.cat([Wu, SB, sqrt_rho], -2))  # (21)
        Qux = _mT(Wu) @ Wx + _mT(SB) @ SA
        diag = torch.diagonal(Zuu, dim1=-2, dim2=-1).abs()
        good = (diag > torch.finfo(dtype).eps * diag.amax(-1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)).all(-1)
        Zuu = torch.where(good.reshape(Bsz, 1, 1), Zuu, eye_u.expand_as(Zuu))
        L = _mT(Zuu)
        K = -torch.cholesky_solve(Qux, L) if nu > 0 else Qux.new_zeros(Bsz, 0, nx)  # (22)
        C = torch.linalg.solve_triangular(_mT(Zxx), _mT(Qux), upper=False)  # Z_xx^{-T} Q_xu, (27)
        D, down_ok = downdate(Zuu, C)  # (28): rows of C (nx, nu) are the downdates
        S = _qr_r(torch.cat([Zxx + C @ K, D @ K], -2))  # (29)
        ok = ok & good & down_ok & torch.isfinite(S).flatten(1).all(-1)
        Quu = _mT(Zuu) @ Zuu - sqrt_rho @ sqrt_rho
        Ps[t], Ks[t], Quus[t], Quxs[t], chols[t] = _mT(S) @ S, K, Quu, Qux, L
    return RiccatiFactor(
        lqr=lqr, K=torch.stack(Ks, 1), P=torch.stack(Ps, 1), ok=ok, Quu=torch.stack(Quus, 1),
        Qux=torch.stack(Quxs, 1), chol=torch.stack(chols, 1), free=None, stage=None, terminal=None,
    )
