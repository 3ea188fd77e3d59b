r"""The lean sweeps with back-propagated rows: :mod:`~torchtraj.riccati.propagation`'s recursion in a few dozen
batched calls per stage (matrices), about fifteen (vectors) and three (multipliers).

The mathematics is that of :mod:`~torchtraj.riccati.propagation` (Horizon eILQR, Laurenzi et al. §II-B/C): at
stage k the rows ``M = [[C_k, D_k], [G_{k+1} A_k, G_{k+1} B_k]]`` are rotated by the SVD ``M_u = U Σ Vᵀ``; the
directions above the rank tolerance fix ``δu = K_c δx + k_c`` with ``K_c = −V Σ⁺ Uᵀ M_x``, the rows left act on
``δx`` and are compressed by a second SVD to ``G_k``, and the free directions ``V_f`` minimise the Q-function:
``K = K_c + V_f K_w``, ``K_w = −H_w⁻¹ V_fᵀ (Q_ux + Q_uu K_c)``, ``H_w = V_fᵀ (Q_uu + ρI) V_f + Π_fixed``.

As in :mod:`~torchtraj.riccati.sweep`, what does not depend on the recursion is done once for all stages: the
matrices that the vector sweep applies to each stage's right-hand side are formed after the matrix sweep,

.. math::

    k_c = -V Σ^+ [U^T m]_{fixed},\quad k_w = Z (Q_u + Q_{uu} k_c),\ Z = -H_w^{-1} V_f^T,\quad
    g_k = Y\,U^T m,\ Y = \mathrm{diag}(\text{kept}) U_2^T \mathrm{diag}(\text{rest}),

with ``m = [e_k; G_{k+1} c_k + g_{k+1}]``, so that a stage of the vector sweep is a handful of products.
The multipliers' forward sweep reads the u-stationarity residuals of all stages, computed at once.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import addmatmul, matmul
from .linalg import _cholesky, _cholesky_solve, _mT, _sym, _time_major
from .lqr import LQR, LQRVectors
from .propagation import _Constraint, _terminal_rhs
from .sweep import stage_terms


def factorize_rows(W: Tensor, Hs: Tensor, QN: Tensor, rows: Tensor, G_last: Tensor, rho: Tensor, tol: float):
    """The matrix sweep with back-propagated rows.

    ``W (N, B, nx, nx+nu)``, ``Hs (N, B, nx+nu, nx+nu)`` time-major stage blocks; ``rows (B, N, m, nx+nu)`` the
    masked stage rows ``[C_k D_k]``; ``G_last (B, nx, nx)`` the compressed terminal rows; ``ρ (B,)``. Returns
    ``(P, K, Quu, Qux, ok, stage, sweep)``: ``P (B, N+1, nx, nx)`` … ``Qux`` batch-first, ``ok (B,)``, ``stage`` the
    per-stage :class:`~torchtraj.riccati.propagation._Constraint` records and ``sweep`` the stacked matrices the
    vector sweeps read (:func:`solve_rows`, :func:`multipliers_rows`)."""
    N, Bsz, nx, n = W.shape
    nu, m = n - nx, rows.shape[-2]
    mt = m + nx
    fix = min(mt, nu)  # directions the rows can fix
    dtype, device = W.dtype, W.device
    tiny = torch.finfo(dtype).tiny
    eye_x = torch.eye(nx, dtype=dtype, device=device).expand(Bsz, nx, nx)
    rho = rho.reshape(Bsz, 1, 1) * torch.eye(nu, dtype=dtype, device=device)
    Ws, WTs, Hss, stage_rows = W.unbind(0), _mT(W).unbind(0), Hs.unbind(0), rows.unbind(1)
    ones_rest = W.new_ones(Bsz, mt - nu) if mt > nu else None
    zero_s = W.new_zeros(Bsz, nu - mt) if mt < nu else None
    one, zero = W.new_ones(()), W.new_zeros(())
    P, G = QN, G_last
    out = {name: [None] * N for name in ("P", "K", "Quu", "Qux", "ok", "U", "VS", "rest", "U2", "kept", "G", "Vf", "L",
                                         "inv_s")}
    for t in range(N - 1, -1, -1):
        H = addmatmul(Hss[t], WTs[t], matmul(P, Ws[t]))
        Qux, Quu = H[:, nx:].split([nx, nu], -1)
        M = matmul(G, Ws[t])
        if m:
            M = torch.cat([stage_rows[t], M], -2)
        Mx, Mu = M.split([nx, nu], -1)
        U, s, Vh = torch.linalg.svd(Mu)
        threshold = torch.linalg.vector_norm(M, float("inf"), dim=(-2, -1)).mul(tol).clamp_min(tol * tiny)
        threshold = threshold.unsqueeze(-1)
        if zero_s is not None:
            s = torch.cat([s, zero_s], -1)
        fixed = s > threshold
        free = (s <= threshold).to(dtype)
        inv_s = torch.where(fixed, s.reciprocal(), zero)
        V = _mT(Vh)
        VS = V * inv_s.unsqueeze(-2)  # V Σ⁺
        T = matmul(_mT(U), Mx)
        Kc = matmul(VS[..., :fix], T[:, :fix]).neg()
        rest = torch.cat([free, ones_rest], -1) if ones_rest is not None else free[:, :mt]
        U2, s2, V2h = torch.linalg.svd(T * rest.unsqueeze(-1))
        kept = (s2 > threshold).to(dtype)
        G = (s2 * kept).unsqueeze(-1) * V2h
        Vf = V * free.unsqueeze(-2)
        VfT = _mT(Vf)
        Hw = addmatmul(torch.diag_embed(1.0 - free), VfT, matmul(Quu + rho, Vf))
        rhs = matmul(VfT, addmatmul(Qux, Quu, Kc))
        if nu == 1:
            ok = Hw > 0
            L = torch.where(ok, Hw, one)
            K = addmatmul(Kc, Vf, rhs / L.neg())
        else:
            L, info = _cholesky(Hw)
            ok = info == 0
            K = addmatmul(Kc, Vf, _cholesky_solve(rhs, L).neg())
        E = torch.cat([eye_x, K], -2)
        P = _sym(matmul(_mT(E), matmul(H, E)))
        for name, value in (("P", P), ("K", K), ("Quu", Quu), ("Qux", Qux), ("ok", ok), ("U", U), ("VS", VS),
                            ("rest", rest), ("U2", U2[..., :nx]), ("kept", kept), ("G", G), ("Vf", Vf), ("L", L),
                            ("inv_s", inv_s)):
            out[name][t] = value
    stage = [_Constraint(U=out["U"][t], inv_s=out["inv_s"][t], V=None, rest=out["rest"][t], U2=out["U2"][t],
                         gmask=out["kept"][t], G=out["G"][t]) for t in range(N)]
    st = {name: _time_major(values) for name, values in out.items() if name not in ("P", "ok")}
    # Z = −H_w⁻¹ V_fᵀ; a single control's factor is the root of H_w (kept as it is in the loop)
    L = st["L"].sqrt() if nu == 1 else st["L"]
    Z = _mT(st["Vf"]) / st["L"].neg() if nu == 1 else -_cholesky_solve(_mT(st["Vf"]), L)
    sweep = {
        "UT": _mT(st["U"]),
        "U": st["U"],
        "negVS": -st["VS"][..., :fix],
        "VS": st["VS"],
        "Z": Z,
        "Vf": st["Vf"],
        "Y": st["kept"].unsqueeze(-1) * _mT(st["U2"]) * st["rest"].unsqueeze(-2),
        "U2kept": st["U2"] * st["kept"].unsqueeze(-2),
        "G": st["G"],
        "fix": fix,
    }
    P_all = _time_major(out["P"] + [QN])
    return (P_all, st["K"], st["Quu"], st["Qux"], L, torch.stack(out["ok"], 1).all(1).reshape(Bsz), stage, sweep)


def solve_rows(lqr: LQR, sweep: dict, terminal: _Constraint, W: Tensor, P: Tensor, K: Tensor, Quu: Tensor,
               Qux: Tensor, rhs: LQRVectors):
    """The vector sweep with back-propagated rows: ``(k (B, N, nu), p (B, N+1, nx), Q_u (B, N, nu), g_0 (B, nx))``,
    ``g_0`` the right-hand side of the rows left at the initial state.

    ``sweep`` and ``terminal`` from :func:`factorize_rows` and the terminal rows' compression, ``W``, ``P``,
    ``K``, ``Quu``, ``Qux`` the factorisation's (batch-first), ``rhs`` the right-hand side."""
    Bsz, N, nx = P.shape[0], K.shape[1], P.shape[-1]
    m = sweep["U"].shape[-1] - nx
    fix = sweep["fix"]
    WTs, Ps, ET, Ms, qz, cs = stage_terms(W, P, K, Quu, Qux, rhs.q, rhs.r, rhs.c)
    Quus = Quu.unbind(1)
    G_after = torch.cat([sweep["G"][:, 1:], terminal.G.unsqueeze(1)], 1).unbind(1)
    UT, negVS, Z, Vf, Y = (sweep[name].unbind(1) for name in ("UT", "negVS", "Z", "Vf", "Y"))
    if m:
        e = rhs.e * lqr.mask if rhs.e is not None else rhs.q.new_zeros(Bsz, N, m)
        es = e.unsqueeze(-1).unbind(1)
    g = _terminal_rhs(terminal, lqr, rhs).unsqueeze(-1)
    p = rhs.qN.unsqueeze(-1)
    ps, ks, Qus = [None] * (N + 1), [None] * N, [None] * N
    ps[N] = p
    for t in range(N - 1, -1, -1):
        Qz = addmatmul(qz[t], WTs[t], addmatmul(p, Ps[t + 1], cs[t]))
        Qu = Qz[:, nx:]
        rows = addmatmul(g, G_after[t], cs[t])
        if m:
            rows = torch.cat([es[t], rows], -2)
        rotated = matmul(UT[t], rows)
        kc = matmul(negVS[t], rotated[:, :fix])
        k = addmatmul(kc, Vf[t], matmul(Z[t], addmatmul(Qu, Quus[t], kc)))
        g = matmul(Y[t], rotated)
        p = addmatmul(matmul(ET[t], Qz), Ms[t], k)
        ps[t], ks[t], Qus[t] = p, k, Qu
    return (torch.stack(ks, 1).squeeze(-1), torch.stack(ps, 1).squeeze(-1), torch.stack(Qus, 1).squeeze(-1),
            g.squeeze(-1))


def multipliers_rows(lqr: LQR, sweep: dict, terminal: _Constraint, Quu: Tensor, Qux: Tensor, dx: Tensor,
                     du: Tensor, Qu: Tensor, initial_multiplier: Optional[Tensor] = None):
    """The forward multiplier sweep: the stage rows' ``ν (B, N, m)`` and the terminal rows' ``ν_N (B, mN)``.

    On the fixing directions the rotated rows' multipliers are ``−Σ⁺ Vᵀ`` of the stage's u-stationarity residual
    (all stages at once), on the others the multipliers ``η`` of the rows handed on (module docstring of
    :mod:`~torchtraj.riccati.propagation`). ``initial_multiplier (B, nx)``: the multipliers ``η_0`` of the rows
    ``G_0`` (default zero: a fixed initial state absorbs them)."""
    Bsz, N, nx = dx.shape[0], du.shape[1], dx.shape[-1]
    mt, fix = sweep["U"].shape[-1], sweep["fix"]
    m = mt - nx
    residual = (matmul(Quu, du.unsqueeze(-1)) + matmul(Qux, dx[:, :-1].unsqueeze(-1))).squeeze(-1) + Qu
    fixing = -matmul(_mT(sweep["VS"]), residual.unsqueeze(-1))[:, :, :fix]
    if mt > fix:
        fixing = torch.cat([fixing, fixing.new_zeros(Bsz, N, mt - fix, 1)], -2)
    fixings, Us, U2s = fixing.unbind(1), sweep["U"].unbind(1), sweep["U2kept"].unbind(1)
    # multiplier of G_0 rows: absorbed by the initial condition unless the initial state is optimised
    eta = dx.new_zeros(Bsz, nx, 1) if initial_multiplier is None else initial_multiplier.unsqueeze(-1)
    rotated = [None] * N
    for t in range(N):
        rotated[t] = matmul(Us[t], addmatmul(fixings[t], U2s[t], eta))
        eta = rotated[t][:, m:]
    nus = torch.stack(rotated, 1)[:, :, :m, 0]
    nus = nus * lqr.mask if lqr.mask is not None else nus
    nuN = matmul(terminal.U2 * terminal.gmask.unsqueeze(-2), eta).squeeze(-1)
    return nus, nuN * lqr.maskN if lqr.maskN is not None else nuN
