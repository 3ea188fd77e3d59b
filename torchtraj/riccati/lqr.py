r"""The data of a batched LQR problem: its matrices, its right-hand sides and the solution of one right-hand side.

The time-varying LQR problem of the package docstring (:mod:`torchtraj.riccati`), for each of B instances (every
tensor batch-first), is split into the matrices (:class:`LQR`), which one factorisation reads, and the vectors
(:class:`LQRVectors`), of which each solve takes one set: the adjoint system of implicit differentiation or a
second-order correction reuses the factorisation. The constraint rows may be switched off per instance by a mask, or
declared simple bounds on the controls (:mod:`torchtraj.riccati.bounds`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor


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

    def rows(self, index: Tensor) -> "LQR":
        """The instances ``index`` of the batch (a copy; ``bounds``, shared by the batch, stays), with their stacked
        blocks where the batch has them."""
        def take(a: Optional[Tensor]) -> Optional[Tensor]:
            return None if a is None else a[index]

        rows = {name: take(getattr(self, name)) for name in ("C", "D", "mask", "CN", "maskN", "root", "rootN")}
        if self.W is not None:
            return LQR.from_blocks(self.W[index], self.H[index], self.QN[index], bounds=self.bounds, **rows)
        return LQR(A=self.A[index], B=self.B[index], Q=self.Q[index], R=self.R[index], S=self.S[index],
                   QN=self.QN[index], bounds=self.bounds, **rows)

    @property
    def constrained(self) -> bool:
        return self.C is not None or self.CN is not None

    @property
    def propagated(self) -> bool:
        """Whether the rows take the constraint back-propagation (rows that are not declared ``bounds``)."""
        return self.constrained and self.bounds is None


def _views_of_blocks(lqr: LQR) -> bool:
    """Whether ``A`` … ``S`` of ``lqr`` are the blocks of its stacked ``W`` and ``H`` (:meth:`LQR.from_blocks`).
    Traced by ``torch.compile``, which cannot compare data pointers (a graph break in every kernel that makes an
    LQR), never: the blocks are stacked again, in the compiled kernel's fused loops."""
    if torch.compiler.is_compiling():
        return False
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

    ``g0 (B, nx)``: with back-propagated rows, the right-hand side of the rows ``G_0 δx_0 + g_0 = 0`` that no
    control satisfied and stage 0 hands to the initial state (``G_0`` is ``RiccatiFactor.stage[0].G``); a solver
    that optimises ``δx_0`` (Horizon eILQR §II-D) minimises ``V_0`` subject to them.
    """

    dx: Optional[Tensor]  # None: not asked for (RiccatiFactor.solve(forward=False))
    du: Optional[Tensor]
    k: Tensor
    p: Tensor
    dV1: Tensor
    dV2: Tensor
    costate: Optional[Tensor] = None
    nu: Optional[Tensor] = None
    nuN: Optional[Tensor] = None
    g0: Optional[Tensor] = None
