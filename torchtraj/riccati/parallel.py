r"""The parallel-in-time Riccati sweep: the LQR's backward and forward passes as associative scans, O(log N) deep.

Following Särkkä & García-Fernández, "Temporal parallelization of dynamic programming and linear quadratic
control" (IEEE TAC 2023, arXiv 2104.03186, §IV), the cost of going from ``x`` at stage ``i`` to ``y`` at stage
``j`` optimally, the conditional value function, is kept in the form

.. math::  V_{i\to j}(x, y) = \tfrac12 x^T J x - \eta^T x
           + \max_\lambda \big[\lambda^T (y - A x - b) - \tfrac12 \lambda^T C \lambda\big] + \text{const},

an element ``(A, b, C, η, J)``. One stage with ``x_{k+1} = A_k x + B_k u + c_k`` and the stage cost of the package
docstring is such an element once its control is minimised out for given end points: with ``u = w − R^{-1}(S x +
r)``,

.. math::  A_e = A - B R^{-1} S,\quad b_e = c - B R^{-1} r,\quad C_e = B R^{-1} B^T,\quad
           J_e = Q - S^T R^{-1} S,\quad \eta_e = S^T R^{-1} r - q,

and the terminal cost is the element ``(0, 0, 0, −q_N, Q_N)``. Minimising over the middle point joins two
elements, earlier ``1`` and later ``2`` (the paper's Lemma 8):

.. math::  A_{12} &= A_2 (I + C_1 J_2)^{-1} A_1, &\quad C_{12} &= A_2 (I + C_1 J_2)^{-1} C_1 A_2^T + C_2,\\
           J_{12} &= A_1^T (I + J_2 C_1)^{-1} J_2 A_1 + J_1, &\quad
           \eta_{12} &= A_1^T (I + J_2 C_1)^{-1} (\eta_2 - J_2 b_1) + \eta_1,

an associative operation: the reverse scan (:mod:`~torchtraj.riccati.parallel_scan`) of the stage elements and the
terminal one gives, at every ``k``, the value function's Hessian ``P_k = J_{k→N}`` in ``⌈log₂(N+1)⌉`` levels. The
gains then follow for all stages in one batched call, ``K_k = −Q_{uu}^{-1} Q_{ux}`` from ``P_{k+1}``.

A right-hand side's value-function gradients obey the affine recursion (the exact minimiser makes
``Q_uu k_k + Q_u = 0``) ``p_k = (A_k + B_k K_k)^T (P_{k+1} c_k + p_{k+1}) + q_k + K_k^T r_k``, ``p_N = q_N``, and
the step the closed-loop one ``δx_{k+1} = (A_k + B_k K_k) δx_k + B_k k_k + c_k``: both are scans of affine maps
(the paper's §V). Only the vector part ``b, η`` of the elements therefore never needs scanning.

Held bounds (:mod:`~torchtraj.riccati.bounds`): with ``F`` the free controls and ``h`` the held ones' values,
``u = F v + h`` turns the stage into one with ``R̃ = F R F + I − F``, ``S̃ = F S``, ``B̃ = B F``, ``r̃ = F (r + R h)``,
``q̃ = q + S^T h``, ``c̃ = c + B h``: the held controls are eliminated stage by stage before the elements are built,
and the gains are those of the sequential sweep, ``K = −(F Q_uu F + I − F)^{-1} F Q_ux``.

Differences from the sequential sweep (:func:`~torchtraj.riccati.factorize`):

- the elements need each stage's (reduced) control Hessian ``R̃`` positive definite, where the sequential sweep
  needs only ``Q_uu``: an instance where some ``R̃`` is not is flagged not ``ok``;
- ``ρ`` (``regularization``) is a proximal term ``½ ρ |δu|²`` of the problem, in the gains *and* the value
  function: the sequential sweep's value function along the regularised gains
  (``P = Q_xx + K^T Q_ux − ρ K^T K``) is not the value function of any LQR and has no associative form. At
  ``ρ = 0`` both give the same step to round-off.
- constraint rows that take the back-propagation (``LQR.propagated``) have no parallel form here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..core.compiled import matmul as _mm
from ..core.compiled import matvec as _mv
from .bounds import _bound_multipliers, _held_controls, _held_values
from .factor import RiccatiFactor
from .linalg import _cholesky, _cholesky_solve, _factored_solve, _mT, _sym
from .lqr import LQR, LQRSolution, LQRVectors
from .parallel_scan import affine_scan, associative_scan
from .sanitize import _sanitize_stacked, all_finite

SWEEPS = ("sequential", "parallel", "auto")


def choose_sweep(lqr: LQR, sweep: str) -> str:
    """``"sequential"`` or ``"parallel"``: the sweep that :func:`~torchtraj.riccati.factorize` runs for ``sweep``.

    ``"auto"`` takes the parallel sweep where it applies (no back-propagated rows) and where it was measured to
    win: on a CUDA device from ``N ≥ 16``; on CPU where the horizon is long against the batch,
    ``N ≥ 32`` and ``B · log₂ N ≤ 8 N`` (both sweeps timed on one core, ``nx = 4``, ``nu = 2``: the parallel sweep
    saves the sequential one's per-stage dispatch, but does ``log₂ N`` times its arithmetic)."""
    if sweep not in SWEEPS:
        raise ValueError(f"sweep must be one of {', '.join(SWEEPS)}, not {sweep!r}")
    if sweep == "sequential":
        return sweep
    if lqr.propagated:
        if sweep == "parallel":
            raise ValueError("the parallel Riccati sweep takes no back-propagated constraint rows (LQR.C, D, CN "
                             "without LQR.bounds): use sweep='sequential' or 'auto'")
        return "sequential"
    if sweep == "parallel":
        return sweep
    Bsz, N = lqr.B.shape[0], lqr.B.shape[1]
    if lqr.B.device.type == "cuda":
        return "parallel" if N >= 16 else "sequential"
    depth = max(N - 1, 1).bit_length()
    return "parallel" if N >= 32 and Bsz * depth <= 8 * N else "sequential"


@dataclass
class ParallelRiccatiFactor(RiccatiFactor):
    """A :class:`RiccatiFactor` from :func:`factorize_parallel`; its :meth:`solve` runs the two affine scans.

    ``closed_loop (B, N, nx, nx)``: ``A_k + B_k K_k``. ``Quu``, ``Qux`` are the unregularised Q-function blocks
    and ``chol`` the Cholesky factor of the reduced, regularised ``F (Q_uu + ρI) F + I − F``, as the sequential
    sweep's."""

    closed_loop: Optional[Tensor] = None

    def solve(self, rhs: LQRVectors, multipliers: bool = False) -> LQRSolution:
        """Solve the LQR problem for ``rhs``: the gradients ``p`` by a reverse affine scan, the feedforward of all
        stages at once, the step by a forward affine scan."""
        lqr, K, Phi = self.lqr, self.K, self.closed_loop
        P_next = self.P[:, 1:]
        held = _held_values(self.fixed, lqr, rhs)
        c, q, r = rhs.c, rhs.q, rhs.r
        if held is not None:  # the held controls' values moved into the stage's vectors
            c_held = c + _mv(lqr.B, held)
            q_held = q + _mv(_mT(lqr.S), held)
            r_held = r + _mv(lqr.R, held)
        else:
            c_held, q_held, r_held = c, q, r
        g = q_held + _mv(_mT(K), r_held) + _mv(_mT(Phi), _mv(P_next, c_held))
        p_head = affine_scan(_mT(Phi), g, rhs.qN, reverse=True)
        p = torch.cat([p_head, rhs.qN.unsqueeze(1)], 1)
        Qu = r + _mv(_mT(lqr.B), _mv(P_next, c) + p[:, 1:])
        if held is not None:
            grad = (Qu + _mv(self.Quu, held)) * (1.0 - self.fixed)
            k = held - _cholesky_solve(grad.unsqueeze(-1), self.chol).squeeze(-1)
        else:
            k = -_cholesky_solve(Qu.unsqueeze(-1), self.chol).squeeze(-1)
        dV1 = (k * Qu).sum((1, 2))
        dV2 = 0.5 * (k * _mv(self.Quu, k)).sum((1, 2))
        x_tail = affine_scan(Phi, _mv(lqr.B, k) + c, rhs.x0)
        dx = torch.cat([rhs.x0.unsqueeze(1), x_tail], 1)
        du = _mv(K, dx[:, :-1]) + k
        out = LQRSolution(dx=dx, du=du, k=k, p=p, dV1=dV1, dV2=dV2)
        if multipliers:
            self._parallel_multipliers(rhs, out, Qu)
        return out

    def _parallel_multipliers(self, rhs: LQRVectors, out: LQRSolution, Qu: Tensor) -> None:
        """The held rows' ``ν`` (all stages at once) and the costates: ``λ_k = P_k δx_k + p_k`` where the gains
        are exact, else the reverse scan of ``λ_k = A_k^T λ_{k+1} + Q_k δx_k + S_k^T δu_k + q_k``."""
        lqr, dx, du = self.lqr, out.dx, out.du
        if self.fixed is not None:
            out.nu = _bound_multipliers(lqr, self.fixed, self.Quu, self.Qux, dx, du, Qu)
        if self.exact:
            out.costate = _mv(self.P, dx) + out.p
            return
        last = _mv(lqr.QN, dx[:, -1]) + rhs.qN
        g = _mv(lqr.Q, dx[:, :-1]) + _mv(_mT(lqr.S), du) + rhs.q
        head = affine_scan(_mT(lqr.A), g, last, reverse=True)
        out.costate = torch.cat([head, last.unsqueeze(1)], 1)


def _stage_elements(lqr: LQR, rho: Optional[Tensor], held: Optional[Tensor]):
    """The stages' ``(A_e, C_e, J_e)`` (each ``(B, N, nx, nx)``) with the held controls eliminated, and the
    ``info (B, N)`` of the Cholesky factorisation of the reduced ``R̃`` (0 where positive definite)."""
    nx = lqr.A.shape[-1]
    R, S, Bu = lqr.R, lqr.S, lqr.B
    if rho is not None:
        R = R + rho
    if held is not None:
        free = 1.0 - held
        R = R * free.unsqueeze(-1) * free.unsqueeze(-2) + torch.diag_embed(held)
        S = S * free.unsqueeze(-1)
        Bu = Bu * free.unsqueeze(-2)
    L, info = _cholesky(R)
    Y = _cholesky_solve(torch.cat([S, _mT(Bu)], -1), L)  # R̃⁻¹ [S̃, B̃ᵀ]
    A = lqr.A - _mm(Bu, Y[..., :nx])
    C = _sym(_mm(Bu, Y[..., nx:]))
    J = _sym(lqr.Q - _mm(_mT(S), Y[..., :nx]))
    return A, C, J, info


def _join(earlier, later):
    """The matrix part ``(A, C, J)`` of ``earlier ⊗ later`` (module docstring), for all pairs of a level."""
    A1, C1, J1 = earlier
    A2, C2, J2 = later
    nx = A1.shape[-1]
    eye = torch.eye(nx, dtype=A1.dtype, device=A1.device)
    # (I + C1 J2)⁻¹ [A1, C1] in one solve; (I + J2 C1)⁻¹ = (I + C1 J2)⁻ᵀ gives J's factor from the same one
    T = torch.linalg.solve_ex(eye + _mm(C1, J2), torch.cat([A1, C1], -1))[0]
    TA, TC = T[..., :nx], T[..., nx:]
    A12 = _mm(A2, TA)
    C12 = _sym(_mm(_mm(A2, TC), _mT(A2))) + C2
    J12 = _sym(_mm(_mT(TA), _mm(J2, A1))) + J1
    return A12, C12, J12


def factorize_parallel(lqr: LQR, regularization: Optional[Tensor] = None,
                       shift: Optional[Tensor] = None) -> ParallelRiccatiFactor:
    """The parallel-in-time factorisation of ``lqr`` (module docstring); arguments as
    :func:`~torchtraj.riccati.factorize`, whose ``sweep="parallel"`` calls it. ``regularization ρ (B,)`` is a
    proximal term on the controls here (module docstring)."""
    if lqr.propagated:
        raise ValueError("the parallel Riccati sweep takes no back-propagated constraint rows")
    exact = regularization is None
    lqr, finite, W, Hs = _sanitize_stacked(lqr, shift)
    Bsz, N, nx, nu = lqr.B.shape
    dtype = lqr.A.dtype
    held = _held_controls(lqr, dtype) if lqr.bounds is not None else None
    rho = None
    if regularization is not None:
        rho = regularization.reshape(Bsz, 1, 1, 1) * torch.eye(nu, dtype=dtype, device=lqr.A.device)
    A, C, J, info_R = _stage_elements(lqr, rho, held)
    zero = lqr.QN.new_zeros(Bsz, 1, nx, nx)
    elements = (torch.cat([A, zero], 1), torch.cat([C, zero], 1), torch.cat([J, lqr.QN.unsqueeze(1)], 1))
    _, _, P = associative_scan(elements, _join, reverse=True)
    # every stage's Q-function from P_{k+1} in one batched congruence, as the sequential sweep's H + Wᵀ P W
    Wb, Hb = W.transpose(0, 1), Hs.transpose(0, 1)
    H = Hb + _mm(_mT(Wb), _mm(P[:, 1:], Wb))
    Quu, Qux = _sym(H[..., nx:, nx:]), H[..., nx:, :nx]
    Hu = Quu if rho is None else Quu + rho
    if held is not None:
        free = 1.0 - held
        Hu = Hu * free.unsqueeze(-1) * free.unsqueeze(-2) + torch.diag_embed(held)
        Qux_free = Qux * free.unsqueeze(-1)
    else:
        Qux_free = Qux
    L, info = _cholesky(Hu)
    K = -_factored_solve(Hu, L, info, Qux_free)
    ok = finite & (info == 0).all(1) & (info_R == 0).all(1) & all_finite([P])
    return ParallelRiccatiFactor(
        lqr=lqr, K=K, P=P, ok=ok, Quu=Quu, Qux=Qux, chol=L, free=None, stage=None, terminal=None, exact=exact,
        fixed=held, closed_loop=lqr.A + _mm(lqr.B, K),
    )
