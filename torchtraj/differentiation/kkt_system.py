r"""The KKT system at a returned solution, with its active inequality rows held as equalities.

At a solution ``w = (X, U)`` of a batch instance with parameters ``θ = (x̄_0, p)``, the first-order (KKT)
conditions of the problem with its *active* inequality rows held as equalities read ``F(w, y, θ) = 0``:

.. math::

    \nabla_w \mathcal L(w, y, θ) = 0, \qquad c(w, θ) = 0,

with the Lagrangian (the sign conventions of :mod:`torchtraj.riccati` and
:func:`torchtraj.core.derivatives.problem_lagrangian_hessian`)

.. math::

    \mathcal L = \sum_{k<N} \big[\, l(z_k) + λ_{k+1}^T (f(z_k) - x_{k+1}) + ν_k^T h(z_k) + μ_k^T g_A(z_k) \big]
        + l_N(x_N) + ν_N^T h_N(x_N) + μ_N^T g_{N,A}(x_N) + λ_0^T (\bar x_0 - x_0),

``z_k = (x_k, u_k)``, all ``y = (λ, ν, μ)``. The constraints ``c`` are the initial condition, the dynamics, the
equalities and the active rows ``g_A`` of the inequalities. Its Jacobian in ``(w, y)`` is the symmetric KKT matrix
``K = [[∇²_w \mathcal L, ∂c/∂w^T], [∂c/∂w, 0]]``, which is the held-rows LQR of :mod:`torchtraj.kkt.newton` with
the Lagrangian Hessian: the batched Riccati core factorises it, no dense matrix is formed.

The multipliers ``y`` are computed here, not taken from the solver, so every method that returns a KKT point gets
the same gradients: at a KKT point, the Riccati solve of the constrained LQR problem with the cost gradient as
linear term and zero defects gives a (near) zero step and the multipliers as its dual part (with the cost Hessian;
the Hessian does not change the multipliers where the step is zero). The Lagrangian Hessian is then built with them.

Active set (:func:`active_rows`), identified once at the solver's point and then held fixed: an inequality row is
active where ``g > -active_tolerance``, or where the solver's multiplier of the row (``Solution.multipliers``, the
set ALTRO's projection identified) exceeds the row's slack ``-g`` and ``g > -1e3 active_tolerance``
(:func:`torchtraj.kkt.activity.by_multiplier_against_slack`). The default :func:`default_active_tolerance` is
``max(1e-6, 10⁴ ε)`` (``1e-6`` in float64, ``1.2e-3`` in float32). ALTRO's final projection leaves active rows at
``|g| ≲ 1e-8`` and inactive rows of a converged solve are far below ``-1e-6`` unless they are (weakly) active; a
weakly active row (zero multiplier) is held as an equality, which gives the one-sided derivative in which it stays
active. The signs of the multipliers are not checked: a row held with a negative multiplier (the optimum leaves the
bound) gives the derivative of the KKT point with the row held. Dropping such rows at the solver's point does not
repair a point that is not a KKT point (on the pendulum it leaves the reduced Hessian indefinite all the same, and
makes two more instances' indefinite), so refinement's stationarity test decides instead
(:mod:`torchtraj.differentiation.refine`).

Where the active rows are linearly dependent (LICQ fails, :func:`dependent_rows`: more active rows than the controls
can satisfy, rows left on ``δx_0``, or rows at round-off) the multipliers and, in general, the derivative are not
defined; :class:`KKTSystem` marks such instances ``degenerate``.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional

import torch
from torch import Tensor

from ..core.batching import map_stage, map_state
from ..core.constraints import Constraints
from ..core.derivatives import (
    Expansion,
    affine_stage_jacobian,
    problem_lagrangian_hessian,
    quadratic_stage_hessian,
    quadratize_cost,
    stage_jacobian,
    terminal_hessian,
    terminal_jacobian,
)
from ..core.graphs import graphed
from ..core.masks import where_rows
from ..core.problem import Problem
from ..kkt import activity
from ..kkt.newton import held_lqr, newton_rhs, without_offsets
from ..riccati import LQR, LQRVectors, RiccatiFactor, factorize


def default_active_tolerance(dtype: torch.dtype) -> float:
    """Rows with ``g > -tolerance`` are active: ``max(1e-6, 1e4 * eps)`` of ``dtype``."""
    return max(1e-6, 1e4 * float(torch.finfo(dtype).eps))


def constraints_of(problem: Problem, constrained: bool) -> Constraints:
    """The problem's constraints, none where the method ignores them (so do its KKT conditions)."""
    return Constraints.of(problem, ignored=not constrained)


def graphed_where_capturable(fn, cuda_graphs: bool, cons: Constraints):
    """``fn`` replayed from CUDA graphs where asked, unless the rows take the Riccati core's SVD (general rows held
    as equalities), which cannot be captured: then ``fn`` itself."""
    return graphed(fn) if cuda_graphs and not cons.back_propagated else fn


@dataclasses.dataclass
class Multipliers:
    """``costate (B, N+1, nx)``, stage rows ``nu (B, N, me+mi)`` and terminal rows ``nuN (B, meN+miN)``
    (equalities first, then inequalities; zero on inactive rows; ``None`` where there are no rows)."""

    costate: Tensor
    nu: Optional[Tensor]
    nuN: Optional[Tensor]

    def where(self, mask: Tensor, other: "Multipliers") -> "Multipliers":
        def pick(a, b):
            return None if a is None else where_rows(mask, a, b)

        return Multipliers(pick(self.costate, other.costate), pick(self.nu, other.nu), pick(self.nuN, other.nuN))


@dataclasses.dataclass
class KKTSystem:
    """The constrained LQR model of the KKT conditions at ``(X, U)``, batched over B.

    ``lqr`` holds the Lagrangian Hessian (built with ``multipliers``), the linearised dynamics and the
    constraint rows with the active ones unmasked; ``factor`` factorises it. ``newton`` is the
    right-hand side of a Newton step on the KKT conditions (cost gradient, defects
    ``f(x_k, u_k) − x_{k+1}``, initial-state defect, constraint values); ``ok (B,)`` marks the instances
    whose factorisations succeeded; ``degenerate (B,)`` those whose active rows are linearly dependent
    (:func:`dependent_rows`).
    """

    lqr: LQR
    factor: RiccatiFactor
    newton: LQRVectors
    multipliers: Multipliers
    ok: Tensor
    degenerate: Tensor


@dataclasses.dataclass
class Rows:
    """The constraint rows at ``(X, U)``, equalities first, then inequalities: stage ``values (B, N, m)``, Jacobians
    ``jacobian (B, N, m, nx+nu)`` and active ``mask (B, N, m)``; terminal ``valuesN (B, mN)``, ``jacobianN
    (B, mN, nx)``, ``maskN (B, mN)``; ``None`` where there are no rows. Inequality rows off at a knot have value 0
    and are never active."""

    values: Optional[Tensor] = None
    jacobian: Optional[Tensor] = None
    mask: Optional[Tensor] = None
    valuesN: Optional[Tensor] = None
    jacobianN: Optional[Tensor] = None
    maskN: Optional[Tensor] = None


def rows_at(cons: Constraints, X: Tensor, U: Tensor, params, tol: float, active: Optional[tuple] = None) -> Rows:
    """The :class:`Rows` at ``(X, U)``; ``active = (mask, maskN)`` imposes the masks, else an inequality row is
    active where ``g > -tol`` (:func:`torchtraj.kkt.activity.by_value`)."""
    vals, jacs, masks = [], [], []
    if cons.me:
        h, J = stage_jacobian(cons.stage_eq, X, U, params)
        vals.append(h), jacs.append(J), masks.append(torch.ones_like(h))
    if cons.mi:
        g, J = stage_jacobian(cons.stage_ineq, X, U, params)
        applies = cons.ineq_knot_mask > 0
        vals.append(torch.where(applies, g, torch.zeros_like(g))), jacs.append(J)
        masks.append((activity.by_value(g, tol) & applies).to(X.dtype))
    out = Rows()
    if vals:
        out.values, out.jacobian = torch.cat(vals, -1), torch.cat(jacs, -2)
        out.mask = torch.cat(masks, -1) if active is None else active[0]
    vals, jacs, masks = [], [], []
    if cons.meN:
        h, J = terminal_jacobian(cons.terminal_eq, X[:, -1], params)
        vals.append(h), jacs.append(J), masks.append(torch.ones_like(h))
    if cons.miN:
        g, J = terminal_jacobian(cons.terminal_ineq, X[:, -1], params)
        vals.append(g), jacs.append(J), masks.append(activity.by_value(g, tol).to(X.dtype))
    if vals:
        out.valuesN, out.jacobianN = torch.cat(vals, -1), torch.cat(jacs, -2)
        out.maskN = torch.cat(masks, -1) if active is None else active[1]
    return out


def active_rows(problem: Problem, X: Tensor, U: Tensor, params, constrained: bool = True,
                active_tolerance: Optional[float] = None, multipliers: Optional[Mapping[str, Tensor]] = None):
    """The active set ``(mask (B, N, me+mi), maskN (B, meN+miN))`` at a solution (``None`` without rows).

    Equalities are always active; an inequality row is active where ``g > −tol`` or, when the solver's
    ``multipliers`` (``Solution.multipliers``, by block) are given, where its multiplier exceeds the row's
    slack ``−g`` and ``g > −1e3 tol`` (the set an augmented-Lagrangian solver and ALTRO's projection
    identified; :func:`torchtraj.kkt.activity.by_multiplier_against_slack` says why against the slack).
    """
    cons = constraints_of(problem, constrained)
    tol = default_active_tolerance(X.dtype) if active_tolerance is None else active_tolerance
    B, N = U.shape[0], U.shape[1]
    multipliers = multipliers or {}
    ones = X.new_ones
    mask = maskN = None
    if cons.me or cons.mi:
        parts = [ones(B, N, cons.me)]
        if cons.mi:
            g = map_stage(cons.stage_ineq, X[:, :-1], U, params)
            dual = torch.cat([multipliers[name] if name in multipliers else torch.zeros_like(g[..., rows])
                              for name, rows in cons.ineq_blocks.items()], -1)
            on = activity.by_multiplier_against_slack(g, dual, tol)
            parts.append((on & (cons.ineq_knot_mask > 0)).to(X.dtype))
        mask = torch.cat(parts, -1)
    if cons.meN or cons.miN:
        parts = [ones(B, cons.meN)]
        if cons.miN:
            g = map_state(cons.terminal_ineq, X[:, -1], params)
            dual = multipliers.get("terminal_ineq", torch.zeros_like(g))
            parts.append(activity.by_multiplier_against_slack(g, dual, tol).to(X.dtype))
        maskN = torch.cat(parts, -1)
    return mask, maskN


def kkt_system(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params, constrained: bool = True,
               active_tolerance: Optional[float] = None, multipliers: Optional[Multipliers] = None,
               active: Optional[tuple] = None, gauss_newton: bool = False,
               need_multipliers: bool = True, cons: Optional[Constraints] = None) -> KKTSystem:
    """The factorised KKT system at ``X (B, N+1, nx)``, ``U (B, N, nu)`` from ``x0 (B, nx)``.

    ``params`` are batched to B. Without ``multipliers`` they are computed from the cost Hessian (one
    more factorisation, module docstring). ``active`` (from :func:`active_rows`) imposes the active
    set; else rows with ``g > -active_tolerance`` are active. With ``constrained=False`` the
    constraints are left out (the KKT conditions of the unconstrained problem, for methods that ignore
    constraints). ``gauss_newton``: the cost Hessian instead of the Lagrangian's (iLQR's model, the
    unrolled mode of :mod:`torchtraj.differentiation.layer`); its factorisation is the one that computes the
    multipliers. ``need_multipliers=False``: with the cost Hessian, where the caller takes the multipliers from a
    Newton step instead, they are not computed (zero), which saves a solve. ``cons``: the problem's constraints,
    made once by the caller (made here if not given).
    """
    cons = constraints_of(problem, constrained) if cons is None else cons
    tol = default_active_tolerance(X.dtype) if active_tolerance is None else active_tolerance
    if problem.linear_quadratic:
        f, fz, cost = _linear_quadratic_expansion(problem, X, U, params)
    else:
        f, fz = stage_jacobian(problem.dynamics, X, U, params)
        cost = quadratize_cost(problem.stage_cost, problem.terminal_cost, X, U, params)
    rows = rows_at(cons, X, U, params, tol, active)
    mask, maskN = rows.mask, rows.maskN

    def system(hessian: Tensor, hessianN: Tensor) -> LQR:
        # control bounds alone: the Riccati core holds the controls of the active rows (no back-propagation, no SVD)
        return held_lqr(fz, hessian, hessianN, rows.jacobian, mask, rows.jacobianN, maskN,
                        bounds=cons.bound_rows(), lower_only=True)

    lqr = system(cost.hessian, cost.terminal_hessian)
    newton = newton_rhs(cost.gradient, cost.terminal_gradient, f - X[:, 1:], x0 - X[:, 0], rows.values,
                        rows.valuesN)
    gradient = without_offsets(newton)  # whose solve at a KKT point gives the multipliers
    zeros = torch.zeros_like
    ok = torch.ones(X.shape[0], dtype=torch.bool, device=X.device)
    # of a linear-quadratic problem the cost Hessian is the Lagrangian's: one factorisation is exact
    gauss_newton = gauss_newton or problem.linear_quadratic
    first = factorize(lqr) if multipliers is None or gauss_newton else None  # of the cost Hessian
    if multipliers is None and gauss_newton and not need_multipliers:
        multipliers = Multipliers(zeros(X), None if rows.values is None else zeros(rows.values),
                                  None if rows.valuesN is None else zeros(rows.valuesN))
    elif multipliers is None:
        step = first.solve(gradient, multipliers=True)
        multipliers, ok = Multipliers(step.costate, step.nu, step.nuN), first.ok
    else:  # the rows' activity may have changed: a multiplier lives on active rows only
        multipliers = Multipliers(multipliers.costate, None if mask is None else multipliers.nu * mask,
                                  None if maskN is None else multipliers.nuN * maskN)
    if gauss_newton:
        return KKTSystem(lqr=lqr, factor=first, newton=newton, multipliers=multipliers, ok=ok & first.ok,
                         degenerate=dependent_rows(first) > 0.5)
    me, meN = cons.me, cons.meN
    nu, nuN = multipliers.nu, multipliers.nuN
    H, HN = problem_lagrangian_hessian(
        problem, cons, X, U, params, multipliers.costate,
        None if nu is None else nu[..., :me], None if nu is None else nu[..., me:],
        None if nuN is None else nuN[..., :meN], None if nuN is None else nuN[..., meN:])
    lqr = system(H, HN)
    factor = factorize(lqr)
    return KKTSystem(lqr=lqr, factor=factor, newton=newton, multipliers=multipliers, ok=ok & factor.ok,
                     degenerate=dependent_rows(factor) > 0.5)


def _linear_quadratic_expansion(problem: Problem, X: Tensor, U: Tensor, params):
    """``(f (B, N, nx), f_z (B, N, nx, nx+nu), the costs' Expansion)`` of a linear-quadratic problem
    (``Problem.linear_quadratic``): the derivatives at each instance's first stage, broadcast over the stages
    (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`)."""
    f, fz = affine_stage_jacobian(problem.dynamics, X, U, params)
    stage = quadratic_stage_hessian(problem.stage_cost, X, U, params)
    terminal = terminal_hessian(problem.terminal_cost, X[:, -1], params)
    return f, fz, Expansion(*stage, *terminal)


def dependent_rows(factor: RiccatiFactor) -> Tensor:
    """How many active constraint rows ``(B,)`` the constraint back-propagation of ``factor`` found
    linearly dependent on the others (LICQ fails where it is positive).

    At stage k the rows in play are the active stage rows and the rows kept from stage k+1; each either
    fixes a control direction (``inv_s ≠ 0``) or is kept as a row on ``δx_k``; the recursion drops a row
    whose singular value is at round-off, and rows still on ``δx_0`` depend on the initial condition.
    """
    lqr = factor.lqr
    B = lqr.A.shape[0]
    lost = lqr.A.new_zeros(B)
    if factor.fixed is not None:  # declared bounds: each active row holds one control, two rows one control twice
        return lqr.mask.sum((1, 2)) - factor.fixed.sum((1, 2))
    if factor.stage is None:
        return lost
    kept = factor.terminal.gmask.sum(-1)
    if lqr.CN is not None:
        lost = lost + lqr.maskN.sum(-1) - kept
    for t in range(lqr.A.shape[1] - 1, -1, -1):
        con = factor.stage[t]
        rows = kept + (lqr.mask[:, t].sum(-1) if lqr.C is not None else 0)
        kept = con.gmask.sum(-1)
        lost = lost + rows - (con.inv_s != 0).sum(-1).to(rows.dtype) - kept
    return lost + kept
