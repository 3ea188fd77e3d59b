r"""The lean sweeps: the recursions of :mod:`~torchtraj.riccati.factorization` and :mod:`~torchtraj.riccati.factor`
written as a handful of batched library calls per stage.

A stage of a sweep works on tiny matrices, so its cost is the number of calls, not their arithmetic. Everything
that does not depend on the recursion is therefore done for all stages at once, before or after the loop: the
stage blocks are split into per-stage views by one ``unbind`` (not one indexing call per block and stage), the
right-hand sides are stacked and transposed once, the expected decrease ``ΔV`` and the gains' stationarity terms
are batched over the horizon; the matrix sweep writes each stage's results into views of buffers allocated once,
so that no stage joins, splits or stacks blocks. Vectors are carried as columns ``(B, n, 1)``, so that each
product with its addend is one ``baddbmm``. With the stage blocks ``W_k = [A_k B_k]``, ``H_k`` and
``E_k = [I; K_k]`` (ALTRO, Howell et al. 2019 eqs. 14-16), the matrix sweep is, per stage,

.. math::

    H = H_k + W_k^T P_{k+1} W_k,\quad K_k = -(Q_{uu} + \rho I)^{-1} Q_{ux},\quad P_k = \mathrm{sym}(E_k^T H E_k),

the vector sweep, with ``Q_z = [Q_x; Q_u]`` and ``M_k = (Q_{uu} K_k + Q_{ux})^T`` computed for all stages at once,

.. math::

    Q_z = [q_k; r_k] + W_k^T (P_{k+1} c_k + p_{k+1}),\quad k_k = -(Q_{uu} + \rho I)^{-1} Q_u,\quad
    p_k = E_k^T Q_z + M_k k_k,

(which is ``Q_x + K_kᵀ (Q_uu k_k + Q_u) + Q_xu k_k``), and the forward sweep
``δu_k = K_k δx_k + k_k``, ``δx_{k+1} = A_k δx_k + B_k δu_k + c_k``. Both vector sweeps are affine recursions
once the matrices are known: the feedforward is affine in ``Q_u`` (``k_k = k0_k + G_k Q_u``), so
``p_k = b_k + F_k p_{k+1}`` (:func:`solve_stages`) and ``δx_{k+1} = Φ_k δx_k + d_k`` with ``Φ_k = A_k + B_k K_k``
(:func:`forward_stages`); their coefficients are formed for all stages at once, and each stage is then one
product. A single control (``nu = 1``) takes its
gain as a product with ``−1 / (Q_uu + ρ)``, a division for the whole horizon instead of a factorisation per stage;
declared bounds (:mod:`~torchtraj.riccati.bounds`) take the free-control mask ``F`` into the same products. Stages
whose reduced Hessian is not positive definite get the identity in its place, as the general sweep does.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import addmatmul, matmul
from .linalg import _batch_first, _cholesky, _cholesky_solve, _mT, _time_major


def _stages(a: Tensor) -> tuple:
    """The per-stage views ``a[:, t]`` of a batch-first ``(B, T, ...)`` tensor, in one call."""
    return a.unbind(1)


def _columns(v: Tensor) -> tuple:
    """The per-stage column vectors ``(B, n, 1)`` of ``v (B, T, n)``."""
    return v.unsqueeze(-1).unbind(1)


def _stage_inputs(W: Tensor, Hs: Tensor, rho: Tensor, held: Optional[Tensor], negated: bool = False) -> tuple:
    """What both matrix sweeps read per stage, made once for the horizon: ``(ρ I, W_k / 2, W_kᵀ, H_k, (outer,
    held_diag, free_rows))``, the held controls' terms per stage (each ``None`` without ``held``); ``−H_k`` where
    ``negated`` (the eager sweep, which carries its matrices negated).

    The sweep carries ``2 P_k = X + Xᵀ`` (``X = E_kᵀ H E_k``), the symmetrisation without its halving, and takes
    ``P_k W_k`` as ``(2 P_k)(W_k / 2)``: scaling by a power of two is exact, so every ``P_k``, ``H`` and ``K`` is the
    one of ``sym(X)``, one call a stage fewer, and the stack of them is halved once."""
    Bsz, nu = W.shape[1], W.shape[-1] - W.shape[-2]
    rho = rho.reshape(Bsz, 1, 1) * torch.eye(nu, dtype=W.dtype, device=W.device)
    held_terms = (None, None, None) if held is None else tuple(_stages(term) for term in _held_terms(held))
    return rho, (0.5 * W).unbind(0), _mT(W).unbind(0), (Hs.neg() if negated else Hs).unbind(0), held_terms


def _held_terms(held: Tensor) -> tuple:
    """``(outer, held_diag, free_rows)`` ``(B, N, ...)`` of the held controls ``held (B, N, nu)``: the free
    controls' outer product, the held ones' diagonal and the free ones as a column."""
    free = 1.0 - held
    return free.unsqueeze(-1) * free.unsqueeze(-2), torch.diag_embed(held), free.unsqueeze(-1)


def factorize_stages(W: Tensor, Hs: Tensor, QN: Tensor, rho: Tensor, held: Optional[Tensor]):
    """The matrix sweep without back-propagated rows.

    ``W (N, B, nx, nx+nu)`` and ``Hs (N, B, nx+nu, nx+nu)`` the time-major stage blocks, ``QN (B, nx, nx)``,
    ``ρ (B,)``, ``held (B, N, nu)`` the controls that declared bounds hold (``None``: none). Returns
    ``(P (B, N+1, nx, nx), K (B, N, nu, nx), Q_uu, Q_ux, chol, ok)``, batch-first views of time-major buffers;
    ``chol`` the Cholesky factors of the reduced Hessians (``nu = 1``: the reduced Hessian negated, whose root
    :func:`finish_single` takes) and ``ok``: ``nu = 1`` the stages' tests, time-major ``(N, B, 1, 1)``, else
    ``(B,)``.

    Each stage writes its results into buffers allocated once (:class:`_Buffers`), whose per-stage blocks are
    views made once for the horizon: ``H`` holds ``Q_ux`` and ``Q_uu``, the gains are the lower rows of the buffer
    of ``E_k = [I; K_k]`` (its identity rows set once) and ``E_kᵀ`` is a view of it, so that a stage of a single
    control is eight calls: two products for ``H``, three for the gain, two for ``X = E_kᵀ H E_k`` and one for
    ``X + Xᵀ``, with no joining, splitting or stacking.

    The sweep carries every matrix negated, ``−H``, ``−X`` and ``−2 P_k`` (from ``−H_k`` given once for all
    stages): negation is exact, so each is the negation of the plain sweep's to the last bit, and the gain of a
    single control is then one division, ``K = (−Q_ux) / d`` with ``d = Q_uu + ρ`` where it is positive and 1
    elsewhere (``torch.threshold``, one call where a test and a choice took two). The stacks are negated back once.
    A NaN pivot (an overflow inside the sweep: non-finite blocks are replaced before it) gives NaN gains where a test
    and a choice gave the identity's; its stage fails the ``ok`` test either way."""
    if torch.compiler.is_compiling() or (torch.is_grad_enabled() and any(t.requires_grad for t in (W, Hs, QN, rho))):
        return _factorize_stages_traced(W, Hs, QN, rho, held)
    N, Bsz, nx, n = W.shape
    nu = n - nx
    buf = _Buffers(W, N, Bsz, nx, nu)
    rho, Ws, WTs, minus_Hss, (outer, held_diag, free_rows) = _stage_inputs(W, Hs, rho, held, negated=True)
    chols, oks = [None] * N, [None] * N
    buf.put(buf.P[N], torch.mul, QN, -2.0)
    for t in range(N - 1, -1, -1):  # buf.H, buf.X and buf.P hold −H, −X and −2 P (docstring)
        H = buf.put(buf.H[t], buf.addmatmul, minus_Hss[t], WTs[t], buf.matmul(buf.P[t + 1], Ws[t]))
        Qux = rows = buf.Qux[t]
        if nu == 1:  # K = −Q_ux / (Q_uu + ρ), the identity in place of a reduced Hessian that is not positive
            if held is None:
                buf.put(buf.pivot[t], torch.sub, rho, buf.Quu[t])
            else:  # the held controls out of the free ones' system
                buf.put(buf.pivot[t], torch.add, torch.sub(rho, buf.Quu[t]) * outer[t], held_diag[t])
                rows = Qux * free_rows[t]
            buf.put(buf.K[t], torch.div, rows, buf.put(buf.chol[t], torch.threshold, buf.pivot[t], 0.0, 1.0))
        else:
            Hu = torch.sub(rho, buf.Quu[t])
            if held is not None:
                Hu = Hu * outer[t] + held_diag[t]
                rows = Qux * free_rows[t]
            chols[t], info = _cholesky(Hu)
            oks[t] = info == 0
            buf.K[t].copy_(_cholesky_solve(rows, chols[t]))
        buf.put(buf.P[t], torch.add, buf.put(buf.X[t], buf.matmul, buf.ET[t], buf.matmul(H, buf.E[t])), buf.XT[t])
    chol, ok = buf.single() if nu == 1 else (_time_major(chols), torch.stack(oks, 1).all(1))
    K, Quu, Qux = buf.stacked()
    return buf.Ps * -0.5, K, Quu, Qux, chol, ok


def _factorize_stages_traced(W: Tensor, Hs: Tensor, QN: Tensor, rho: Tensor, held: Optional[Tensor]):
    """:func:`factorize_stages` traced by ``torch.compile`` or under autograd: the same recursion with new tensors
    for every stage's results (writes into views of buffers make a compiled kernel's batch size static, and ``out=``
    takes no part in autograd). The loop keeps ``H`` and ``2 P`` of each stage; the gains, pivots and tests of all
    stages are made again from the stack of ``H`` after it, by the same elementwise arithmetic. In a compiled kernel
    each stage's result that leaves the loop is a tensor handle of its own, and at a batch of one the handles cost
    more than the arithmetic."""
    N, Bsz, nx, n = W.shape
    eye_x = torch.eye(nx, dtype=W.dtype, device=W.device).expand(Bsz, nx, nx)
    rho, Ws, WTs, Hss, _ = _stage_inputs(W, Hs, rho, None)
    terms = None if held is None else _held_terms(held)  # made once: the loop reads their stages, the end all
    held_stages = None if terms is None else tuple(_stages(term) for term in terms)
    P2 = QN + QN
    Ps, Hs_stages = [None] * (N + 1), [None] * N
    Ps[N] = P2
    for t in range(N - 1, -1, -1):
        H = addmatmul(Hss[t], WTs[t], matmul(P2, Ws[t]))
        K = _stage_gains(H, nx, rho, None if terms is None else tuple(term[t] for term in held_stages))[0]
        E = torch.cat([eye_x, K], -2)
        X = matmul(_mT(E), matmul(H, E))
        P2 = X + _mT(X)
        Ps[t], Hs_stages[t] = P2, H
    K, Quu, Qux, L, ok = _stage_gains(torch.stack(Hs_stages, 1), nx, rho.unsqueeze(1), terms)
    return _time_major(Ps) * 0.5, K, Quu, Qux, L, (ok.transpose(0, 1) if K.shape[-2] == 1 else ok.all(1))


def _stage_gains(H: Tensor, nx: int, rho: Tensor, held_terms: Optional[tuple]) -> tuple:
    """``(K, Q_uu, Q_ux, L, ok)`` of the traced sweep from ``H (..., n, n)``, one stage's ``(B, n, n)`` or every
    stage's ``(B, N, n, n)``, with ``ρ I`` and the held controls' terms (``None``: none held) shaped to match: the
    gain ``K = −(Q_uu + ρ)⁻¹ Q_ux`` (a single control: ``Q_ux / −(Q_uu + ρ)``, ``L = −(Q_uu + ρ)`` and −1 where
    the pivot is not positive), the factor ``L`` and the test ``ok``."""
    nu = H.shape[-1] - nx
    Qux, Quu = H[..., nx:, :].split([nx, nu], -1)
    rows = Qux
    if nu == 1:  # K = Q_ux / −(Q_uu + ρ), the identity in place of a reduced Hessian that is not positive
        negative = torch.sub(-rho, Quu)
        if held_terms is not None:  # the held controls out of the free ones' system
            outer, held_diag, free_rows = held_terms
            negative = negative * outer - held_diag
            rows = Qux * free_rows
        ok = negative < 0
        L = torch.where(ok, negative, -1.0)
        return rows / L, Quu, Qux, L, ok
    Hu = Quu + rho
    if held_terms is not None:
        outer, held_diag, free_rows = held_terms
        Hu = Hu * outer + held_diag
        rows = Qux * free_rows
    L, info = _cholesky(Hu)
    return -_cholesky_solve(rows, L), Quu, Qux, L, info == 0


class _Buffers:
    """The time-major outputs of :func:`factorize_stages` and the per-stage views it reads and writes, each made
    once for the horizon (one ``unbind`` a block, not one indexing call a stage).

    A stage's call writes its buffer itself (``out=``, :meth:`put`); a batched product written so may take another of
    the library's kernels than one into a new tensor, so a result can differ from that of the traced sweep
    (:func:`_factorize_stages_traced`) in its last bits."""

    matmul, addmatmul = staticmethod(torch.bmm), staticmethod(torch.baddbmm)

    def __init__(self, W: Tensor, N: int, Bsz: int, nx: int, nu: int):
        n = nx + nu
        Hb = W.new_empty(N, Bsz, n, n)
        Eb = W.new_empty(N, Bsz, n, nx)
        Eb[..., :nx, :] = torch.eye(nx, dtype=W.dtype, device=W.device)
        Xb = W.new_empty(N, Bsz, nx, nx)
        Pb = W.new_empty(N + 1, Bsz, nx, nx)
        Kb, Quub, Quxb = Eb[..., nx:, :], Hb[..., nx:, nx:], Hb[..., nx:, :nx]
        self.H, self.E, self.ET, self.X, self.XT = Hb.unbind(0), Eb.unbind(0), _mT(Eb).unbind(0), Xb.unbind(0), \
            _mT(Xb).unbind(0)
        self.P, self.K, self.Quu, self.Qux = Pb.unbind(0), Kb.unbind(0), Quub.unbind(0), Quxb.unbind(0)
        self._stacked = (Kb, Quub, Quxb)
        self.Ps = Pb.transpose(0, 1)
        if nu == 1:  # the stages' pivots Q_uu + ρ and their divisors (the pivot where positive, else 1)
            self._pivots, self._divisors = W.new_empty(N, Bsz, 1, 1), W.new_empty(N, Bsz, 1, 1)
            self.pivot, self.chol = self._pivots.unbind(0), self._divisors.unbind(0)

    def single(self) -> tuple:
        """``nu = 1``: ``(chol (B, N, 1, 1), ok (N, B, 1, 1))`` from the stages' divisors and pivots, as
        :func:`finish_single` takes them: ``chol`` the negated divisors (the reduced Hessians negated, −1 where not
        positive), ``ok`` where the pivot is positive."""
        return self._divisors.neg().transpose(0, 1), torch.gt(self._pivots, 0)

    def stacked(self) -> tuple:
        """``(K, Q_uu, Q_ux)``, each a batch-first view of a contiguous time-major copy: the stages' blocks are
        strided views of ``E`` and ``H``, and the later sweeps' products read them as the stacked lists were.
        ``H`` holds ``−H`` (:func:`factorize_stages`), so ``Q_uu`` and ``Q_ux`` are copied negated."""
        K, Quu, Qux = self._stacked
        return K.contiguous().transpose(0, 1), Quu.neg().transpose(0, 1), Qux.neg().transpose(0, 1)

    @staticmethod
    def put(out: Tensor, op, *args) -> Tensor:
        """``op(*args)`` written into ``out``, which is returned."""
        return op(*args, out=out)


def finish_single(chol: Tensor, ok: Tensor) -> tuple:
    """``nu = 1``: the Cholesky factors ``(B, N, 1, 1)`` from the stacked negated reduced Hessians, and
    ``ok (B,)`` from the time-major ``ok (N, B, 1, 1)`` of the stages."""
    return chol.neg().sqrt(), ok.all(0).reshape(-1)


def stage_terms(W: Tensor, P: Tensor, K: Tensor, Quu: Tensor, Qux: Tensor, q: Tensor, r: Tensor, c: Tensor) -> tuple:
    """What the vector sweep with back-propagated rows reads per stage, split once for all stages: ``(W_kᵀ, P_k,
    E_kᵀ, M_k, [q_k; r_k], c_k)`` with ``E_k = [I; K_k]``, ``M_k = (Q_uu K_k + Q_ux)ᵀ`` and the vectors as columns
    (module docstring)."""
    Bsz, N, nx = P.shape[0], K.shape[1], P.shape[-1]
    ET = torch.cat([torch.eye(nx, dtype=K.dtype, device=K.device).expand(Bsz, N, nx, nx), _mT(K)], -1)
    return (_stages(_mT(W)), _stages(P), _stages(ET), _stages(_mT(matmul(Quu, K) + Qux)),
            _columns(torch.cat([q, r], -1)), _columns(c))


def _flat(a: Tensor) -> Tensor:
    """``a (B, T, ...)``, a batch-first view of a time-major buffer (or any tensor), as ``(T·B, ...)`` time-major:
    a view where ``a`` is one, else one copy."""
    return a.transpose(0, 1).reshape(-1, *a.shape[2:])


def _feedforward(Quu: Tensor, chol: Tensor, held: Optional[Tensor], value: Optional[Tensor]) -> tuple:
    """The feedforward as an affine map of the stage's ``Q_u``, ``k_k = k0_k + G_k Q_u``, time-major
    (``(N·B, ...)``): ``(gain, k0)``, where ``gain(Y)`` is ``G Y`` for any columns ``Y (N·B, nu, m)`` and ``k0``
    ``(N·B, nu, 1)`` (``None`` without held controls).

    Unconstrained ``G = −(Q_uu + ρ)^{-1}`` (``nu = 1``: ``−1 / (Q_uu + ρ)``); with held controls at ``v``, the free
    ones minimise given them, ``k = v − (Q_uu + ρ)_F^{-1} F (Q_u + Q_uu v)``, so ``G = −(Q_uu + ρ)_F^{-1} F`` and
    ``k0 = v + G Q_uu v`` (``F`` the free-control mask). For ``nu > 1`` ``G`` is applied by a solve with the
    factor, never formed: an interior point's barrier makes ``Q_uu`` ill conditioned, and a product with an
    explicit inverse is not backward stable (in float32 the Newton steps of ``tests/test_implicit.py``'s car
    stalled at a stationarity of 1e-4)."""
    chol = _flat(chol)
    nu = chol.shape[-1]
    free = None if held is None else _flat(1.0 - held).unsqueeze(-1)
    if nu == 1:
        g = -1.0 / (chol * chol)
        if free is not None:
            g = g * free

        def gain(Y: Tensor) -> Tensor:
            return g * Y
    else:
        def gain(Y: Tensor) -> Tensor:
            return -_cholesky_solve(Y if free is None else Y * free, chol)
    if held is None:
        return gain, None
    v = _flat(value).unsqueeze(-1)
    return gain, v + gain(matmul(_flat(Quu), v))


def solve_stages(W: Tensor, P: Tensor, K: Tensor, Quu: Tensor, Qux: Tensor, chol: Tensor, q: Tensor, r: Tensor,
                 qN: Tensor, c: Tensor, held: Optional[Tensor] = None, value: Optional[Tensor] = None):
    r"""The vector sweep without back-propagated rows: ``(k (B, N, nu), p (B, N+1, nx), Q_u (B, N, nu))``.

    ``W (B, N, nx, nx+nu)``, ``P (B, N+1, nx, nx)``, ``K``, ``Quu``, ``Qux``, ``chol`` of the factorisation;
    ``q, r, qN, c`` the right-hand side; ``held (B, N, nu)`` the held controls and ``value (B, N, nu)`` the
    values they are held at (declared bounds, else ``None``).

    The feedforward is affine in ``Q_u`` (:func:`_feedforward`: ``k = k0 + G Q_u``), so with
    ``v_k = P_{k+1} c_k + p_{k+1}`` the vector recursion (module docstring) is affine in ``p_{k+1}``:

    .. math::  p_k = Q_x + K_k^T Q_u + M_k k_k = b_k + F_k p_{k+1},\quad F_k = A_k^T + R_k B_k^T,\quad
               R_k = K_k^T + M_k G_k,\quad b_k = q_k + R_k r_k + M_k k0_k + F_k P_{k+1} c_k.

    ``F`` and ``b`` are formed for all stages at once, the sweep is one product a stage, and ``Q_u`` and ``k``
    follow for all stages at once."""
    Bsz, N, nx, nu = K.shape[0], K.shape[1], P.shape[-1], K.shape[-2]
    gain, k0 = _feedforward(Quu, chol, held, value)
    A, Bu = _flat(W).split([nx, nu], -1)
    Kt = _flat(K)
    MT = addmatmul(_flat(Qux), _flat(Quu), Kt)  # M_kᵀ
    M = _mT(MT)
    R = _mT(Kt) + _mT(gain(MT))  # Gᵀ = G: the (free-masked) inverse is symmetric
    F = addmatmul(_mT(A), R, _mT(Bu))
    Pc = matmul(_flat(P[:, 1:]), _flat(c).unsqueeze(-1))
    r_col = _flat(r).unsqueeze(-1)
    b = addmatmul(addmatmul(_flat(q).unsqueeze(-1), R, r_col), F, Pc)
    if k0 is not None:
        b = addmatmul(b, M, k0)
    Fs, bs = F.unflatten(0, (N, Bsz)).unbind(0), b.unflatten(0, (N, Bsz)).unbind(0)
    p = qN.unsqueeze(-1)
    ps = [None] * (N + 1)
    ps[N] = p
    for t in range(N - 1, -1, -1):
        p = addmatmul(bs[t], Fs[t], p)
        ps[t] = p
    p = torch.stack(ps, 0)  # (N+1, B, nx, 1)
    Qu = addmatmul(r_col, _mT(Bu), Pc + p[1:].flatten(0, 1))
    k = gain(Qu) if k0 is None else k0 + gain(Qu)
    return _batch_first(k, Bsz), p.squeeze(-1).transpose(0, 1), _batch_first(Qu, Bsz)


def expected_change(k: Tensor, Qu: Tensor, Quu: Tensor) -> tuple:
    """``(ΔV1, ΔV2) (B,)``: ``ΔV(α) = α Σ k_kᵀ Q_u + ½ α² Σ k_kᵀ Q_uu k_k`` over all stages at once."""
    dV1 = (k * Qu).sum((1, 2))
    dV2 = 0.5 * (k * matmul(Quu, k.unsqueeze(-1)).squeeze(-1)).sum((1, 2))
    return dV1, dV2


def forward_stages(W: Tensor, K: Tensor, k: Tensor, c: Tensor, x0: Tensor) -> tuple:
    """The step ``(δx (B, N+1, nx), δu (B, N, nu))``: ``δu_k = K_k δx_k + k_k``,
    ``δx_{k+1} = A_k δx_k + B_k δu_k + c_k`` from ``δx_0 = x0``, as the closed loop
    ``δx_{k+1} = Φ_k δx_k + d_k`` with ``Φ_k = A_k + B_k K_k`` and ``d_k = B_k k_k + c_k`` formed for all stages at
    once (one product a stage), and ``δu`` for all stages after."""
    Bsz, N, nx = K.shape[0], K.shape[1], W.shape[-2]
    A, Bu = _flat(W).split([nx, W.shape[-1] - nx], -1)
    Kt, kt = _flat(K), _flat(k).unsqueeze(-1)
    Phis = addmatmul(A, Bu, Kt).unflatten(0, (N, Bsz)).unbind(0)
    ds = addmatmul(_flat(c).unsqueeze(-1), Bu, kt).unflatten(0, (N, Bsz)).unbind(0)
    x = x0.unsqueeze(-1)
    xs = [x]
    for t in range(N):
        x = addmatmul(ds[t], Phis[t], x)
        xs.append(x)
    X = torch.stack(xs, 0)  # (N+1, B, nx, 1)
    u = addmatmul(kt, Kt, X[:-1].flatten(0, 1))
    return X.squeeze(-1).transpose(0, 1), _batch_first(u, Bsz)


def costate_stages(A: Tensor, local: Tensor, last: Tensor) -> Tensor:
    """``λ (B, N+1, nx)`` of ``λ_N = last``, ``λ_k = local_k + A_kᵀ λ_{k+1}`` (``local (B, N, nx)``: the terms of
    the x-stationarity that do not depend on the recursion, computed for all stages at once)."""
    ATs, locs = _stages(_mT(A)), _columns(local)
    lam = last.unsqueeze(-1)
    lams = [None] * (len(ATs) + 1)
    lams[-1] = lam
    for t in range(len(ATs) - 1, -1, -1):
        lam = addmatmul(locs[t], ATs[t], lam)
        lams[t] = lam
    return torch.stack(lams, 1).squeeze(-1)
