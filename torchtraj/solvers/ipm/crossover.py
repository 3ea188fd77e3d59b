r"""Active-set crossover: the interior-point method's last iterations replaced by one exact solve.

ALTRO solves to a coarse tolerance and then, "once the active inequality constraints are known", switches to an
active-set Newton projection for a precise answer (Howell et al. 2019 §III-D). For a problem whose dynamics and
constraints are affine in ``w = (X, U)`` and whose costs are quadratic (``Problem.linear_quadratic``) that switch
is exact: with a set ``A`` of inequality rows held as equalities, the KKT conditions

.. math::

    \nabla J(w) + \nabla c(w)^T y = 0, \qquad c(w) = 0,\qquad
    c = (\text{dynamics},\ \text{initial state},\ h,\ g_A)

are linear, and one Newton step from any point, the equality-constrained LQR problem of the shared Riccati core
(:mod:`torchtraj.riccati`) with the cost gradient as linear term, the defects and the row values as affine terms,
lands on their solution ``(w_A, y_A)``: the costates ``λ``, the equality multipliers ``ν`` and the multipliers
``y_{A}`` of the held rows come out of the same solve. That point is optimal for the problem exactly when the
rows outside ``A`` hold there (``g ≤ 0``) and the held rows' multipliers are not negative, and it is the problem's
KKT point to round-off, however loose the iterate it started from.

The interior-point iterate proposes ``A``: the rows whose multiplier exceeds their slack, ``z > s`` (near a
solution an active row has ``s ≈ μ/z → 0`` and an inactive one ``z ≈ μ/s → 0``: the strict-complementarity
indicator). The candidate is accepted by the interior-point method's own convergence test, ``E_0 ≤ tol`` at the
primal-dual point with slacks ``s = max(−g, 0)``, multipliers ``z = max(y, 0)`` on the held rows and zero
elsewhere: a row outside ``A`` that the candidate violates leaves a primal residual ``g + s = g``, a negative
multiplier a dual residual ``y − z``, and the test also reads every stationarity and feasibility residual. Where
it fails, the instance goes on with its interior-point iterate, unchanged, and tries again at a later one; the
reduced Hessian must also be positive definite (``RiccatiFactor.ok``), so that ``w_A`` is a strict minimiser
with ``A`` held.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...core.derivatives import multiplier_terms
from ...kkt import activity
from ...kkt.newton import held_lqr as _held_lqr
from ...kkt.newton import newton_rhs, newton_step
from ...riccati import LQR, LQRVectors
from .iterate import Iterate, Model


def proposed_active_set(it: Iterate, knots: Tensor) -> tuple:
    """``(stage (B, N, mi), terminal (B, miN))``: 1 on the inequality rows whose multiplier exceeds their slack
    (:func:`torchtraj.kkt.activity.multiplier_exceeds_slack`)."""
    return ((activity.multiplier_exceeds_slack(it.z, it.s) & (knots > 0)).to(it.s.dtype),
            activity.multiplier_exceeds_slack(it.zN, it.sN).to(it.s.dtype))


def first_active_set(it: Iterate, knots: Tensor, start: bool) -> tuple:
    """The set a crossover's first round holds: none at the ``start`` (the unconstrained optimum), else the
    :func:`proposed_active_set`."""
    active = proposed_active_set(it, knots)
    return tuple(torch.zeros_like(a) for a in active) if start else active


def held_lqr(model: Model, cons: Constraints, active: Tensor, activeN: Tensor) -> LQR:
    """The LQR matrices of the KKT system (:func:`torchtraj.kkt.newton.held_lqr`) with the equality rows and the rows
    of ``active`` held: the Lagrangian Hessian (the cost's, the problem being linear-quadratic), the dynamics'
    Jacobians, the rows ``[h; g]`` (``[h_N; g_N]`` at the end), and the control bounds held by the core itself where
    they are the only rows."""
    rows = torch.cat([model.Hz, model.Gz], -2)
    rowsN = torch.cat([model.HN, model.GN], -2)
    stage, terminal = {}, {}
    if rows.shape[-2]:
        stage = dict(rows=rows, mask=torch.cat([torch.ones_like(model.h), active], -1), bounds=cons.bound_rows())
    if rowsN.shape[-2]:
        terminal = dict(rowsN=rowsN, maskN=torch.cat([torch.ones_like(model.hN), activeN], -1))
    return _held_lqr(model.fz, model.Lzz, model.LNxx, **stage, **terminal)


def held_rhs(model: Model, it: Iterate, x0: Tensor) -> LQRVectors:
    """The right-hand side (:func:`torchtraj.kkt.newton.newton_rhs`) whose solve gives the new point and the
    multipliers themselves (not their steps): the cost gradient (the Lagrangian's, less the multipliers' terms), the
    defects and the rows' values."""
    stage, terminal = multiplier_terms(model.fz, model.Hz, model.Gz, model.HN, model.GN, it.lam[:, 1:], it.nu, it.y,
                                       it.nuN, it.yN)
    e = torch.cat([model.h, model.g], -1)
    eN = torch.cat([model.hN, model.gN], -1)
    return newton_rhs(model.Lz - stage, model.LNx - terminal, model.f - it.X[:, 1:], x0 - it.X[:, 0],
                      e if e.shape[-1] else None, eN if eN.shape[-1] else None)


@dataclass
class Candidate:
    """The KKT point of the held set: the new ``point`` (slacks and multipliers as the module docstring sets them),
    the feedback gains ``K (B, N, nu, nx)`` of the held system and ``ok (B,)``, whether its reduced Hessians were
    positive definite."""

    point: Iterate
    K: Tensor
    ok: Tensor


def candidate(model: Model, cons: Constraints, it: Iterate, x0: Tensor,
              active: Optional[tuple] = None) -> Candidate:
    """One Newton step onto the KKT point of the rows ``active`` (default :func:`proposed_active_set`) held."""
    knots = model.knots
    active, activeN = proposed_active_set(it, knots) if active is None else active
    solved = newton_step(held_lqr(model, cons, active, activeN), held_rhs(model, it, x0))
    factor, sol = solved.factor, solved.step
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    rows = sol.nu if sol.nu is not None else it.s.new_zeros(*it.s.shape[:2], me + it.s.shape[-1])
    rowsN = sol.nuN if sol.nuN is not None else it.sN.new_zeros(it.sN.shape[0], meN + it.sN.shape[-1])
    y, yN = rows[..., me:] * active, rowsN[..., meN:] * activeN
    dw = torch.cat([sol.dx[:, :-1], sol.du], -1)
    g = (model.g + _mv(model.Gz, dw)) * knots  # the rows are affine: their values at the new point
    gN = model.gN + _mv(model.GN, sol.dx[:, -1])
    # rows off at a knot keep a unit slack, as the initial iterate gives them
    s = torch.where(knots > 0, torch.clamp(-g, min=0.0), 1.0)

    point = Iterate(X=it.X + sol.dx, U=it.U + sol.du, s=s, sN=torch.clamp(-gN, min=0.0), z=y.clamp_min(0.0),
                    zN=yN.clamp_min(0.0), y=y, yN=yN, lam=sol.costate, nu=rows[..., :me], nuN=rowsN[..., :meN])
    return Candidate(point=point, K=factor.K, ok=factor.ok)


def next_active_set(c: Candidate, active: tuple, knots: Tensor) -> tuple:
    """The primal-dual active-set update of a candidate (Hintermüller, Ito & Kunisch 2002,
    :func:`torchtraj.kkt.activity.primal_dual_update`): a held row stays where its multiplier is positive, a free
    one joins where the candidate violates it, ``y + g > 0`` (held rows have ``g = 0``, free ones ``y = 0``)."""
    p = c.point
    stage = activity.primal_dual_update(active[0], p.y, p.s, knots > 0).to(p.y.dtype)
    terminal = activity.primal_dual_update(active[1], p.yN, p.sN).to(p.y.dtype)
    return stage, terminal


def changed(active: tuple, following: tuple) -> Tensor:
    """``(B,)``: whether the active sets differ."""
    return (active[0] != following[0]).flatten(1).any(-1) | (active[1] != following[1]).flatten(1).any(-1)
