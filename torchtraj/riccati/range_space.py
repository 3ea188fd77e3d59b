r"""Terminal equality rows by the range-space (Schur complement) method, on top of the unconstrained sweep.

An LQR problem whose only equality rows are terminal, ``C_N δx_N + e_N = 0`` (an interior point's goal
constraint), is the unconstrained problem with the terminal gradient ``q_N + C_Nᵀ ν`` for the right multiplier
``ν``; its solution is affine in ``ν``. With the unconstrained factorisation (sequential or parallel sweep, no
back-propagated rows: :mod:`~torchtraj.riccati.propagation`'s two SVDs a stage are the costliest part of a sweep
with rows), the response to ``ν`` is the homogeneous problem's (``q = r = c = 0``, ``δx_0 = 0``, ``q_N = C_Nᵀ``),
columns ``Π_k = Ψ_kᵀ C_Nᵀ`` with ``Ψ_k = Φ_{N−1} ⋯ Φ_k`` the closed loop's transition (``Φ_k = A_k + B_k K_k``):

.. math::

    p^h_k = Π_k = Φ_k^T Π_{k+1},\ Π_N = C_N^T, \qquad k^h_k = -Q_{uu,k}^{-1} B_k^T Π_{k+1}, \qquad
    δx^h_{k+1} = Φ_k δx^h_k + B_k k^h_k,\ δx^h_0 = 0,

and ``λ^h_k = P_k δx^h_k + Π_k`` (the gains are exact). The terminal rows then read
``C_N δx_N(ν) + e_N = r + Σ ν = 0`` with ``r = C_N δx^0_N + e_N`` from the unconstrained solution and
``Σ = C_N δx^h_N = Σ_j T_j``, ``T_j = Π_{j+1}^T B_j k^h_j = −Π_{j+1}^T B_j Q_{uu,j}^{-1} B_j^T Π_{j+1}`` (negative
semidefinite: minus the closed loop's reachability Gramian seen through the rows). So ``ν = −Σ⁺ r`` with the
pseudo-inverse at the rank tolerance (dependent rows, and rows the controls cannot reach, drop out as the
back-propagation's rank-revealing SVD drops them), and every field of the solution is the unconstrained one plus
the homogeneous columns times ``ν``.

**The terminal penalty.** The unconstrained sweep needs each stage's ``Q_uu`` positive definite, where the
back-propagation needs the Hessian positive definite only on the directions the rows leave free (the inertia an
interior point's regularisation tests). The unconstrained problem therefore takes ``Q_N + ρ Π`` with
``Π = C_N⁺ C_N`` the projector onto the rows' span: on the rows' feasible set ``Π δx_N = −C_N⁺ e_N`` is fixed, so
the penalty ``½ ρ δx_Nᵀ Π δx_N`` is constant there and the constrained solution does not change, while for ρ large
enough the Hessian is positive definite on the dynamics' null space wherever it is on the rows' (Finsler's lemma),
so the inertia test answers as the back-propagation's. ``ρ`` is ten times the Hessian's largest entry
(:func:`penalised`): a scale, not the bound of Finsler's lemma. The rows' multipliers then carry the penalty's
gradient, ``ν + ρ C_N⁺ᵀ δx_N``.

The feedback gains are the constrained problem's, those of the back-propagation: a perturbation ``δx_k`` moves the
terminal rows by ``Π_kᵀ δx_k`` and the controls from stage ``k`` on can answer with ``Σ_k = Σ_{j ≥ k} T_j``, so

.. math::  K^c_k = K_k - k^h_k Σ_k^+ Π_k^T.

A step needs none of them, only ``Σ_0⁺``, and the per-stage pseudo-inverses are the costliest part of the
factorisation in a large batch (one small factorisation per stage and instance). So the factor holds the gains'
parts (:class:`TerminalGains`) and forms them when they are read (``RangeSpaceFactor.K``); a solver that reports
the gains of each instance's last step keeps the parts instead (:func:`select_gains`, rows by indexing) and forms
the gains once, at the end (:func:`formed`).

The factorisation's cost is the unconstrained sweep's plus two matrix products a stage (the chains of ``Π`` and
``δx^h``; with the parallel sweep, associative scans) and a constant number of calls for all stages at once; each
solve is one unconstrained solve plus a constant number.

On a GPU the pseudo-inverses (of ``C_N`` and of the ``Σ_k``) are Jacobi rotations' (:func:`by_rotations`): the
same thresholds, no host read, so that a CUDA graph captures the whole factorisation. On a CPU they are LAPACK's,
but for ``C_N``'s in a kernel that ``torch.compile`` traces, and for all in a single instance's kernel: there the
rotations are loops of the kernel, where Inductor would call LAPACK once a matrix (and keep that kernel's buffers
off the stack, :mod:`~torchtraj.core.stack_buffers`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import addmatmul, matmul, single_instance
from ..core.graphs import capturing
from ..core.masks import where_rows
from . import jacobi
from .factor import RiccatiFactor
from .linalg import _cholesky_solve, _mT, _sym
from .lqr import LQR, LQRSolution, LQRVectors
from .parallel import ParallelRiccatiFactor
from .parallel_scan import _compose_backward, _compose_forward, associative_scan
from .sanitize import all_finite
from .sweep import expected_change

TERMINAL_ROWS = ("back-propagation", "range-space")
#: The terminal penalty's weight relative to the Hessian's scale (:func:`penalised`).
PENALTY = 10.0


def check_terminal_rows(value: str) -> None:
    """Raise where ``value`` is none of :data:`TERMINAL_ROWS` (a solver option's check)."""
    if value not in TERMINAL_ROWS:
        raise ValueError(f"terminal_rows must be 'range-space' or 'back-propagation', not {value!r}")


def applies(lqr: LQR, regularization: Optional[Tensor]) -> bool:
    """Whether the range-space method takes ``lqr``'s rows: terminal rows only (stage rows absent or none, ``C``
    of zero rows), no declared bounds, no ``ρ``."""
    return (lqr.CN is not None and not _has_stage_rows(lqr) and lqr.bounds is None
            and regularization is None)


def _has_stage_rows(lqr: LQR) -> bool:
    return lqr.C is not None and lqr.C.shape[-2] > 0


@dataclass
class TerminalGains:
    """The constrained feedback gains ``K^c_k = K_k − k^h_k Σ_k⁺ Π_kᵀ`` (module docstring) before they are formed:
    ``K (B, N, nu, nx)`` the unconstrained problem's gains, ``kh (B, N, nu, mN)``, ``Pi (B, N, nx, mN)`` the
    ``Π_k`` of the stages, ``sums (B, N, mN, mN)`` the ``−Σ_k``, ``tol`` the rank tolerance of their
    pseudo-inverses."""

    K: Tensor
    kh: Tensor
    Pi: Tensor
    sums: Tensor
    tol: float

    def value(self) -> Tensor:
        """The gains ``(B, N, nu, nx)``."""
        inverses, _ = _pseudo_inverse(self.sums, self.tol)
        return self.K + self.kh @ (inverses @ _mT(self.Pi))

    def parts(self) -> tuple:
        """The batch-first tensors ``(K, kh, Pi, sums)``."""
        return self.K, self.kh, self.Pi, self.sums

    def __getitem__(self, rows) -> "TerminalGains":
        """The gains of the instances ``rows`` (an index of the batch)."""
        return TerminalGains(*(part[rows] for part in self.parts()), tol=self.tol)

    def index_copy(self, dim: int, index: Tensor, source: "TerminalGains") -> "TerminalGains":
        """These gains with the instances ``index`` replaced by ``source``'s (``dim`` 0, the batch; as
        :meth:`torch.Tensor.index_copy`)."""
        return TerminalGains(*(part.clone().index_copy_(dim, index, row)  # in a copy of the same layout
                               for part, row in zip(self.parts(), source.parts())), tol=self.tol)

    def of(self, K: Tensor) -> "TerminalGains":
        """Formed gains ``K`` in this form: no terminal part (``kh = Π = 0``, ``−Σ = I``), so that
        :meth:`value` gives ``K`` back."""
        eye = torch.eye(self.sums.shape[-1], dtype=K.dtype, device=K.device).expand_as(self.sums)
        return TerminalGains(K, torch.zeros_like(self.kh), torch.zeros_like(self.Pi), eye, self.tol)


def gains_of(factor) -> "Tensor | TerminalGains":
    """The feedback gains of a factorisation, those of a :class:`RangeSpaceFactor` not yet formed."""
    return factor.gains if isinstance(factor, RangeSpaceFactor) else factor.K


def feedforward_of(factor, sol: LQRSolution) -> Tensor:
    """The feedforward ``k (B, N, nu)`` that goes with ``factor.K``, ``δu_k = k_k + K_k δx_k`` along the step
    ``sol`` (a closed-loop rollout's): ``sol.k`` itself, but for a :class:`RangeSpaceFactor`, whose ``sol.k`` goes
    with the unconstrained gains (``inner.K``), ``δu − K δx`` with the constrained gains ``K``."""
    if not isinstance(factor, RangeSpaceFactor):
        return sol.k
    return sol.du - (factor.K @ sol.dx[:, :-1].unsqueeze(-1)).squeeze(-1)


def formed(gains) -> Tensor:
    """The feedback gains of ``gains``, a tensor or :class:`TerminalGains`."""
    return gains.value() if isinstance(gains, TerminalGains) else gains


def select_gains(mask: Tensor, a, b):
    """``a`` for the instances in ``mask (B,)``, ``b`` elsewhere, of gains that are tensors or
    :class:`TerminalGains` (formed ones beside those in the other's form, :meth:`TerminalGains.of`); of two
    tensors, :func:`~torchtraj.core.masks.where_rows`."""
    if isinstance(a, Tensor) and isinstance(b, Tensor):
        return where_rows(mask, a, b)
    a = b.of(a) if isinstance(a, Tensor) else a
    b = a.of(b) if isinstance(b, Tensor) else b
    return TerminalGains(*(where_rows(mask, x, y) for x, y in zip(a.parts(), b.parts())), tol=a.tol)


@dataclass
class RangeSpaceFactor:
    """The factorisation of an LQR problem with terminal rows by the range-space method (module docstring).

    ``inner`` the factorisation of the penalised unconstrained problem, ``lqr`` the shifted problem with its rows
    (its ``Q_N`` with the penalty), ``K (B, N, nu, nx)`` the constrained feedback gains, ``P`` the unconstrained
    value function's Hessians, ``ok (B,)``; the homogeneous columns (last dimension ``mN``):
    ``Pi (B, N+1, nx, mN)``, ``kh (B, N, nu, mN)``, ``dxh (B, N+1, nx, mN)``, ``duh (B, N, nu, mN)``,
    ``lamh (B, N+1, nx, mN)``; ``inverse (B, mN, mN)`` the pseudo-inverse of ``−Σ``; ``penalty (B, mN, nx)`` the
    penalty's share of the rows' multipliers, ``ρ C⁺ᵀ``. ``K`` forms the gains from ``gains`` at its first read."""

    inner: RiccatiFactor
    lqr: LQR
    gains: TerminalGains
    P: Tensor
    ok: Tensor
    Pi: Tensor
    kh: Tensor
    dxh: Tensor
    duh: Tensor
    lamh: Tensor
    inverse: Tensor
    penalty: Tensor
    _K: Optional[Tensor] = field(default=None, init=False, repr=False)

    @property
    def K(self) -> Tensor:
        """The constrained feedback gains ``(B, N, nu, nx)``."""
        if self._K is None:
            self._K = self.gains.value()
        return self._K

    def solve(self, rhs: LQRVectors, multipliers: bool = False, forward: bool = True,
              initial_multiplier: Optional[Tensor] = None) -> LQRSolution:
        """Solve for ``rhs``: the unconstrained solution, the multipliers ``ν = −Σ⁺ r`` of the terminal rows and
        the homogeneous columns times ``ν`` (module docstring). The step is computed whatever ``forward`` (``ν``
        needs ``δx_N``); no rows are left at the fixed initial state, so ``initial_multiplier`` does not apply.
        The feedforward ``k`` is the unconstrained gains' (``δu = k + inner.K δx``); that of the constrained gains
        ``K`` is :func:`feedforward_of`'s."""
        lqr = self.lqr
        base = self.inner.solve(dataclasses.replace(rhs, e=None, eN=None), multipliers=multipliers)
        residual = (_active_rows(lqr) @ base.dx[:, -1].unsqueeze(-1)).squeeze(-1)
        if rhs.eN is not None:
            residual = residual + (rhs.eN * lqr.maskN if lqr.maskN is not None else rhs.eN)
        nu = self.inverse @ residual.unsqueeze(-1)  # ν = −Σ⁺ r = (−Σ)⁺ r
        column = nu.unsqueeze(1)

        def plus(value: Tensor, homogeneous: Tensor) -> Tensor:
            return value + (homogeneous @ column).squeeze(-1)

        k, p = plus(base.k, self.kh), plus(base.p, self.Pi)
        dx, du = plus(base.dx, self.dxh), plus(base.du, self.duh)
        # the Q-functions' gradients of the combined solution, for its expected change
        Qu = (_mT(lqr.B) @ (self.P[:, 1:] @ rhs.c.unsqueeze(-1) + p[:, 1:].unsqueeze(-1))).squeeze(-1) + rhs.r
        dV1, dV2 = expected_change(k, Qu, _stage_matrices(self.inner.Quu))
        out = LQRSolution(dx=dx, du=du, k=k, p=p, dV1=dV1, dV2=dV2)
        if multipliers:
            out.costate = plus(base.costate, self.lamh)
            # the penalty's gradient ρ Π δx_N = C_Nᵀ (ρ C⁺ᵀ δx_N) is part of the rows' multiplier
            nuN = nu.squeeze(-1) + (self.penalty @ dx[:, -1].unsqueeze(-1)).squeeze(-1)
            out.nuN = nuN * lqr.maskN if lqr.maskN is not None else nuN
        return out


def _stage_matrices(a: Tensor) -> Tensor:
    """``(B, N, nu, nu)`` per-stage matrices; the parallel sweep stores its ``1 × 1`` ones as ``(B, N, 1)``."""
    return a if a.dim() == 4 else a.unsqueeze(-1)


def _reverse_chain(PhiT: Tensor, last: Tensor, parallel: bool) -> Tensor:
    """``Π (B, N+1, n, m)``: ``Π_N = last (B, n, m)``, ``Π_k = PhiT_k Π_{k+1}`` for ``PhiT (B, N, n, n)``."""
    if parallel:  # every suffix product Φ_kᵀ ⋯ Φ_{N−1}ᵀ by an associative scan, then applied to Π_N
        B, N = PhiT.shape[:2]
        tm = PhiT.transpose(0, 1).flatten(0, 1)
        (suffix,) = associative_scan((tm,), _compose_backward, B, reverse=True)
        chain = torch.bmm(suffix, last.repeat(N, 1, 1)).unflatten(0, (N, B)).transpose(0, 1)
        return torch.cat([chain, last.unsqueeze(1)], 1)
    steps = PhiT.unbind(1)
    out = [None] * (len(steps) + 1)
    out[-1] = value = last
    for t in range(len(steps) - 1, -1, -1):
        value = matmul(steps[t], value)
        out[t] = value
    return torch.stack(out, 1)


def _forward_chain(Phi: Tensor, drive: Tensor, parallel: bool) -> Tensor:
    """``x (B, N+1, n, m)``: ``x_0 = 0``, ``x_{k+1} = Φ_k x_k + drive_k`` for ``Phi (B, N, n, n)``."""
    B, N, n, m = drive.shape
    zero = drive.new_zeros(B, 1, n, m)
    if parallel:  # the maps x ↦ Φ x + d as [[Φ, d], [0, I]], composed by an associative scan, applied to [0; I]
        eye = torch.eye(m, dtype=drive.dtype, device=drive.device).expand(B, N, m, m)
        maps = torch.cat([torch.cat([Phi, drive], -1), torch.cat([drive.new_zeros(B, N, m, n), eye], -1)], -2)
        (prefix,) = associative_scan((maps.transpose(0, 1).flatten(0, 1),), _compose_forward, B)
        chain = prefix[:, :n, n:].unflatten(0, (N, B)).transpose(0, 1)  # applied to [0; I]: the last m columns
        return torch.cat([zero, chain], 1)
    Phis, drives = Phi.unbind(1), drive.unbind(1)
    out = [zero.squeeze(1)] + [None] * N
    value = drives[0]
    out[1] = value
    for t in range(1, N):
        value = addmatmul(drives[t], Phis[t], value)
        out[t + 1] = value
    return torch.stack(out, 1)


def by_rotations(M: Tensor) -> bool:
    """Whether the pseudo-inverses of ``M`` are Jacobi rotations' (:mod:`~torchtraj.riccati.jacobi`): on a GPU,
    where LAPACK-style solvers read their status on the host, which a CUDA graph cannot capture, and in a single
    instance's compiled kernel (:func:`~torchtraj.core.compiled.single_instance`: a library call there)."""
    return M.is_cuda or capturing() or single_instance(M)


def _eigen_inverse(M: Tensor, tol: float) -> Tensor:
    """The pseudo-inverse of the symmetric positive semidefinite ``M (..., m, m)``: its eigenvalues above ``tol``
    times the largest inverted, the others dropped. Each matrix is divided by its largest entry first
    (``pinv(c M) = pinv(M) / c``), so that the eigensolver's own scaling cannot overflow. Where
    :func:`by_rotations`, by Jacobi rotations (:func:`~torchtraj.riccati.jacobi.pinv`: for this positive
    semidefinite ``M`` the singular values are the eigenvalues)."""
    scale = M.abs().flatten(-2).amax(-1).clamp_min(torch.finfo(M.dtype).tiny).unsqueeze(-1).unsqueeze(-1)
    if by_rotations(M):
        return jacobi.pinv(M / scale, tol) / scale
    w, V = torch.linalg.eigh(M / scale)
    keep = w > (tol * w.amax(-1, keepdim=True)).clamp_min(torch.finfo(w.dtype).tiny)
    inverse_w = torch.where(keep, w.reciprocal(), torch.zeros_like(w))
    return matmul(V * inverse_w.unsqueeze(-2), _mT(V)) / scale


def _isolated_eigen_inverse(M: Tensor, tol: float) -> tuple:
    """:func:`_eigen_inverse` of the matrices ``M (K, m, m)`` and ``ok (K,)``: where LAPACK's eigensolver does not
    converge for one of them (it raises for the whole batch), the batch is halved until that matrix is alone, and
    it gets a zero inverse and ``ok`` false (its instance fails; the others' inverses are those of their own
    halves: the same numbers, as each matrix is decomposed on its own)."""
    try:
        return _eigen_inverse(M, tol), torch.ones(M.shape[0], dtype=torch.bool, device=M.device)
    except torch.linalg.LinAlgError:
        if M.shape[0] == 1:
            return torch.zeros_like(M), torch.zeros(1, dtype=torch.bool, device=M.device)
        half = M.shape[0] // 2
        (first, ok_first), (second, ok_second) = (_isolated_eigen_inverse(part, tol)
                                                  for part in (M[:half], M[half:]))
        return torch.cat([first, second]), torch.cat([ok_first, ok_second])


def _pseudo_inverse(negative: Tensor, tol: float) -> tuple:
    """The pseudo-inverse of the symmetric positive semidefinite ``negative (..., m, m)`` at the relative ``tol``
    of its largest eigenvalue, and whether it was finite (a non-finite matrix gets the identity's: no instance's
    failure reaches the batched eigensolver of the others).

    A batched eigensolver of many tiny matrices costs several times a Cholesky factorisation, and most of these
    matrices (every stage but the last few, whose controls cannot reach every row) are well conditioned. So all
    are factorised, and those whose factor proves ``λ_min > tol λ_max`` are inverted with it: with the pivots
    ``p_i = L_ii²`` and the largest diagonal entry ``d``, ``λ_max ≤ m d`` and ``λ_min ≥ Π p_i / λ_max^{m−1}``, so
    ``Π p_i > tol (m d)^m`` suffices. The others (gathered, one read of their count by the host) take the
    eigen-decomposition; while a CUDA graph is captured or torch.compile traces, every matrix does. A matrix the
    eigensolver does not converge on counts as not finite (:func:`_isolated_eigen_inverse`)."""
    M = _sym(negative)  # finiteness after symmetrising: entries near the largest float overflow in the sum
    finite = torch.isfinite(M).flatten(-2).all(-1)
    m = negative.shape[-1]
    eye = torch.eye(m, dtype=negative.dtype, device=negative.device)
    M = torch.where(finite.unsqueeze(-1).unsqueeze(-1), M, eye)
    if torch.compiler.is_compiling() or capturing():
        return _eigen_inverse(M, tol), finite
    L, info = torch.linalg.cholesky_ex(M)
    pivots = L.diagonal(dim1=-2, dim2=-1).square().prod(-1)
    largest = M.diagonal(dim1=-2, dim2=-1).amax(-1)
    easy = (info == 0) & (pivots > tol * (m * largest) ** m)
    inverse = torch.cholesky_solve(eye.expand_as(M), torch.where(easy.unsqueeze(-1).unsqueeze(-1), L, eye))
    hard = (~easy).nonzero(as_tuple=True)
    if hard[0].numel():
        hard_inverse, converged = _isolated_eigen_inverse(M[hard], tol)
        inverse = inverse.index_put(hard, hard_inverse)
        finite = finite.index_put(hard, finite[hard] & converged)
    return inverse, finite


def _active_rows(lqr: LQR) -> Tensor:
    """The terminal rows ``C_N (B, mN, nx)`` with the masked ones zero."""
    return lqr.CN * lqr.maskN.unsqueeze(-1) if lqr.maskN is not None else lqr.CN


def penalised(lqr: LQR, tol: float) -> tuple:
    """The unconstrained problem that :func:`factorize_range_space` factorises: ``lqr`` without its terminal rows
    (and its stage rows, of which there are none) and with the penalty ``Q_N + ρ Π`` (module docstring), ``ρ (B,)``
    ``PENALTY`` times the Hessian's largest entry (at least 1) and ``Π = C⁺ C`` the projector onto the rows' span,
    ``C⁺`` their pseudo-inverse at the rank tolerance (zero for an instance whose rows are not finite: its ``Σ``
    fails); and the multipliers' correction ``ρ C⁺ᵀ (B, mN, nx)``."""
    C = _active_rows(lqr)
    H = torch.cat([lqr.Q.flatten(1), lqr.R.flatten(1), lqr.S.flatten(1), lqr.QN.flatten(1)], -1)
    rho = (PENALTY * H.abs().amax(-1).clamp_min(1.0)).reshape(-1, 1, 1)
    finite = torch.isfinite(C).flatten(1).all(-1).reshape(-1, 1, 1)
    rows = torch.where(finite, C, 0.0)
    traced = torch.compiler.is_compiling()  # Inductor calls LAPACK's SVD once a matrix; rotations fuse in its loops
    pinv = jacobi.pinv(rows, tol) if by_rotations(rows) or traced else torch.linalg.pinv(rows, rtol=tol)
    projector = matmul(pinv, C.nan_to_num())
    return (dataclasses.replace(lqr, C=None, D=None, mask=None, CN=None, maskN=None, QN=lqr.QN + rho * projector),
            rho * _mT(pinv))


def _suffix_sums(T: Tensor) -> Tensor:
    """``Σ_{j ≥ k} T_j`` for every stage ``k`` of ``T (B, N, ...)``: a reversed cumulative sum, added in the same
    order stage by stage in a single instance's compiled graph, where ``cumsum`` would be a library call
    (:func:`~torchtraj.core.compiled.single_instance`)."""
    if not single_instance(T):
        return T.flip(1).cumsum(1).flip(1)
    sums = [T[:, -1]]
    for k in range(T.shape[1] - 2, -1, -1):
        sums.append(sums[-1] + T[:, k])
    return torch.stack(sums[::-1], 1)


def factorize_range_space(inner: RiccatiFactor, lqr: LQR, correction: Tensor, tol: float) -> RangeSpaceFactor:
    """The range-space factorisation (module docstring) of ``lqr`` (terminal rows ``CN``, ``maskN`` only) from the
    factorisation ``inner`` (either sweep, shifted as ``lqr`` is to be) of its :func:`penalised` problem and that
    problem's multiplier ``correction``, at the rank tolerance ``tol``."""
    C = _active_rows(lqr)
    lqr = dataclasses.replace(inner.lqr, CN=lqr.CN, maskN=lqr.maskN)
    A, Bu = lqr.A, lqr.B
    parallel = isinstance(inner, ParallelRiccatiFactor)
    Phi = A + matmul(Bu, inner.K)
    Pi = _reverse_chain(_mT(Phi), _mT(C), parallel)
    kh = -_cholesky_solve(matmul(_mT(Bu), Pi[:, 1:]), _stage_matrices(inner.chol))
    drive = matmul(Bu, kh)
    dxh = _forward_chain(Phi, drive, parallel)
    duh = kh + matmul(inner.K, dxh[:, :-1])
    lamh = Pi + matmul(inner.P, dxh)
    # −Σ_k = −Σ_{j ≥ k} T_j for the gains, all stages at once; −Σ_0 for the multipliers
    T = matmul(_mT(Pi[:, 1:]), drive).neg()
    sums = _suffix_sums(T)
    inverse, finite = _pseudo_inverse(sums[:, 0], tol)
    ok = inner.ok & finite & all_finite([kh, dxh])
    gains = TerminalGains(K=inner.K, kh=kh, Pi=Pi[:, :-1], sums=sums, tol=tol)
    return RangeSpaceFactor(inner=inner, lqr=lqr, gains=gains, P=inner.P, ok=ok, Pi=Pi, kh=kh, dxh=dxh, duh=duh,
                            lamh=lamh, inverse=inverse, penalty=correction)
