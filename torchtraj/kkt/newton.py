r"""The Newton step on the KKT conditions with some inequality rows held as equalities, as an LQR problem.

At ``w = (X, U)`` with multipliers ``y``, hold the equality rows ``h`` and the inequality rows ``g_A`` of an active
set ``A`` (:mod:`torchtraj.kkt.activity`) as equalities. A Newton step ``δw`` on the KKT conditions of that
equality-constrained problem solves

.. math::

    \begin{bmatrix} H & ∂c/∂w^T \\ ∂c/∂w & 0 \end{bmatrix}
    \begin{bmatrix} δw \\ y^+ \end{bmatrix} = -\begin{bmatrix} \nabla J \\ c \end{bmatrix},
    \qquad c = \big(\bar x_0 - x_0,\ f(z_k) - x_{k+1},\ h(z_k),\ g_A(z_k),\ h_N(x_N),\ g_{N,A}(x_N)\big),

with ``H`` the Hessian of the Lagrangian (or the cost's, iLQR's Gauss-Newton model, or one the caller
augments, the interior point's barrier terms). Stage by stage that is the equality-constrained LQR problem of the
shared Riccati core (:mod:`torchtraj.riccati`):

.. math::

    \min \sum_k \tfrac12 δz_k^T H_k δz_k + \nabla l_k^T δz_k + \tfrac12 δx_N^T H_N δx_N + \nabla l_N^T δx_N
    \ \text{s.t.}\ δx_{k+1} = A_k δx_k + B_k δu_k + (f_k - x_{k+1}),\ δx_0 = \bar x_0 - x_0,\
    C_k δx_k + D_k δu_k + e_k = 0 \ \text{(held rows)},

whose matrices :func:`held_lqr` builds and whose vectors :func:`newton_rhs` builds; :func:`newton_step` factorises
and solves it, the costates ``λ`` and the held rows' multipliers ``ν`` coming out of the same solve
(``multipliers=True``). Rows outside ``A`` are masked off, not removed, so one LQR serves every instance of a batch
whatever its set. With the cost gradient as linear term and zero offsets (:func:`without_offsets`) the step at a
KKT point is zero and the dual part is the multipliers; with a loss's cotangents it is the adjoint of implicit
differentiation (:mod:`torchtraj.differentiation.adjoint`).

Used by ALTRO's projection (Howell et al. 2019 §III-D, the objective's Hessian, feasibility steps), the implicit layer
(:mod:`torchtraj.differentiation`, refinement and the adjoint), the IPM's crossover
(:mod:`torchtraj.solvers.ipm.crossover`) and the IPM's reduced primal-dual system (FATROP eq. 9, barrier-augmented
Hessian, equality rows only).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..riccati import LQR, LQRSolution, LQRVectors, RiccatiFactor, factorize


def held_lqr(dynamics_jacobian: Tensor, hessian: Tensor, hessianN: Tensor, rows: Optional[Tensor] = None,
             mask: Optional[Tensor] = None, rowsN: Optional[Tensor] = None, maskN: Optional[Tensor] = None,
             bounds: Optional[Tensor] = None, lower_only: bool = False) -> LQR:
    """The LQR matrices of the KKT system with the rows of ``mask`` and ``maskN`` held.

    Args:
        dynamics_jacobian: ``f_z = [A B] (B, N, nx, nx+nu)``.
        hessian: ``(B, N, nx+nu, nx+nu)`` over ``z = (x, u)``: the cost's, the Lagrangian's or the caller's.
        hessianN: ``(B, nx, nx)``.
        rows: stage row Jacobians ``(B, N, m, nx+nu)``; ``None``: no stage rows. A block of zero rows is kept as
            one (the Riccati core then takes the constrained sweep, as ALTRO's projection always has).
        mask: ``(B, N, m)``, 1 on the held rows; ``None``: all held (equality rows).
        rowsN: terminal row Jacobians ``(B, mN, nx)``; ``None``: none.
        maskN: ``(B, mN)``; ``None``: all held.
        bounds: ``(m, nu)`` from :meth:`~torchtraj.core.constraints.Constraints.bound_rows`: the stage rows are
            control bounds, held by the Riccati core itself (no back-propagation, no SVD).
        lower_only: read the Hessian's cross block from its lower part only, ``S = H_ux`` and ``H_xu = Sᵀ``, as
            ALTRO's projection and the implicit layer always have; otherwise the stacked blocks are factorised as
            they are (:meth:`~torchtraj.riccati.LQR.from_blocks`: two copies instead of five strided ones). The
            two differ by round-off where ``hessian`` is not exactly symmetric (``jacrev`` of ``jacrev``).
    """
    nx = dynamics_jacobian.shape[-2]
    constraints = {}
    if rows is not None:
        constraints.update(C=rows[..., :nx], D=rows[..., nx:], bounds=bounds,
                           mask=rows.new_ones(rows.shape[:-1]) if mask is None else mask)
    if rowsN is not None:
        constraints.update(CN=rowsN, maskN=rowsN.new_ones(rowsN.shape[:-1]) if maskN is None else maskN)
    if not lower_only:
        return LQR.from_blocks(dynamics_jacobian, hessian, hessianN, **constraints)
    return LQR(A=dynamics_jacobian[..., :nx], B=dynamics_jacobian[..., nx:], Q=hessian[..., :nx, :nx],
               R=hessian[..., nx:, nx:], S=hessian[..., nx:, :nx], QN=hessianN, **constraints)


def newton_rhs(gradient: Tensor, gradientN: Tensor, defects: Tensor, initial: Tensor,
               values: Optional[Tensor] = None, valuesN: Optional[Tensor] = None) -> LQRVectors:
    """The right-hand side of the Newton step: the gradient ``(B, N, nx+nu)`` and ``gradientN (B, nx)`` (of the
    cost, or of the Lagrangian less the multipliers' terms where the solve gives the new multipliers themselves),
    the ``defects`` ``f(x_k, u_k) − x_{k+1} (B, N, nx)``, the ``initial`` defect ``x̄_0 − x_0 (B, nx)`` and the
    rows' ``values (B, N, m)``, ``valuesN (B, mN)`` (``None`` where there are no rows; off rows are masked by the
    LQR)."""
    nx = defects.shape[-1]
    return LQRVectors(q=gradient[..., :nx], r=gradient[..., nx:], qN=gradientN, c=defects, x0=initial, e=values,
                      eN=valuesN)


def without_offsets(rhs: LQRVectors) -> LQRVectors:
    """``rhs`` with zero defects, initial defect and row values: with the cost gradient, the solve whose dual part
    is the multipliers of a KKT point (its primal step is zero there); with a loss's cotangents, the adjoint."""
    zeros = torch.zeros_like
    return dataclasses.replace(rhs, c=zeros(rhs.c), x0=zeros(rhs.x0), e=None if rhs.e is None else zeros(rhs.e),
                               eN=None if rhs.eN is None else zeros(rhs.eN))


@dataclass
class NewtonStep:
    """A factorised KKT system and one solve: ``step.dx (B, N+1, nx)``, ``step.du (B, N, nu)`` and, with
    multipliers, ``step.costate (B, N+1, nx)``, ``step.nu (B, N, m)``, ``step.nuN (B, mN)`` (zero on off rows);
    ``factor.ok (B,)`` where the reduced Hessians were positive definite."""

    factor: RiccatiFactor
    step: LQRSolution


def newton_step(lqr: LQR, rhs: LQRVectors, regularization: Optional[Tensor] = None,
                rank_tolerance: Optional[float] = None, multipliers: bool = True,
                terminal_rows: str = "back-propagation") -> NewtonStep:
    """Factorise ``lqr`` (:func:`~torchtraj.riccati.factorize`, ``regularization (B,)`` on ``Q_uu`` for the gains,
    its ``terminal_rows``) and solve for ``rhs``, with the multipliers unless ``multipliers=False``."""
    factor = factorize(lqr, regularization, rank_tolerance=rank_tolerance, terminal_rows=terminal_rows)
    return NewtonStep(factor=factor, step=factor.solve(rhs, multipliers=multipliers))
