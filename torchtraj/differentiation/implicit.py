r"""Implicit differentiation of solutions: a solve is a differentiable layer.

At a returned solution ``w = (X, U)`` of a batch instance with parameters ``θ = (x̄_0, p)``, the
first-order (KKT) conditions of the problem with its *active* inequality rows held as equalities
read ``F(w, y, θ) = 0``:

.. math::

    \nabla_w \mathcal L(w, y, θ) = 0, \qquad c(w, θ) = 0,

with the Lagrangian (the sign conventions of :mod:`torchtraj.riccati` and
:func:`torchtraj.core.derivatives.problem_lagrangian_hessian`)

.. math::

    \mathcal L = \sum_{k<N} \big[\, l(z_k) + λ_{k+1}^T (f(z_k) - x_{k+1}) + ν_k^T h(z_k) + μ_k^T g_A(z_k) \big]
        + l_N(x_N) + ν_N^T h_N(x_N) + μ_N^T g_{N,A}(x_N) + λ_0^T (\bar x_0 - x_0),

``z_k = (x_k, u_k)``, all ``y = (λ, ν, μ)``. The constraints ``c`` are the initial condition, the
dynamics, the equalities and the active rows ``g_A`` of the inequalities. By the implicit function
theorem ``∂(w, y)/∂θ = -K^{-1} ∂F/∂θ`` with the symmetric KKT matrix
``K = [[∇²_w \mathcal L, ∂c/∂w^T], [∂c/∂w, 0]]``. For a loss with cotangents ``w̄ = (X̄, Ū)``
the reverse-mode product is therefore

.. math::

    \bar θ = (∂F/∂θ)^T s,\qquad K s = -\begin{bmatrix} \bar w \\ 0 \end{bmatrix}.

The system ``K s = -(w̄, 0)`` is exactly the KKT system of the equality-constrained LQR problem
with Hessian ``∇²\mathcal L`` (:func:`~torchtraj.core.derivatives.problem_lagrangian_hessian`), the
linearised dynamics, the active constraint rows as stagewise equalities (inactive rows masked
off), linear terms ``(q, r, q_N) = w̄`` and zero defects, initial state and constraint
offsets. It is solved by the batched Riccati core (:func:`torchtraj.riccati.factorize` and
:meth:`~torchtraj.riccati.RiccatiFactor.solve` with ``multipliers=True``), whose primal step and
multipliers are ``s`` — no dense KKT matrix is formed. The product ``(∂F/∂θ)^T s`` is
``∂/∂θ`` of the directional derivative of the Lagrangian along ``s``,

.. math::

    \bar θ = \nabla_θ \Big[ \sum_k \tfrac{d}{dε} \mathcal L_k(z_k + ε s_{z_k},\, y_k + ε s_{y_k}, θ)
        + \tfrac{d}{dε} \mathcal L_N(\dots) \Big]_{ε=0}, \qquad \bar x_0 = s_{λ_0},

evaluated with ``torch.func.jvp`` inside ``torch.func.vjp``, mapped over batch and time.

The multipliers ``y`` are computed here, not taken from the solver, so every method that returns a
KKT point gets the same gradients: at a KKT point, the Riccati solve of the constrained LQR problem
with the cost gradient as linear term and zero defects gives a (near) zero step and the multipliers
as its dual part (with the cost Hessian; the Hessian does not change the multipliers where the step
is zero). The Lagrangian Hessian is then built with them.

Refinement. The gradient is exact at an exact KKT point, but solvers stop at their tolerances, and
the line search of iLQR cannot resolve cost changes below round-off: controls are accurate only to
about ``sqrt(ε J / σ_min(∇²J))`` (``1e-5`` relative on the pendulum, whose control weight is
``6e-5``). So a differentiable solve first takes Newton (SQP) steps on the KKT conditions with the
active set held fixed — the same LQR system with the cost gradient, the dynamics defects and the
active constraint values as right-hand side — until the step reaches round-off
(:func:`refine`). From a converged solution they converge quadratically (on the pendulum: steps
``1e-3, 2e-7, 4e-14``; from ALTRO at reference accuracy, 0.13 short of the KKT point in ``U``:
``1e-1, …, 1e-14``), and the last factorisation is reused by the backward pass. A point is
differentiated only if it *is* a KKT point: the last Newton step, computed at the returned point, must
be at most ``default_stationarity_tolerance · (1 + |w|∞)`` (``1.5e-6`` relative in float64). A solver
that reports convergence by a cost-decrease test can stop far from one: ALTRO at its default
tolerances (``cost_tolerance = 1e-4``) stops on the pendulum 5-30 % above the optimal cost, ``|ΔU|∞ ≈ 5``
away, where the Newton steps are of size ``1e1 - 1e5`` and the Lagrangian Hessian (its costates
times the dynamics' curvature) makes the reduced Hessian indefinite over the bang-bang arcs. No
derivative describes such a point (a re-solve from it goes to the KKT point), so it gets none.

Active set (:func:`active_rows`), identified once at the solver's point and then held fixed: an
inequality row is active where ``g > -active_tolerance``, or where the solver's multiplier of the row
(``Solution.multipliers``, the set ALTRO's projection identified) exceeds the row's slack ``-g`` and
``g > -1e3 active_tolerance`` (not merely positive: an interior-point method's multipliers are
positive on every row, and ``z > s`` is its strict-complementarity test of activity). The default
:func:`default_active_tolerance` is ``max(1e-6, 10⁴ ε)`` (``1e-6`` in float64, ``1.2e-3`` in float32).
ALTRO's final projection leaves active rows at ``|g| ≲ 1e-8`` and inactive rows of a converged solve
are far below ``-1e-6`` unless they are (weakly) active; a weakly active row (zero multiplier) is
held as an equality, which gives the one-sided derivative in which it stays active. The set is not
re-evaluated during refinement (but a row a step would violate joins it, :func:`refine`): a Newton step from a point that is only ``1e-3`` stationary moves active rows of a curved constraint by
``~1e-6`` before the next step drives them back to zero. The signs of the multipliers are not
checked: a row held with a negative multiplier (the optimum leaves the bound) gives the derivative of
the KKT point with the row held. Dropping such rows at the solver's point does not repair a point that
is not a KKT point (on the pendulum above it leaves the reduced Hessian indefinite all the same, and
makes two more instances' indefinite), so the stationarity test below decides instead.

Instances get a **zero gradient**, and a ``RuntimeWarning`` names them with the reason, where

* they did not converge (``status != CONVERGED``; warned at the solve),
* their KKT system could not be factorised: a stage's reduced Hessian is not positive definite (the
  point is not a strict local minimum with its active set held: a saddle, or a solver that stopped
  short of a minimum), or non-finite values;
* their active rows are linearly dependent (LICQ fails, :func:`dependent_rows`: more active rows than
  the controls can satisfy, rows left on ``δx_0``, or rows at round-off), so that the multipliers and,
  in general, the derivative are not defined;
* refinement did not reach a KKT point (the stationarity test above; skipped with ``refine_steps=0``);
* the gradient is not finite;

(at the backward pass for all but the first); other instances of the batch are unaffected. Gradients
flow to ``x0`` and the tensors of ``Problem.params``; bounds, initial guesses and options get none.

Unrolled mode (``tt.solve(..., gradients="unrolled")``): the derivative of one final iLQR
(Gauss-Newton SQP) step taken at the solver's point with its active set held, the iterations before it
cut off (their iterate treated as a constant). The step solves ``M δ = -F(w, θ)`` with iLQR's model

.. math::

    M = \begin{bmatrix} \nabla^2_w \textstyle\sum_k l(z_k) + l_N & ∂c/∂w^T \\ ∂c/∂w & 0 \end{bmatrix},

the cost Hessian in place of the Lagrangian's (the multiplier-weighted curvature of the dynamics and
the constraint rows left out), so ``∂(w + δ)/∂θ = -M^{-1} ∂F/∂θ - (∂M^{-1}/∂θ) F``; at the solver's
point ``F ≈ 0`` and the second term is dropped. That is the formula above with ``K`` replaced by ``M``:
the same adjoint code with one factorisation of ``M``, no refinement, no Lagrangian Hessian (the
second derivatives of the dynamics, the dear part of an RK4 model's expansion). It is the gradient of
differentiating through the last LQR approximation (as mpc.pytorch does at its fixed point). It
equals the exact gradient where ``M = K``: linear dynamics and linear constraints with a quadratic
cost (the bench's ``linear_box``), up to the solver's tolerance, which is not refined away. It
disagrees wherever the dynamics or an active constraint is curved, by about ``‖M^{-1}(K - M)‖``
relative: ``python -m torchtraj.bench --grad --gradients unrolled`` reports its agreement with
finite differences on the pendulum next to the linear rows (README), and the tests measure both
sides. Only instances that did not converge get zero gradients; the others get the unrolled
derivative at whatever point the solver stopped.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Mapping, Optional

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable
from torch.func import grad, jvp, vmap

from ..core.batching import map_stage, map_state
from ..core.constraints import Constraints
from ..core.derivatives import (
    affine_stage_jacobian,
    linearize_dynamics,
    problem_lagrangian_hessian,
    quadratic_stage_hessian,
    quadratize_cost,
    stage_jacobian,
    terminal_hessian,
    terminal_jacobian,
)
from ..core.graphs import graphed
from ..core.problem import Problem
from ..core.solution import Solution
from ..core.status import Status
from ..kkt.model import total_cost
from ..riccati import LQR, LQRVectors, RiccatiFactor, factorize

#: How a differentiable solve differentiates (``tt.solve(..., gradients=...)``).
GRADIENT_MODES = ("implicit", "unrolled")


def check_gradients_mode(gradients: str) -> None:
    """A clear error for a ``gradients`` value not in :data:`GRADIENT_MODES`."""
    if gradients not in GRADIENT_MODES:
        raise ValueError(f"gradients must be one of {GRADIENT_MODES}, got {gradients!r}")


def default_active_tolerance(dtype: torch.dtype) -> float:
    """Rows with ``g > -tolerance`` are active: ``max(1e-6, 1e4 * eps)`` of ``dtype``."""
    return max(1e-6, 1e4 * float(torch.finfo(dtype).eps))


def default_stationarity_tolerance(dtype: torch.dtype) -> float:
    """A refined point whose Newton step is ``|δw|∞ ≤ tolerance · (1 + |w|∞)`` is a KKT point:
    ``1e2 sqrt(ε)`` of ``dtype`` (``1.5e-6`` in float64)."""
    return 1e2 * float(torch.finfo(dtype).eps) ** 0.5


def requires_gradients(x0: Tensor, params: Mapping[str, Tensor]) -> bool:
    """Whether a solve from ``x0`` with ``params`` must return differentiable ``X``, ``U``, ``cost``."""
    if not torch.is_grad_enabled():
        return False
    return x0.requires_grad or any(v.requires_grad for v in params.values())


# ----------------------------------------------------------------------------- linearisation
def _constraints(problem: Problem, constrained: bool) -> Constraints:
    """The problem's constraints, none where the method ignores them (so do its KKT conditions)."""
    return Constraints(problem, ignored=not constrained)


@dataclasses.dataclass
class Multipliers:
    """``costate (B, N+1, nx)``, stage rows ``nu (B, N, me+mi)`` and terminal rows ``nuN (B, meN+miN)``
    (equalities first, then inequalities; zero on inactive rows; ``None`` where there are no rows)."""

    costate: Tensor
    nu: Optional[Tensor]
    nuN: Optional[Tensor]

    def where(self, mask: Tensor, other: "Multipliers") -> "Multipliers":
        def pick(a, b):
            return None if a is None else torch.where(mask.reshape(-1, *([1] * (a.dim() - 1))), a, b)

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


def _rows(cons: Constraints, X: Tensor, U: Tensor, params, tol: float, active: Optional[tuple] = None):
    """Values, Jacobians and active masks of the stage rows ``(B, N, m)`` and terminal rows ``(B, mN)``.

    ``active = (mask, maskN)`` imposes the masks; else a row is active where ``g > -tol``.
    Returns ``(e, C, D, mask, eN, CN, maskN)``, ``None`` where there are no rows."""
    nx = X.shape[-1]
    vals, jacs, masks = [], [], []
    if cons.me:
        h, J = stage_jacobian(cons.stage_eq, X, U, params)
        vals.append(h), jacs.append(J), masks.append(torch.ones_like(h))
    if cons.mi:
        g, J = stage_jacobian(cons.stage_ineq, X, U, params)
        applies = cons.ineq_knot_mask > 0
        vals.append(torch.where(applies, g, torch.zeros_like(g))), jacs.append(J)
        masks.append(((g > -tol) & applies).to(X.dtype))
    e = C = D = mask = None
    if vals:
        J = torch.cat(jacs, -2)
        e, C, D, mask = torch.cat(vals, -1), J[..., :nx], J[..., nx:], torch.cat(masks, -1)
        mask = mask if active is None else active[0]
    vals, jacs, masks = [], [], []
    if cons.meN:
        h, J = terminal_jacobian(cons.terminal_eq, X[:, -1], params)
        vals.append(h), jacs.append(J), masks.append(torch.ones_like(h))
    if cons.miN:
        g, J = terminal_jacobian(cons.terminal_ineq, X[:, -1], params)
        vals.append(g), jacs.append(J), masks.append((g > -tol).to(X.dtype))
    eN = CN = maskN = None
    if vals:
        eN, CN, maskN = torch.cat(vals, -1), torch.cat(jacs, -2), torch.cat(masks, -1)
        maskN = maskN if active is None else active[1]
    return e, C, D, mask, eN, CN, maskN


def active_rows(problem: Problem, X: Tensor, U: Tensor, params, constrained: bool = True,
                active_tolerance: Optional[float] = None, multipliers: Optional[Mapping[str, Tensor]] = None):
    """The active set ``(mask (B, N, me+mi), maskN (B, meN+miN))`` at a solution (``None`` without rows).

    Equalities are always active; an inequality row is active where ``g > −tol`` or, when the solver's
    ``multipliers`` (``Solution.multipliers``, by block) are given, where its multiplier exceeds the row's
    slack ``−g`` and ``g > −1e3 tol`` (the set an augmented-Lagrangian solver and ALTRO's projection
    identified). Multiplier against slack, not multiplier against zero: an interior-point method's
    multipliers are positive on every row (``z s = μ``), and near a bound both are small, so only
    which of the two is larger tells an active row (``s ≈ μ / z``) from an inactive one (``z ≈ μ / s``);
    a fixed threshold on the multiplier held rows 1e-3 inside a bound with ``z ≈ 1e-6``, and refinement
    then moved ``linear_box`` instances 1e-3 away to a dearer point.
    """
    cons = _constraints(problem, constrained)
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
            on = (g > -tol) | ((dual > -g) & (g > -1e3 * tol))
            parts.append((on & (cons.ineq_knot_mask > 0)).to(X.dtype))
        mask = torch.cat(parts, -1)
    if cons.meN or cons.miN:
        parts = [ones(B, cons.meN)]
        if cons.miN:
            g = map_state(cons.terminal_ineq, X[:, -1], params)
            dual = multipliers.get("terminal_ineq", torch.zeros_like(g))
            parts.append(((g > -tol) | ((dual > -g) & (g > -1e3 * tol))).to(X.dtype))
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
    unrolled mode of the module docstring); its factorisation is the one that computes the multipliers.
    ``need_multipliers=False``: with the cost Hessian, where the caller takes the multipliers from a Newton step
    instead, they are not computed (zero), which saves a solve. ``cons``: the problem's constraints, made once by
    the caller (made here if not given).
    """
    cons = _constraints(problem, constrained) if cons is None else cons
    tol = default_active_tolerance(X.dtype) if active_tolerance is None else active_tolerance
    nx = X.shape[-1]
    if problem.linear_quadratic:
        f, A, Bm, lz, lzz, lNx, lNxx = _linear_quadratic_expansion(problem, X, U, params)
    else:
        f, A, Bm = linearize_dynamics(problem.dynamics, X, U, params)
        _, lz, lzz, _, lNx, lNxx = quadratize_cost(problem.stage_cost, problem.terminal_cost, X, U, params)
    e, C, D, mask, eN, CN, maskN = _rows(cons, X, U, params, tol, active)
    zeros = torch.zeros_like
    # control bounds alone: the Riccati core holds the controls of the active rows (no back-propagation, no SVD)
    lqr = LQR(A=A, B=Bm, Q=lzz[..., :nx, :nx], R=lzz[..., nx:, nx:], S=lzz[..., nx:, :nx], QN=lNxx,
              C=C, D=D, mask=mask, CN=CN, maskN=maskN, bounds=cons.bound_rows())
    gradient = LQRVectors(q=lz[..., :nx], r=lz[..., nx:], qN=lNx, c=zeros(X[:, 1:]), x0=zeros(x0),
                          e=None if e is None else zeros(e), eN=None if eN is None else zeros(eN))
    ok = torch.ones(X.shape[0], dtype=torch.bool, device=X.device)
    newton = dataclasses.replace(gradient, c=f - X[:, 1:], x0=x0 - X[:, 0], e=e, eN=eN)
    # of a linear-quadratic problem the cost Hessian is the Lagrangian's: one factorisation is exact
    gauss_newton = gauss_newton or problem.linear_quadratic
    first = factorize(lqr) if multipliers is None or gauss_newton else None  # of the cost Hessian
    if multipliers is None and gauss_newton and not need_multipliers:
        multipliers = Multipliers(zeros(X), None if e is None else zeros(e), None if eN is None else zeros(eN))
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
    lqr = dataclasses.replace(lqr, Q=H[..., :nx, :nx], R=H[..., nx:, nx:], S=H[..., nx:, :nx], QN=HN)
    factor = factorize(lqr)
    return KKTSystem(lqr=lqr, factor=factor, newton=newton, multipliers=multipliers, ok=ok & factor.ok,
                     degenerate=dependent_rows(factor) > 0.5)


def _linear_quadratic_expansion(problem: Problem, X: Tensor, U: Tensor, params):
    """:func:`linearize_dynamics` and :func:`quadratize_cost` of a linear-quadratic problem
    (``Problem.linear_quadratic``): the derivatives at each instance's first stage, broadcast over the stages
    (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`)."""
    nx = X.shape[-1]
    f, fz = affine_stage_jacobian(problem.dynamics, X, U, params)
    _, lz, lzz = quadratic_stage_hessian(problem.stage_cost, X, U, params)
    _, lNx, lNxx = terminal_hessian(problem.terminal_cost, X[:, -1], params)
    return f, fz[..., :nx], fz[..., nx:], lz, lzz, lNx, lNxx


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


# -------------------------------------------------------------------------------- refinement
def _violated_rows(cons: Constraints, X: Tensor, U: Tensor, params, active: tuple) -> tuple:
    """The inequality rows outside ``active = (mask, maskN)`` that are violated (``g > 0``) at
    ``(X, U)``: ``(the active set with them added, (B,) whether an instance has any)``."""
    mask, maskN = active
    violated = torch.zeros(X.shape[0], dtype=torch.bool, device=X.device)
    if cons.mi:
        g = map_stage(cons.stage_ineq, X[:, :-1], U, params)
        add = (mask[..., cons.me:] == 0) & (cons.ineq_knot_mask > 0) & (g > 0)
        mask = torch.cat([mask[..., :cons.me], mask[..., cons.me:] + add.to(mask.dtype)], -1)
        violated = violated | add.flatten(1).any(-1)
    if cons.miN:
        g = map_state(cons.terminal_ineq, X[:, -1], params)
        add = (maskN[..., cons.meN:] == 0) & (g > 0)
        maskN = torch.cat([maskN[..., :cons.meN], maskN[..., cons.meN:] + add.to(maskN.dtype)], -1)
        violated = violated | add.any(-1)
    return (mask, maskN), violated


@dataclasses.dataclass
class Refined:
    """Result of :func:`refine`: the point ``X``, ``U``, its ``multipliers``, the Newton ``steps (B,)``
    taken and the size of the last one computed (``residual (B,)``, ``|δw|∞``); ``stationary (B,)``
    where that is at most ``default_stationarity_tolerance · (1 + |w|∞)`` (the point is a KKT point of
    its active set); ``kkt`` is the KKT system at the point (within round-off), or ``None`` when the last
    steps were still large."""

    X: Tensor
    U: Tensor
    multipliers: Multipliers
    steps: Tensor
    residual: Tensor
    kkt: Optional[KKTSystem]
    active: tuple
    stationary: Tensor


def refine(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params, steps: int = 4, constrained: bool = True,
           active_tolerance: Optional[float] = None, mask: Optional[Tensor] = None,
           solver_multipliers: Optional[Mapping[str, Tensor]] = None, cuda_graphs: bool = False) -> Refined:
    """Newton (SQP) steps on the KKT conditions with the active set held fixed (module docstring).

    ``x0 (B, nx)``, ``X (B, N+1, nx)``, ``U (B, N, nu)``, ``params`` batched to B. The active set is
    :func:`active_rows` at the starting point (with the solver's multipliers, by block, when given) and
    is kept while the rows move: a Newton step drives active rows to zero. An inactive inequality row
    that a step would violate joins the active set instead, and the instance's step is computed again
    with it (an interior-point solution leaves the rows where a bound arc begins or ends at
    ``z ≈ s ≈ √μ``, which no test on ``z`` and ``s`` alone sorts: such a row is held once the step
    shows that it binds), at most ``steps`` times. A step of an instance is taken only if its KKT
    system factorised, and the step is finite, small (``|δw|∞ ≤ 1e-1 (1 + |w|∞)``), contracts
    (smaller than the instance's previous step) and leaves every inactive inequality row satisfied;
    otherwise the instance keeps its point and stops. An instance also stops once its step is at
    round-off (``|δw|∞ ≤ 1e3 ε (1 + |w|∞)``), or, of a linear-quadratic problem
    (``Problem.linear_quadratic``), once it has taken a step: the KKT conditions of an active set are then
    linear, and one step solves them. Only the instances in ``mask (B,)`` (default: all) move.
    ``cuda_graphs``: on a GPU, each step's system and solve are replayed from a CUDA graph (:mod:`torchtraj.core.graphs`),
    where the rows are control bounds alone or there are none.
    """
    cons = _constraints(problem, constrained)
    B = X.shape[0]
    # of a linear-quadratic problem the KKT conditions of an active set are linear: one step solves them
    exact = problem.linear_quadratic
    moving = torch.ones(B, dtype=torch.bool, device=X.device) if mask is None else mask.clone()
    previous = X.new_full((B,), float("inf"))
    taken = torch.zeros(B, dtype=torch.long, device=X.device)
    eps = float(torch.finfo(X.dtype).eps)

    def expand(t, like):
        return t.reshape(B, *([1] * (like.dim() - 1)))

    multipliers = None
    active = active_rows(problem, X, U, params, constrained, active_tolerance, solver_multipliers)
    joined = torch.zeros(B, dtype=torch.long, device=X.device)  # rounds in which an instance's set grew
    step = _graphed_where_capturable(_newton_step, cuda_graphs, cons)
    for _ in range(2 * max(steps, 1)):
        kkt, s = step(problem, cons, x0, X, U, params, constrained, active_tolerance, multipliers, active,
                      not exact)
        size = torch.maximum(s.dx.abs().flatten(1).amax(-1), s.du.abs().flatten(1).amax(-1))
        scale = 1 + torch.maximum(X.abs().flatten(1).amax(-1), U.abs().flatten(1).amax(-1))
        Xn, Un = X + s.dx, U + s.du
        candidate = moving & kkt.ok & torch.isfinite(size) & (size <= 1e-1 * scale) & (size < previous)
        violated = grew = torch.zeros_like(candidate)
        if cons.mi or cons.miN:
            more, violated = _violated_rows(cons, Xn, Un, params, (kkt.lqr.mask, kkt.lqr.maskN))
            grew = violated & candidate & (joined < steps)
            active = tuple(None if m is None else torch.where(expand(grew, m), a, m)
                           for m, a in zip((kkt.lqr.mask, kkt.lqr.maskN), more))
            joined = joined + grew.long()
        take = candidate & ~violated
        if steps == 0:
            take = torch.zeros_like(take)
        X, U = torch.where(expand(take, X), Xn, X), torch.where(expand(take, U), Un, U)
        multipliers = Multipliers(s.costate, s.nu, s.nuN).where(take, kkt.multipliers)
        previous = torch.where(take, size, previous)
        taken = taken + take.long()
        # where a step was taken, kkt is stale by that step: fine at round-off, else go on; where
        # rows joined, the step is computed again
        moving = (take & (size > 1e3 * eps * scale) & (not exact)) | grew
        # a step that was not taken was computed at the instance's point: it measures the distance to
        # the KKT point of the active set (a taken one, from the previous point, overestimates it)
        stationary = kkt.ok & ((size <= default_stationarity_tolerance(X.dtype) * scale) | (take & exact)) & ~grew
        if not bool(moving.any()):
            return Refined(X, U, multipliers, taken, size, kkt, active, stationary)
    return Refined(X, U, multipliers, taken, size, None, active, stationary)


def _graphed_where_capturable(fn, cuda_graphs: bool, cons: Constraints):
    """``fn`` replayed from CUDA graphs where asked, unless the rows take the Riccati core's SVD (general rows held
    as equalities), which cannot be captured: then ``fn`` itself."""
    return graphed(fn) if cuda_graphs and not cons.back_propagated else fn


def _newton_step(problem: Problem, cons: Constraints, x0: Tensor, X: Tensor, U: Tensor, params, constrained: bool,
                 active_tolerance: Optional[float], multipliers: Optional[Multipliers], active: tuple,
                 need_multipliers: bool) -> tuple:
    """``(kkt, step)``: :func:`refine`'s KKT system at ``(X, U)`` and its Newton step, with the multipliers."""
    kkt = kkt_system(problem, x0, X, U, params, constrained, active_tolerance, multipliers, active,
                     need_multipliers=need_multipliers, cons=cons)
    return kkt, kkt.factor.solve(kkt.newton, multipliers=True)


# ------------------------------------------------------------------------------ the adjoint
def _lagrangians(problem: Problem, cons: Constraints):
    """Per-instance stage and terminal Lagrangians ``L_k(x, u, y, p)``, ``L_N(x, y, p)``,
    ``y = (λ_{k+1}, ν_k, μ_k)`` and ``y_N = (ν_N, μ_N)``."""
    nx, me, meN = problem.nx, cons.me, cons.meN

    def stage(x, u, y, p):
        out = problem.stage_cost(x, u, p) + (y[:nx] * problem.dynamics(x, u, p)).sum()
        if me:
            out = out + (y[nx:nx + me] * cons.stage_eq(x, u, p)).sum()
        if cons.mi:
            out = out + (y[nx + me:] * cons.stage_ineq(x, u, p)).sum()
        return out

    def terminal(x, y, p):
        out = problem.terminal_cost(x, p)
        if meN:
            out = out + (y[:meN] * cons.terminal_eq(x, p)).sum()
        if cons.miN:
            out = out + (y[meN:] * cons.terminal_ineq(x, p)).sum()
        return out

    return stage, terminal


def _stacked(m: Multipliers):
    """Stage ``(B, N, nx + m)`` (``λ_{k+1}`` first) and terminal ``(B, mN)`` multiplier vectors."""
    y = m.costate[:, 1:] if m.nu is None else torch.cat([m.costate[:, 1:], m.nu], -1)
    yN = m.costate.new_zeros(m.costate.shape[0], 0) if m.nuN is None else m.nuN
    return y, yN


def parameter_gradients(problem: Problem, cons: Constraints, X: Tensor, U: Tensor, params: dict,
                        y: Multipliers, s: tuple) -> dict:
    """``(∂F/∂p)^T s`` for every parameter: ``{name: (B, *shape)}``.

    ``y`` are the multipliers at ``(X, U)``; ``s = (sX, sU, sy)`` the adjoint (``sy`` multipliers in the
    same layout). ``params`` are batched to B.
    """
    stage, terminal = _lagrangians(problem, cons)

    def stage_dir(x, u, yk, sx, su, syk, p):
        return jvp(lambda x_, u_, y_: stage(x_, u_, y_, p), (x, u, yk), (sx, su, syk))[1]

    def terminal_dir(x, yk, sx, syk, p):
        return jvp(lambda x_, y_: terminal(x_, y_, p), (x, yk), (sx, syk))[1]

    sX, sU, sy = s
    (yk, yN), (syk, syN) = _stacked(y), _stacked(sy)
    per_stage = vmap(vmap(stage_dir, in_dims=(0, 0, 0, 0, 0, 0, None)))
    per_terminal = vmap(terminal_dir)

    def total(p):
        out = per_stage(X[:, :-1], U, yk, sX[:, :-1], sU, syk, p).sum()
        return out + per_terminal(X[:, -1], yN, sX[:, -1], syN, p).sum()

    return grad(total)(params)


def backward_solve(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params: dict, X_bar: Tensor,
                   U_bar: Tensor, constrained: bool = True, active_tolerance: Optional[float] = None,
                   kkt: Optional[KKTSystem] = None, multipliers: Optional[Multipliers] = None,
                   active: Optional[tuple] = None, gauss_newton: bool = False,
                   cons: Optional[Constraints] = None):
    """Gradients ``(x0_bar (B, nx), {name: (B, *shape)}, kkt)`` of a loss with cotangents
    ``X_bar (B, N+1, nx)``, ``U_bar (B, N, nu)`` at the solution ``(X, U)`` from ``x0 (B, nx)``.

    ``params`` are batched to B; ``kkt``, ``multipliers`` and the ``active`` set at ``(X, U)`` are reused
    when given (from :func:`refine`). ``kkt`` is returned too: ``kkt.ok`` is False where the KKT system
    could not be factorised, ``kkt.degenerate`` where its active rows are linearly dependent.
    ``gauss_newton``: the adjoint of iLQR's model instead of the KKT matrix (unrolled mode). ``cons``: the
    problem's constraints, made once by the caller (made here if not given).
    """
    cons = _constraints(problem, constrained) if cons is None else cons
    if kkt is None:
        kkt = kkt_system(problem, x0, X, U, params, constrained, active_tolerance, multipliers, active,
                         gauss_newton, cons=cons)
    multipliers = kkt.multipliers if multipliers is None else multipliers
    zeros = torch.zeros_like
    rhs = LQRVectors(q=X_bar[:, :-1], r=U_bar, qN=X_bar[:, -1], c=zeros(X[:, 1:]), x0=zeros(x0),
                     e=None if kkt.newton.e is None else zeros(kkt.newton.e),
                     eN=None if kkt.newton.eN is None else zeros(kkt.newton.eN))
    s = kkt.factor.solve(rhs, multipliers=True)
    sy = Multipliers(s.costate, s.nu, s.nuN)
    p_bar = parameter_gradients(problem, cons, X, U, params, multipliers, (s.dx, s.du, sy)) if params else {}
    return s.costate[:, 0], p_bar, kkt


def _adjoint(problem: Problem, cons: Constraints, x0: Tensor, X: Tensor, U: Tensor, params: dict, X_bar: Tensor,
             U_bar: Tensor, constrained: bool, active_tolerance: Optional[float], kkt: Optional[KKTSystem],
             multipliers: Optional[Multipliers], active: Optional[tuple], gauss_newton: bool) -> tuple:
    """:func:`backward_solve` as the backward pass uses it: ``(x0_bar, p_bar, kkt.ok, kkt.degenerate)``."""
    x0_bar, p_bar, kkt = backward_solve(problem, x0, X, U, params, X_bar, U_bar, constrained, active_tolerance, kkt,
                                        multipliers, active, gauss_newton, cons)
    return x0_bar, p_bar, kkt.ok, kkt.degenerate


# --------------------------------------------------------------------------- the autograd layer
@dataclasses.dataclass(frozen=True, eq=False)
class _Spec:
    """What the backward pass needs besides the saved tensors."""

    problem: Problem
    names: tuple
    usable: Tensor  # (B,) bool: instances that converged
    stationary: Tensor  # (B,) bool: instances refined to a KKT point (all True without refinement)
    constrained: bool
    active_tolerance: Optional[float]
    refined: Optional[Refined]
    gauss_newton: bool = False  # the unrolled mode (module docstring)
    cuda_graphs: bool = False  # the adjoint replayed from a CUDA graph (attach_gradients)


class ImplicitSolution(torch.autograd.Function):
    """``(X, U)`` of a solved batch as a function of ``(x0, *params)``; the backward pass is
    :func:`backward_solve` (the implicit function theorem on the KKT conditions)."""

    @staticmethod
    def forward(spec: _Spec, X: Tensor, U: Tensor, x0: Tensor, *params: Tensor):
        return X.clone(), U.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        spec, X, U, x0, *params = inputs
        ctx.spec = spec
        ctx.save_for_backward(X, U, x0, *params)

    @staticmethod
    @once_differentiable
    def backward(ctx, X_bar: Tensor, U_bar: Tensor):
        spec: _Spec = ctx.spec
        X, U, x0, *values = ctx.saved_tensors
        params = dict(zip(spec.names, values))
        refined = spec.refined
        cons = _constraints(spec.problem, spec.constrained)
        adjoint = _graphed_where_capturable(_adjoint, spec.cuda_graphs, cons)
        x0_bar, p_bar, ok, dependent = adjoint(
            spec.problem, cons, x0, X, U, params, X_bar.contiguous(), U_bar.contiguous(), spec.constrained,
            spec.active_tolerance, None if refined is None else refined.kkt,
            None if refined is None else refined.multipliers, None if refined is None else refined.active,
            spec.gauss_newton)
        B = X.shape[0]
        finite = torch.isfinite(x0_bar).all(-1)
        for v in p_bar.values():
            finite = finite & torch.isfinite(v.reshape(B, -1)).all(-1)
        # one reason per instance, the first that applies (module docstring)
        unfactorised = spec.usable & ~ok
        degenerate = spec.usable & ok & dependent
        not_kkt = spec.usable & ok & ~dependent & ~spec.stationary
        keep = spec.usable & ok & ~dependent & spec.stationary & finite
        non_finite = spec.usable & ~keep & ~unfactorised & ~degenerate & ~not_kkt
        reasons = [(unfactorised, "the KKT system could not be factorised (reduced Hessian not positive "
                                  "definite: not a strict local minimum with the active set held, often a "
                                  "solver stopped short of one; tighter solver tolerances help)"),
                   (degenerate, "the active constraint rows are linearly dependent (LICQ fails: more active "
                                "rows than the controls can satisfy, or rows at round-off)"),
                   (not_kkt, "the point is not a KKT point (Newton refinement with the active set held "
                             "could not reach stationarity: the solver stopped short of a solution; "
                             "tighter solver tolerances help)"),
                   (non_finite, "the gradient is not finite")]
        for bad, why in reasons:
            if bool(bad.any()):
                warnings.warn(f"implicit gradients: instance(s) {_indices(bad)}: {why}; their gradients are "
                              "zero", RuntimeWarning, stacklevel=2)

        def masked(g):
            return torch.where(keep.reshape(B, *([1] * (g.dim() - 1))), g, torch.zeros_like(g))

        grads = [masked(p_bar[n]) if ctx.needs_input_grad[4 + i] else None for i, n in enumerate(spec.names)]
        x0_grad = masked(x0_bar) if ctx.needs_input_grad[3] else None
        return (None, None, None, x0_grad, *grads)


def _indices(mask: Tensor) -> list:
    return torch.nonzero(mask).reshape(-1).tolist()


def _violation(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params) -> Tensor:
    """Largest constraint violation (as every method reports it), dynamics and initial-state defect ``(B,)``."""
    defect = (map_stage(problem.dynamics, X[:, :-1], U, params) - X[:, 1:]).abs().flatten(1).amax(-1)
    defect = torch.maximum(defect, (x0 - X[:, 0]).abs().amax(-1))
    return torch.maximum(defect, Constraints(problem).max_violation(X, U, params))


def attach_gradients(problem: Problem, x0: Tensor, params: Mapping[str, Tensor], solution: Solution,
                     refine_steps: int = 4, active_tolerance: Optional[float] = None,
                     gradients: str = "implicit", cuda_graphs: bool = False, constrained: bool = True) -> Solution:
    """``solution`` with ``X``, ``U`` and ``cost`` differentiable with respect to ``x0`` and ``params``.

    Args:
        problem: the solved problem.
        x0: ``(B, nx)`` initial states, possibly requiring grad.
        params: the problem's parameters batched to B (``Problem.batched_params``), possibly requiring grad.
        solution: the method's result, computed from detached ``x0`` and ``params``.
        refine_steps: at most this many Newton steps of :func:`refine` on the converged instances before
            differentiating (0: differentiate at the solver's point as it is).
        active_tolerance: inequality rows with ``g > -active_tolerance`` are held active;
            default :func:`default_active_tolerance`.
        gradients: ``"implicit"`` (exact, this module) or ``"unrolled"`` (the derivative of a final
            iLQR step at the solver's point, unrefined: module docstring).
        cuda_graphs: on a GPU, replay refinement's Newton steps and the backward pass's adjoint solve from
            CUDA graphs (:mod:`torchtraj.core.graphs`; ``tt.solve`` passes :func:`~torchtraj.core.graphs.graphs_used`), where
            the constraint rows are control bounds alone or there are none (the Riccati core's SVD of general
            rows cannot be captured).
        constrained: whether the solution is a KKT point of the constrained problem; ``False`` for a method that
            ignores the constraints, whose KKT conditions are then the unconstrained ones.

    Instances whose status is not ``CONVERGED`` get zero gradients (and are not refined); a
    ``RuntimeWarning`` names them. So do, at the backward pass, instances that refinement could not
    bring to a KKT point, and those whose KKT system is not factorisable or degenerate (module
    docstring). ``max_violation`` is re-evaluated at the refined point.
    """
    check_gradients_mode(gradients)
    unrolled = gradients == "unrolled"
    refine_steps = 0 if unrolled else refine_steps
    usable = solution.status == Status.CONVERGED
    if not bool(usable.all()):
        warnings.warn(f"implicit gradients: instance(s) {_indices(~usable)} did not converge (status "
                      f"{Status.describe(solution.status[~usable])}); their gradients will be zero",
                      RuntimeWarning, stacklevel=3)
    x0_d = x0.detach()
    detached = {k: v.detach() for k, v in params.items()}
    X, U = solution.X.detach(), solution.U.detach()
    violation, refined = solution.max_violation, None
    if refine_steps > 0 and bool(usable.any()):
        refined = refine(problem, x0_d, X, U, detached, refine_steps, constrained, active_tolerance, usable,
                         {k: v.detach() for k, v in solution.multipliers.items()}, cuda_graphs)
        X, U = refined.X, refined.U
        violation = torch.where(usable, _violation(problem, x0_d, X, U, detached), violation)
    names = tuple(params)
    stationary = torch.ones_like(usable) if refined is None else refined.stationary
    spec = _Spec(problem=problem, names=names, usable=usable, stationary=stationary, constrained=constrained,
                 active_tolerance=active_tolerance, refined=refined, gauss_newton=unrolled, cuda_graphs=cuda_graphs)
    X, U = ImplicitSolution.apply(spec, X, U, x0, *(params[n] for n in names))
    cost = total_cost(problem, X, U, params)
    # where an instance gets no gradient, its cost gets none either (not even the explicit ∂l/∂p)
    keep = usable.to(cost.dtype)
    cost = keep * cost + (1 - keep) * cost.detach()
    return dataclasses.replace(solution, X=X, U=U, cost=cost, max_violation=violation)
