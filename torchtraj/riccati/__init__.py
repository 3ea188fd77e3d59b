r"""The batched Riccati (LQR) core that every solver and the implicit backward pass share.

It solves, for a batch of B instances at once, the time-varying LQR problem

.. math::

    \min_{\delta x, \delta u}\; \sum_{k=0}^{N-1} \tfrac12 \delta x_k^T Q_k \delta x_k
        + \delta u_k^T S_k \delta x_k + \tfrac12 \delta u_k^T R_k \delta u_k
        + q_k^T \delta x_k + r_k^T \delta u_k
        \;+\; \tfrac12 \delta x_N^T Q_N \delta x_N + q_N^T \delta x_N

    \text{s.t.}\quad \delta x_{k+1} = A_k \delta x_k + B_k \delta u_k + c_k,
    \quad \delta x_0 = \bar x_0,
    \quad C_k \delta x_k + D_k \delta u_k + e_k = 0,
    \quad C_N \delta x_N + e_N = 0,

with cross terms ``S``, affine dynamics terms ``c`` (multiple-shooting defects) and stagewise
equality constraints whose rows may be switched off per instance by a mask.

Equality constraints are handled by the generalised Riccati recursion with constraint
back-propagation (Horizon eILQR, papers/horizon-eilqr.md §II-B/C; FATROP, papers/fatrop.md,
its reference [30]). At stage k the stage rows and the rows propagated from stage k+1,

.. math::  M_x \delta x + M_u \delta u + m = 0,\quad
           M = \begin{bmatrix} C_k & D_k \\ G_{k+1} A_k & G_{k+1} B_k \end{bmatrix},

are rotated by the SVD ``M_u = U \Sigma V^T``. Directions with a singular value above a relative
tolerance fix the matching components of ``δu``; the remaining rows involve ``δx`` only and are
compressed (a second SVD) into at most ``nx`` rows ``G_k δx + g_k = 0`` passed to stage k-1.
The free control directions ``V_f`` minimise the stage's Q-function:

.. math::  \delta u = K \delta x + k,\quad K = K_c + V_f K_w,\quad
           K_w = -(V_f^T (Q_{uu} + \rho I) V_f + \Pi_{fixed})^{-1} V_f^T (Q_{ux} + Q_{uu} K_c).

The value function ``V_k(δx) = ½ δxᵀ P_k δx + p_kᵀ δx`` follows by substitution
(ALTRO eqs. 14-15), and the costate obeys ``λ_k = P_k δx_k + p_k + G_kᵀ η_k`` (Horizon eq. 5a).

The recursion is split into :func:`factorize` (matrices only) and
:meth:`RiccatiFactor.solve` (right-hand sides only), so a new right-hand side — the adjoint
system of implicit differentiation, a second-order correction — costs one cheap sweep.
Multipliers (costates ``λ``, constraint multipliers ``ν``) are recovered by a forward sweep.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import matmul as _mm
from ..core.compiled import matvec as _mv


def _mT(a: Tensor) -> Tensor:
    return a.transpose(-1, -2)


def _sym(a: Tensor) -> Tensor:
    return 0.5 * (a + _mT(a))


def default_rank_tolerance(dtype: torch.dtype) -> float:
    """Relative singular-value threshold that separates satisfiable from back-propagated rows."""
    return float(torch.finfo(dtype).eps) ** 0.75


@dataclass
class LQR:
    """Matrices of a batched LQR problem (the right-hand sides live in :class:`LQRVectors`).

    Shapes: ``A (B, N, nx, nx)``, ``B (B, N, nx, nu)``, ``Q (B, N, nx, nx)``, ``R (B, N, nu, nu)``,
    ``S (B, N, nu, nx)``, ``QN (B, nx, nx)``; optional equality constraints ``C (B, N, m, nx)``,
    ``D (B, N, m, nu)`` with row mask ``mask (B, N, m)``, and ``CN (B, mN, nx)`` with ``maskN (B, mN)``.
    The square-root pass (:mod:`torchtraj.riccati.square_root`) may be given square roots of the cost
    Hessians: rows ``root (B, N, r, nx+nu)`` with ``[[Q, Sᵀ], [S, R]] = rootᵀ root`` and
    ``rootN (B, rN, nx)`` with ``QN = rootNᵀ rootN``.

    ``W (B, N, nx, nx+nu)`` and ``H (B, N, nx+nu, nx+nu)``, when given (:meth:`from_blocks`), are the stage blocks
    stacked over ``z = (δx, δu)``, ``W = [A B]`` and ``H = [[Q, Sᵀ], [S, R]]``, of which ``A`` … ``S`` are views: the
    sweep then copies two blocks instead of five strided ones. A replaced ``A`` … ``S`` (``dataclasses.replace``) no
    longer is such a view, and the stacked blocks are dropped.

    ``bounds (m, nu)`` declares the stage rows simple bounds: ``C = 0`` and ``D = bounds``, a signed selection (each
    row ``±1`` on one control), without terminal rows. An active row then holds its control at ``δu_i = ∓e``, and the
    recursion fixes those controls instead of back-propagating rows (no SVD): where ``f`` marks the free controls,
    ``K = −(F Q_uu F + I − F)⁻¹ F Q_ux`` with ``F = diag(f)``, and the row's multiplier is the stationarity residual
    of its control, ``ν = −bounds_i (Q_uu δu + Q_ux δx + Q_u)``. Two active rows on one control depend on each other.
    """

    A: Tensor
    B: Tensor
    Q: Tensor
    R: Tensor
    S: Tensor
    QN: Tensor
    C: Optional[Tensor] = None
    D: Optional[Tensor] = None
    mask: Optional[Tensor] = None
    CN: Optional[Tensor] = None
    maskN: Optional[Tensor] = None
    root: Optional[Tensor] = None
    rootN: Optional[Tensor] = None
    W: Optional[Tensor] = None
    H: Optional[Tensor] = None
    bounds: Optional[Tensor] = None

    def __post_init__(self):
        if self.W is not None and not _views_of_blocks(self):
            self.W = self.H = None

    @classmethod
    def from_blocks(cls, W: Tensor, H: Tensor, QN: Tensor, **constraints) -> "LQR":
        """The LQR whose stage blocks are ``W = [A B]`` and ``H = [[Q, Sᵀ], [S, R]]`` (batch-first)."""
        nx = W.shape[-2]
        return cls(A=W[..., :nx], B=W[..., nx:], Q=H[..., :nx, :nx], R=H[..., nx:, nx:], S=H[..., nx:, :nx], QN=QN,
                   W=W, H=H, **constraints)

    @property
    def constrained(self) -> bool:
        return self.C is not None or self.CN is not None

    @property
    def propagated(self) -> bool:
        """Whether the rows take the constraint back-propagation (rows that are not declared ``bounds``)."""
        return self.constrained and self.bounds is None


def _views_of_blocks(lqr: LQR) -> bool:
    """Whether ``A`` … ``S`` of ``lqr`` are the blocks of its stacked ``W`` and ``H`` (:meth:`LQR.from_blocks`)."""
    W, H, nx = lqr.W, lqr.H, lqr.A.shape[-1]
    if H is None or W.shape[-2] != nx or W.shape[:2] != H.shape[:2]:
        return False
    views = ((lqr.A, W[..., :nx]), (lqr.B, W[..., nx:]), (lqr.Q, H[..., :nx, :nx]), (lqr.R, H[..., nx:, nx:]),
             (lqr.S, H[..., nx:, :nx]))
    return all(a.data_ptr() == b.data_ptr() and a.stride() == b.stride() and a.shape == b.shape for a, b in views)


@dataclass
class LQRVectors:
    """Right-hand sides: ``q (B, N, nx)``, ``r (B, N, nu)``, ``qN (B, nx)``, ``c (B, N, nx)``,
    ``x0 (B, nx)``, and for constrained problems ``e (B, N, m)``, ``eN (B, mN)``."""

    q: Tensor
    r: Tensor
    qN: Tensor
    c: Tensor
    x0: Tensor
    e: Optional[Tensor] = None
    eN: Optional[Tensor] = None


@dataclass
class LQRSolution:
    """Solution of one right-hand side.

    ``dx (B, N+1, nx)``, ``du (B, N, nu)``, feedforward ``k (B, N, nu)``, value-function gradients
    ``p (B, N+1, nx)``, expected change of the quadratic model along the step,
    ``dV = (dV1, dV2)`` with ``ΔV(α) = α dV1 + α² dV2`` (ALTRO eq. 16, zero defects), and — when
    asked for — costates ``costate (B, N+1, nx)`` (``costate[:, 0]`` is the multiplier of the
    initial condition), stage multipliers ``nu (B, N, m)`` and terminal multipliers ``nuN (B, mN)``.
    """

    dx: Tensor
    du: Tensor
    k: Tensor
    p: Tensor
    dV1: Tensor
    dV2: Tensor
    costate: Optional[Tensor] = None
    nu: Optional[Tensor] = None
    nuN: Optional[Tensor] = None


@dataclass
class _Constraint:
    """Per-stage data of the constraint back-propagation (all batched over B)."""

    U: Tensor  # (B, mt, mt) left singular vectors of M_u
    inv_s: Tensor  # (B, nu) 1/σ on fixed directions, 0 elsewhere
    V: Tensor  # (B, nu, nu) right singular vectors of M_u
    rest: Tensor  # (B, mt) rows left for earlier stages
    U2: Tensor  # (B, mt, nx) left singular vectors of the propagated rows (padded)
    gmask: Tensor  # (B, nx) propagated rows that are kept
    G: Tensor  # (B, nx, nx) propagated constraint matrix on δx_k


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

    def solve(self, rhs: LQRVectors, multipliers: bool = False) -> LQRSolution:
        """Solve the LQR problem for the right-hand side ``rhs`` (one backward and one forward sweep)."""
        lqr = self.lqr
        Bsz, N, nu = lqr.B.shape[0], lqr.B.shape[1], lqr.B.shape[-1]
        constrained = lqr.propagated
        p_next = rhs.qN
        g_next = None
        ks, ps = [None] * N, [None] * (N + 1)
        Qus, Quuks = [None] * N, [None] * N
        ps[N] = p_next
        if constrained:
            g_next = self._terminal_rhs(rhs)
        held = self._held(rhs)
        for t in range(N - 1, -1, -1):
            A, Bu, P_next = lqr.A[:, t], lqr.B[:, t], self.P[:, t + 1]
            c = rhs.c[:, t]
            v = _mv(P_next, c) + p_next
            Qx = rhs.q[:, t] + _mv(_mT(A), v)
            Qu = rhs.r[:, t] + _mv(_mT(Bu), v)
            Quu, Qux, K = self.Quu[:, t], self.Qux[:, t], self.K[:, t]
            if constrained:
                con = self.stage[t]
                e = rhs.e[:, t] * lqr.mask[:, t] if rhs.e is not None else Qu.new_zeros(Bsz, 0)
                m0 = torch.cat([e, _mv(self.stage[t + 1].G if t + 1 < N else self.terminal.G, c) + g_next], -1)
                t0 = _mv(_mT(con.U), m0)
                top = _pad_rows(t0.unsqueeze(-1), nu).squeeze(-1)
                kc = -_mv(con.V, con.inv_s * top)
                Vf = self.free[:, t]
                grad = _mv(Quu, kc) + Qu
                kw = -_cholesky_solve(_mv(_mT(Vf), grad).unsqueeze(-1), self.chol[:, t]).squeeze(-1)
                k = kc + _mv(Vf, kw)
                g_next = _mv(_mT(con.U2), con.rest * t0) * con.gmask
            elif held is not None:  # the held controls at their values, the free ones minimise given them
                free, value = 1.0 - self.fixed[:, t], held[:, t]
                grad = (Qu + _mv(Quu, value)) * free
                k = value - _cholesky_solve(grad.unsqueeze(-1), self.chol[:, t]).squeeze(-1)
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
        out = LQRSolution(dx=dx, du=du, k=k_all, p=p_all, dV1=dV1, dV2=dV2)
        if multipliers:
            self._multipliers(rhs, out, Qu_all)
        return out

    # ------------------------------------------------------------------ helpers
    def _held(self, rhs: LQRVectors) -> Optional[Tensor]:
        """``(B, N, nu)``: the values ``δu_i = ∓e`` at which the active ``bounds`` rows hold their controls."""
        if self.fixed is None:
            return None
        if rhs.e is None:
            return torch.zeros_like(self.fixed)
        return -(rhs.e * self.lqr.mask) @ self.lqr.bounds.to(rhs.e.dtype)

    def _terminal_rhs(self, rhs: LQRVectors) -> Tensor:
        con = self.terminal
        eN = rhs.eN * self.lqr.maskN if rhs.eN is not None else rhs.qN.new_zeros(rhs.qN.shape[0], 0)
        return _mv(_mT(con.U2), eN) * con.gmask

    def _forward(self, rhs: LQRVectors, k: Tensor):
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

    def _multipliers(self, rhs: LQRVectors, out: LQRSolution, Qu: Tensor) -> None:
        """Recover ν (forward, from the u-stationarity of each stage) and λ (backward)."""
        lqr = self.lqr
        Bsz, N, nx = lqr.A.shape[0], lqr.A.shape[1], lqr.A.shape[-1]
        dx, du = out.dx, out.du
        nus = [None] * N
        nuN = None
        if self.fixed is not None:  # a held control's stationarity residual, on the rows that hold it
            grad_u = (self.Quu @ du.unsqueeze(-1) + self.Qux @ dx[:, :-1].unsqueeze(-1)).squeeze(-1) \
                + Qu
            out.nu = ((-grad_u * self.fixed) @ lqr.bounds.T.to(grad_u.dtype)) * lqr.mask
        if lqr.propagated:
            m = lqr.C.shape[2] if lqr.C is not None else 0
            eta = dx.new_zeros(Bsz, nx)  # multiplier of G_0 rows: absorbed by the initial condition
            for t in range(N):
                con = self.stage[t]
                grad_u = _mv(self.Quu[:, t], du[:, t]) + _mv(self.Qux[:, t], dx[:, t]) + Qu[:, t]
                fixed = -con.inv_s * _mv(_mT(con.V), grad_u)  # (B, nu)
                mt = con.U.shape[-1]
                nu_hat = _pad_rows(fixed.unsqueeze(-1), mt).squeeze(-1) + _mv(con.U2, eta * con.gmask)
                nu_tilde = _mv(con.U, nu_hat)
                nus[t] = nu_tilde[:, :m] * lqr.mask[:, t] if m else nu_tilde[:, :0]
                eta = nu_tilde[:, m:]
            con = self.terminal
            nuN = _mv(con.U2, eta * con.gmask)
            nuN = nuN * lqr.maskN if lqr.maskN is not None else nuN
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


# Cholesky factorisations and solves of the small (nu × nu) Hessians. Eager, LAPACK's batched routines
# are the cheapest for nu ≥ 2, measured on CPU at B = 256, nu = 4: cholesky_ex 27 µs against 180 µs for
# the elementwise formulas below, cholesky_solve of one vector 38 µs against 142 µs. torch.compile fuses
# the elementwise formulas into its loops instead (up to _SMALL), and a 1 × 1 factor is a square root.
_SMALL = 4


def _elementwise(n: int) -> bool:
    """Whether the ``n × n`` factorisation and solves use the elementwise formulas: while traced, and while a
    CUDA graph is captured (MAGMA's batched routines, behind some of the LAPACK-like calls, cannot be)."""
    if n > _SMALL:
        return False
    return torch.compiler.is_compiling() or (torch.cuda.is_available() and torch.cuda.is_current_stream_capturing())


def _cholesky(H: Tensor):
    """Lower Cholesky factor of ``H (..., n, n)`` and ``info (...)`` (0 where positive definite).

    Where ``H`` is not positive definite the returned factor is the identity."""
    n = H.shape[-1]
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    if n == 1:
        positive = H > 0
        return torch.where(positive, H, eye).sqrt(), (~positive[..., 0, 0]).to(torch.int32)
    if not _elementwise(n):
        L, info = torch.linalg.cholesky_ex(H)
        return torch.where((info == 0).unsqueeze(-1).unsqueeze(-1), L, eye), info
    cols = [[None] * n for _ in range(n)]
    ok = torch.ones(H.shape[:-2], dtype=torch.bool, device=H.device)
    for j in range(n):
        pivot = H[..., j, j]
        for k in range(j):
            pivot = pivot - cols[j][k] * cols[j][k]
        ok = ok & (pivot > 0)
        d = torch.sqrt(torch.where(pivot > 0, pivot, torch.ones_like(pivot)))
        cols[j][j] = d
        for i in range(j + 1, n):
            v = H[..., i, j]
            for k in range(j):
                v = v - cols[i][k] * cols[j][k]
            cols[i][j] = v / d
    zero = torch.zeros_like(H[..., 0, 0])
    L = torch.stack([torch.stack([cols[i][j] if j <= i else zero for j in range(n)], -1) for i in range(n)], -2)
    L = torch.where(ok.unsqueeze(-1).unsqueeze(-1), L, eye)
    return L, (~ok).to(torch.int32)


def _cholesky_solve(b: Tensor, L: Tensor) -> Tensor:
    """Solve ``L Lᵀ x = b`` for ``b (..., n, m)`` with the factor of :func:`_cholesky`."""
    n = L.shape[-1]
    if n == 1:
        return b / L / L
    if not _elementwise(n):
        return torch.cholesky_solve(b, L)
    y = [None] * n
    for i in range(n):
        v = b[..., i, :]
        for k in range(i):
            v = v - L[..., i, k].unsqueeze(-1) * y[k]
        y[i] = v / L[..., i, i].unsqueeze(-1)
    x = [None] * n
    for i in range(n - 1, -1, -1):
        v = y[i]
        for k in range(i + 1, n):
            v = v - L[..., k, i].unsqueeze(-1) * x[k]
        x[i] = v / L[..., i, i].unsqueeze(-1)
    return torch.stack(x, -2)


def _factored_solve(H: Tensor, L: Tensor, info: Tensor, b: Tensor) -> Tensor:
    """``_cholesky_solve(b, L)`` for the factor ``L, info`` of ``H`` by :func:`_cholesky`.

    Eager, an LU solve of ``H`` (the identity where ``info > 0``, as ``L``) is the cheaper LAPACK call for
    a matrix right-hand side (B = 256, 4 × 4 by 4 × 8: 53 µs, against 121 µs for torch.cholesky_solve)."""
    n = H.shape[-1]
    if n == 1 or _elementwise(n):
        return _cholesky_solve(b, L)
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    return torch.linalg.solve_ex(torch.where((info == 0).unsqueeze(-1).unsqueeze(-1), H, eye), b)[0]


def _mm_stacked(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for the blocks stacked over ``(δx, δu)``: as :func:`torchtraj.core.compiled.matmul`, but written
    as a broadcast sum when traced whatever the contraction ``nx + nu``, so that the congruence
    ``Eᵀ H E`` of :func:`factorize` stays in inductor's loops as its unstacked products did."""
    if torch.compiler.is_compiling():
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return _mm(a, b)


def _pad_rows(a: Tensor, rows: int) -> Tensor:
    """Truncate or zero-pad the second-to-last dimension of ``a`` to ``rows``."""
    n = a.shape[-2]
    if n >= rows:
        return a[..., :rows, :]
    pad = a.new_zeros(*a.shape[:-2], rows - n, a.shape[-1])
    return torch.cat([a, pad], -2)


def _pad_cols(a: Tensor, cols: int) -> Tensor:
    return _mT(_pad_rows(_mT(a), cols))


def _compress(R: Tensor, nx: int, tol: float, scale: Tensor):
    """Rows ``R (B, mt, nx)`` acting on δx compressed to ``G (B, nx, nx)`` by an SVD.

    Rows with a singular value below ``tol * scale`` (``scale (B,)``: the magnitude of the
    constraint rows before elimination) are round-off and dropped.
    Returns ``(U2 (B, mt, nx), gmask (B, nx), G)`` with ``G = diag(σ) V2ᵀ`` on kept rows."""
    if R.shape[-2] == 0:  # no rows: nothing to propagate (a shape, not a value, decides)
        zeros = R.new_zeros(R.shape[0], nx)
        return R.new_zeros(R.shape[0], 0, nx), zeros, R.new_zeros(R.shape[0], nx, nx)
    U2, s2, V2h = torch.linalg.svd(R, full_matrices=True)
    r = s2.shape[-1]
    s_pad = _pad_rows(s2.unsqueeze(-1), nx).squeeze(-1)
    gmask = (s_pad > tol * scale.unsqueeze(-1)).to(R.dtype)
    G = _pad_rows(s2.unsqueeze(-1) * V2h[..., :r, :], nx) * gmask.unsqueeze(-1)
    return _pad_cols(U2, nx), gmask, G


def all_finite(values: list) -> Tensor:
    """``(B,)``: whether every entry of an instance is finite in each of ``values`` (batch-first tensors or None)."""
    finite = None
    for value in values:
        if value is not None and value[:1].numel():
            # amax and amin propagate NaN: a fifth of the cost of isfinite(...).all() (0.28 ms against
            # 1.5 ms for an A of B = 256, N = 30, nx = 8); reduced in place, as a reshape copies strided blocks
            dims = tuple(range(1, value.dim()))
            ok = (value.amax(dims) < float("inf")) & (value.amin(dims) > -float("inf"))
            finite = ok if finite is None else finite & ok
    return finite


def _clean(value: Optional[Tensor], finite: Tensor, eye: bool = False) -> Optional[Tensor]:
    """``value`` where ``finite``, else zero (``eye``: the identity)."""
    if value is None:
        return None
    keep = finite.reshape(-1, *([1] * (value.dim() - 1)))
    if eye:
        return torch.where(keep, value, torch.eye(value.shape[-1], dtype=value.dtype, device=value.device))
    return torch.where(keep, value, value.new_zeros(()))  # not zeros_like: seven times dearer


_OTHER_FIELDS = ("QN", "C", "D", "mask", "CN", "maskN", "root", "rootN")


def _sanitize(lqr: LQR):
    """Replace the matrices of instances with non-finite entries by a benign problem.

    LAPACK's SVD may fail for a whole batch when one instance holds a NaN; swapping such an
    instance for ``A = 0, B = 0, Q = R = I`` keeps the others' answers unchanged, and the
    returned mask ``finite (B,)`` marks it as failed."""
    finite = all_finite([lqr.A, lqr.B, lqr.Q, lqr.R, lqr.S, lqr.QN, lqr.C, lqr.D, lqr.CN])
    fields = {name: _clean(getattr(lqr, name), finite, eye=name in ("Q", "R", "QN"))
              for name in ("A", "B", "Q", "R", "S") + _OTHER_FIELDS}
    return LQR(bounds=lqr.bounds, **fields), finite


def _sanitize_stacked(lqr: LQR, shift: Optional[Tensor] = None):
    """:func:`_sanitize` and the stage blocks stacked over ``z = (δx, δu)``, stored time-major:
    ``W = [A B] (N, B, nx, nx+nu)`` and ``Hs = [[Q, Sᵀ], [S, R]] (N, B, nx+nu, nx+nu)``, of which the cleaned
    ``A, B, Q, R, S`` are (batch-first) views. A sweep reads one stage of every instance at a time: stored
    time-major, that stage is one contiguous block (see :func:`_time_major`).

    The cost is in memory: the blocks are checked and cleaned once stacked (not as five, often strided,
    views of one Hessian), in place, and ``Hs`` is filled block by block: every new buffer of megabytes
    costs its page faults (B = 256, N = 30, nx = 8, nu = 4: 5 ms, against 11 ms for :func:`_sanitize` alone).
    Given already stacked (:meth:`LQR.from_blocks`), each is one copy whose rows are contiguous (1.4 ms against
    3.9 ms). ``shift (B,)`` is added to the diagonal of every Hessian block and of ``QN``."""
    Bsz, N, nx, nu = lqr.B.shape
    n = nx + nu
    tm = lambda a: a.transpose(0, 1)  # noqa: E731
    W = lqr.A.new_empty(N, Bsz, nx, n)
    Hs = lqr.Q.new_empty(N, Bsz, n, n)
    if lqr.W is not None:
        W.copy_(tm(lqr.W))
        Hs.copy_(tm(lqr.H))
    else:
        W[..., :nx], W[..., nx:] = tm(lqr.A), tm(lqr.B)
        Hs[..., :nx, :nx], Hs[..., :nx, nx:], Hs[..., nx:, :nx], Hs[..., nx:, nx:] = \
            tm(lqr.Q), tm(_mT(lqr.S)), tm(lqr.S), tm(lqr.R)
    QN = lqr.QN
    if shift is not None:
        Hs.diagonal(dim1=-2, dim2=-1).add_(shift.reshape(1, Bsz, 1))
        QN = QN + shift.reshape(Bsz, 1, 1) * torch.eye(nx, dtype=QN.dtype, device=QN.device)
    finite = all_finite([tm(W), tm(Hs), QN, lqr.C, lqr.D, lqr.CN])
    drop = ~finite.reshape(1, -1, 1, 1)
    W.masked_fill_(drop, 0.0)
    Hs.masked_fill_(drop, 0.0)
    Hs.diagonal(dim1=-2, dim2=-1).masked_fill_(drop[..., 0], 1.0)
    fields = {name: _clean(QN if name == "QN" else getattr(lqr, name), finite, eye=name == "QN")
              for name in _OTHER_FIELDS}
    cleaned = LQR(A=tm(W[..., :nx]), B=tm(W[..., nx:]), Q=tm(Hs[..., :nx, :nx]), R=tm(Hs[..., nx:, nx:]),
                  S=tm(Hs[..., nx:, :nx]), bounds=lqr.bounds, **fields)
    return cleaned, finite, W, Hs


def _time_major(stages: list) -> Tensor:
    """The per-stage tensors ``(B, ...)`` of a sweep as one batch-first ``(B, len, ...)`` view of a time-major
    buffer. A later sweep reads ``[:, t]``: one contiguous block, where a batch-first buffer would give B
    pieces a stage apart. Measured on one CPU core at B = 256, one 8 × 8 matrix-vector product a stage: 39 µs
    time-major against 94 µs batch-first (memory, not arithmetic: the small products are cache-bound)."""
    return torch.stack(stages, 0).transpose(0, 1)


def factorize(lqr: LQR, regularization: Optional[Tensor] = None, rank_tolerance: Optional[float] = None,
              shift: Optional[Tensor] = None) -> RiccatiFactor:
    """Backward Riccati sweep over the matrices of ``lqr``.

    Args:
        lqr: the batched LQR matrices.
        regularization: ``ρ (B,)`` added to ``Q_uu`` (ALTRO eq. 13) for the gains; the value function
            uses the unregularised ``Q_uu``.
        rank_tolerance: relative singular-value threshold for constraint rows; default
            :func:`default_rank_tolerance`.
        shift: ``δ (B,)`` added to the whole Hessian, every ``Q``, ``R`` and ``QN`` (IPOPT's inertia
            correction ``δ_w I``): the factorised problem, and the returned ``lqr``, are the shifted one.
    """
    exact = regularization is None and not lqr.propagated
    lqr, finite, W, Hs = _sanitize_stacked(lqr, shift)
    Bsz, N, nx, nu = lqr.B.shape[0], lqr.B.shape[1], lqr.A.shape[-1], lqr.B.shape[-1]
    dtype = lqr.A.dtype
    tol = default_rank_tolerance(dtype) if rank_tolerance is None else rank_tolerance
    if regularization is None:
        regularization = lqr.A.new_zeros(Bsz)
    eye_u = torch.eye(nu, dtype=dtype, device=lqr.A.device)
    eye_x = torch.eye(nx, dtype=dtype, device=lqr.A.device).expand(Bsz, nx, nx)
    rho = regularization.reshape(Bsz, 1, 1) * eye_u
    # With the stage blocks stacked over z = (δx, δu), one congruence H = Hs + Wᵀ P W gives Q_xx, Q_ux
    # and Q_uu together, and P = Eᵀ H E with E = [I; K] the value function: four products a stage instead
    # of nine, larger ones. On CPU PyTorch multiplies small batched matrices (m·n·k < 400) in a scalar
    # loop that costs more than its BLAS call per instance. Measured at B = 256, nx = 8, nu = 4, a stage:
    # the Q blocks 120 µs against 340 µs one by one, P 100 µs against 390 µs for Qxx + KᵀQux + QuxᵀK + KᵀQuuK.
    constrained = lqr.propagated
    held = None
    if lqr.bounds is not None:
        if lqr.CN is not None:
            raise ValueError("LQR.bounds declares the stage rows simple bounds: no terminal rows go with them")
        held = (lqr.mask @ lqr.bounds.abs().to(dtype)).clamp(max=1.0)  # (B, N, nu)
    P = lqr.QN
    Ps, Ks, Quus, Quxs, chols = [None] * (N + 1), [None] * N, [None] * N, [None] * N, [None] * N
    frees = [None] * N
    stage = [None] * N if constrained else None
    terminal = None
    Ps[N] = P
    infos = [None] * N
    G_next = None
    if constrained:
        CN = lqr.CN * lqr.maskN.unsqueeze(-1) if lqr.CN is not None else lqr.A.new_zeros(Bsz, 0, nx)
        scale = CN.abs().amax(dim=(-1, -2)) if CN.shape[1] else CN.new_zeros(Bsz)
        U2, gmask, G_next = _compress(CN, nx, tol, scale.clamp_min(torch.finfo(dtype).tiny))
        terminal = _Constraint(U=None, inv_s=None, V=None, rest=None, U2=U2, gmask=gmask, G=G_next)
        if lqr.C is not None or lqr.D is not None:
            C = lqr.C if lqr.C is not None else lqr.A.new_zeros(Bsz, N, lqr.D.shape[2], nx)
            D = lqr.D if lqr.D is not None else lqr.A.new_zeros(Bsz, N, C.shape[2], nu)
            CD = torch.cat([C, D], -1) * lqr.mask.unsqueeze(-1)  # (B, N, m, nx+nu) active stage rows
        else:
            CD = lqr.A.new_zeros(Bsz, N, 0, nx + nu)
    for t in range(N - 1, -1, -1):
        Wt = W[t]
        H = Hs[t] + _mm(_mT(Wt), _mm(P, Wt))
        Quu, Qux = _sym(H[..., nx:, nx:]), H[..., nx:, :nx]
        if constrained:
            M = torch.cat([CD[:, t], G_next @ Wt], -2)
            Mx, Mu = M[..., :nx], M[..., nx:]
            mt = Mx.shape[-2]
            U, s, Vh = torch.linalg.svd(Mu, full_matrices=True)
            scale = M.abs().amax(dim=(-1, -2)).clamp_min(torch.finfo(dtype).tiny)
            s_pad = _pad_rows(s.unsqueeze(-1), nu).squeeze(-1)
            fixed = s_pad > tol * scale.unsqueeze(-1)
            inv_s = torch.where(fixed, 1.0 / torch.where(fixed, s_pad, torch.ones_like(s_pad)), torch.zeros_like(s_pad))
            V = _mT(Vh)
            T = _mT(U) @ Mx  # (B, mt, nx)
            Kc = -V @ (inv_s.unsqueeze(-1) * _pad_rows(T, nu))
            rest = torch.ones(Bsz, mt, dtype=dtype, device=Wt.device)
            rest[:, : min(mt, nu)] = (~fixed[:, : min(mt, nu)]).to(dtype)
            U2, gmask, G = _compress(T * rest.unsqueeze(-1), nx, tol, scale)
            Vf = V * (~fixed).to(dtype).unsqueeze(-2)
            Hw = _sym(_mT(Vf) @ (Quu + rho) @ Vf + torch.diag_embed(fixed.to(dtype)))
            L, info = _cholesky(Hw)
            Kw = -_factored_solve(Hw, L, info, _mT(Vf) @ (Qux + Quu @ Kc))
            K = Kc + Vf @ Kw
            stage[t] = _Constraint(U=U, inv_s=inv_s, V=V, rest=rest, U2=U2, gmask=gmask, G=G)
            frees[t] = Vf
            G_next = G
        elif held is not None:  # the held controls out of the free ones' system
            free = 1.0 - held[:, t]
            Hu = (Quu + rho) * free.unsqueeze(-1) * free.unsqueeze(-2) + torch.diag_embed(held[:, t])
            L, info = _cholesky(Hu)
            K = -_factored_solve(Hu, L, info, Qux * free.unsqueeze(-1))
        else:
            Hu = Quu + rho
            L, info = _cholesky(Hu)
            K = -_factored_solve(Hu, L, info, Qux)
        infos[t] = info
        E = torch.cat([eye_x, K], -2)
        P = _sym(_mm_stacked(_mT(E), _mm_stacked(H, E)))
        Ps[t], Ks[t], Quus[t], Quxs[t], chols[t] = P, K, Quu, Qux, L
    return RiccatiFactor(
        lqr=lqr,
        K=_time_major(Ks),
        P=_time_major(Ps),
        ok=finite & (torch.stack(infos, 1) == 0).all(1),
        Quu=_time_major(Quus),
        Qux=_time_major(Quxs),
        chol=_time_major(chols),
        free=_time_major(frees) if constrained else None,
        stage=stage,
        terminal=terminal,
        exact=exact,
        fixed=held,
    )


def solve_lqr(lqr: LQR, rhs: LQRVectors, regularization: Optional[Tensor] = None, multipliers: bool = False) -> LQRSolution:
    """Factorise and solve in one call (see :func:`factorize` and :meth:`RiccatiFactor.solve`)."""
    return factorize(lqr, regularization).solve(rhs, multipliers=multipliers)
