r"""The projection's last part: Newton (SQP) steps on the KKT conditions of the held rows, with the Lagrangian
Hessian, which make the projected point stationary as well as feasible.

The projection (§III-D, :mod:`torchtraj.solvers.altro.projection`) moves the coarse AL-iLQR point onto the held rows
``d(w) = 0`` along the least ``H``-norm step, ``H`` the cost Hessian, and takes the least-squares multipliers of the
point it reaches. That removes the violations but not the stationarity error: the steps are made without the cost
gradient, and at a curved constraint (nonlinear dynamics) the multipliers of a solve with the cost Hessian alone
are off by the curvature term ``Σ_i y_i ∇²d_i`` times the distance to the KKT point. On the 2-D quadrotor the
AL stage ends at stationarity 1.4e-7 with its estimate ``λ + I_μ c`` (eq. 17), the projection moves the controls by
6e-5 to meet violations of 1.8e-7, and the least-squares multipliers leave stationarity 2.4e-6 (scaled as
:mod:`torchtraj.kkt.certificate` scales it), above the certificate's 1e-6: ``STALLED``.

With the active set ``A`` of the projection held, the KKT conditions ``∇J(w) + ∇d(w)ᵀ y = 0``, ``d(w) = 0`` are a
smooth system, and Newton's method on it,

.. math::

    \begin{bmatrix} ∇²_{ww} L(w, y) & ∇d(w)^T \\ ∇d(w) & 0 \end{bmatrix}
    \begin{bmatrix} δw \\ y^+ \end{bmatrix} = -\begin{bmatrix} ∇J(w) \\ d(w) \end{bmatrix},
    \qquad L = J + y^T d,

(the held-rows LQR of :mod:`torchtraj.kkt.newton`, the Lagrangian Hessian from the current multipliers: costates
times the dynamics' curvature, row multipliers times the rows') converges quadratically from the projected point:
on the quadrotor stationarity 2.4e-6, 2e-10, 2e-13 in two steps. With the cost Hessian alone (a Gauss-Newton
model) the same steps do not converge there (1.7e-7, 1.7e-7, 2.0e-7, …): the curvature term is what is missing.

The loop (:func:`torchtraj.solvers.altro.projection.project`) follows each step by the projection's feasibility
steps (a second-order correction) and keeps it per instance only where the system factorised and the KKT error
(:func:`kkt_error`: the largest of the certificate's residuals, stationarity, feasibility of every row and the
dynamics, complementarity, the multipliers' sign) goes down without the violation growing past the tolerance.
Where a step would violate a free row or leaves a held inequality with a negative multiplier, the held set is
updated instead and the step computed again. Instances stop at a step of round-off size.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ...core.compiled import unplanned_single
from ...core.constraints import multiplier_blocks
from ...core.derivatives import problem_lagrangian_hessian, quadratize_cost, stage_jacobian
from ...core.masks import where_rows
from ...kkt.certificate import residuals
from ...kkt.newton import held_lqr, newton_rhs, newton_step
from .augmented_lagrangian import AugmentedLagrangian

#: A step below ``ROUND_OFF · ε · (1 + |w|∞)`` is at round-off: the instance stops.
ROUND_OFF = 1e3


@dataclass
class KKTPoint:
    """A point and its multipliers in the stacked layout of
    :class:`~torchtraj.solvers.altro.augmented_lagrangian.AugmentedLagrangian`: ``costate (B, N+1, nx)``,
    ``stage (B, N, m)``, ``terminal (B, mN)`` (zero off the held rows) and the gains ``K (B, N, nu, nx)`` of the
    held-rows system."""

    X: Tensor
    U: Tensor
    costate: Tensor
    stage: Tensor
    terminal: Tensor
    K: Tensor

    def where(self, mask: Tensor, other: "KKTPoint") -> "KKTPoint":
        """``self`` for the instances in ``mask (B,)``, ``other`` elsewhere."""
        return KKTPoint(*(where_rows(mask, a, b) for a, b in zip(
            (self.X, self.U, self.costate, self.stage, self.terminal, self.K),
            (other.X, other.U, other.costate, other.stage, other.terminal, other.K))))


def kkt_error(al: AugmentedLagrangian, params, x0: Tensor, point: KKTPoint):
    """``(error (B,), violation (B,))`` at ``point``: the largest of the certificate's residuals
    (:func:`torchtraj.kkt.certificate.residuals`) and its feasibility residual alone; NaN counts as infinite."""
    blocks = multiplier_blocks(al.constraints, point.stage, point.terminal)
    r = residuals(al.problem, point.X, point.U, blocks, params, x0, al.constraints)
    error = torch.stack([r.stationarity, r.feasibility, r.complementarity, r.dual_sign], -1).amax(-1)
    infinite = float("inf")
    return torch.nan_to_num(error, nan=infinite), torch.nan_to_num(r.feasibility, nan=infinite)


@unplanned_single
def newton_kkt_step(al: AugmentedLagrangian, params, x0: Tensor, point: KKTPoint, stage_active: Tensor,
                    terminal_active: Tensor, regularization: Tensor, rank_tolerance: float):
    """``(the point after one Newton step, |δw|∞ (B,), ok (B,))``: the step of the module docstring from
    ``point``, with the rows of ``stage_active (B, N, m)`` and ``terminal_active (B, mN)`` held; ``ok`` where the
    system factorised and the step is finite."""
    problem, constraints = al.problem, al.constraints
    X, U = point.X, point.U
    mi, miN = constraints.mi, constraints.miN
    H, HN = problem_lagrangian_hessian(problem, constraints, X, U, params, point.costate,
                                       nu=point.stage[..., mi:], mu=point.stage[..., :mi],
                                       nuN=point.terminal[..., miN:], muN=point.terminal[..., :miN])
    cost = quadratize_cost(problem.stage_cost, problem.terminal_cost, X, U, params)
    f, fz = stage_jacobian(problem.dynamics, X, U, params)
    c, Cz, cN, CN = al.row_jacobians(X, U, params)
    c = c * al.knot_mask * stage_active if al.m else c
    cN = cN * terminal_active
    lqr = held_lqr(fz, H, HN, rows=Cz, mask=stage_active, rowsN=CN, maskN=terminal_active, lower_only=True)
    # the cost gradient as linear term: the dual part of the solve is the new multipliers themselves
    solved = newton_step(lqr, newton_rhs(cost.gradient, cost.terminal_gradient, f - X[:, 1:], x0 - X[:, 0], c, cN),
                         regularization, rank_tolerance)
    factor, step = solved.factor, solved.step
    moved = KKTPoint(X + step.dx, U + step.du, step.costate, step.nu * stage_active, step.nuN * terminal_active,
                     factor.K)
    size = torch.maximum(step.dx.abs().flatten(1).amax(-1), step.du.abs().flatten(1).amax(-1))
    return moved, size, factor.ok & torch.isfinite(size)
