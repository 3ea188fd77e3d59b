r"""Newton refinement of a solver's point onto the KKT point of its active set, before it is differentiated.

The gradient of :mod:`torchtraj.differentiation.adjoint` is exact at an exact KKT point, but solvers stop at their
tolerances, and the line search of iLQR cannot resolve cost changes below round-off: controls are accurate only to
about ``sqrt(ε J / σ_min(∇²J))`` (``1e-5`` relative on the pendulum, whose control weight is ``6e-5``). So a
differentiable solve first takes Newton (SQP) steps on the KKT conditions ``F(w, y) = 0`` with the active set held
fixed,

.. math::

    K(w, y) \begin{bmatrix} δw \\ y^+ \end{bmatrix} = -\begin{bmatrix} \nabla J(w) \\ c(w) \end{bmatrix},

the held-rows LQR of :mod:`torchtraj.kkt.newton` with the Lagrangian Hessian, the cost gradient, the dynamics
defects and the active constraint values as right-hand side, whose dual part is the new multipliers ``y⁺``, until
the step reaches round-off (:func:`refine`). From a converged solution they converge quadratically (on the
pendulum: steps ``1e-3, 2e-7, 4e-14``; from ALTRO at reference accuracy, 0.13 short of the KKT point in ``U``:
``1e-1, …, 1e-14``), and the last factorisation is reused by the backward pass.

A point is differentiated only if it *is* a KKT point: the last Newton step, computed at the returned point, must be
at most ``default_stationarity_tolerance · (1 + |w|∞)`` (``1.5e-6`` relative in float64). A solver that reports
convergence by a cost-decrease test can stop far from one: ALTRO at its default tolerances
(``cost_tolerance = 1e-4``) stops on the pendulum 5-30 % above the optimal cost, ``|ΔU|∞ ≈ 5`` away, where the
Newton steps are of size ``1e1 - 1e5`` and the Lagrangian Hessian (its costates times the dynamics' curvature)
makes the reduced Hessian indefinite over the bang-bang arcs. No derivative describes such a point (a re-solve from
it goes to the KKT point), so it gets none.

The active set is not re-evaluated during refinement: a Newton step from a point that is only ``1e-3`` stationary
moves active rows of a curved constraint by ``~1e-6`` before the next step drives them back to zero. But a row a
step would violate joins it (:func:`torchtraj.kkt.activity.violated`).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional

import torch
from torch import Tensor

from ..core.batching import map_stage, map_state
from ..core.constraints import Constraints
from ..core.masks import where_rows
from ..core.problem import Problem
from ..kkt import activity
from .kkt_system import KKTSystem, Multipliers, active_rows, constraints_of, graphed_where_capturable, kkt_system


def default_stationarity_tolerance(dtype: torch.dtype) -> float:
    """A refined point whose Newton step is ``|δw|∞ ≤ tolerance · (1 + |w|∞)`` is a KKT point:
    ``1e2 sqrt(ε)`` of ``dtype`` (``1.5e-6`` in float64)."""
    return 1e2 * float(torch.finfo(dtype).eps) ** 0.5


def _violated_rows(cons: Constraints, X: Tensor, U: Tensor, params, active: tuple) -> tuple:
    """The inequality rows outside ``active = (mask, maskN)`` that are violated (``g > 0``) at
    ``(X, U)``: ``(the active set with them added, (B,) whether an instance has any)``."""
    mask, maskN = active
    violated = torch.zeros(X.shape[0], dtype=torch.bool, device=X.device)
    if cons.mi:
        g = map_stage(cons.stage_ineq, X[:, :-1], U, params)
        add = activity.violated(mask[..., cons.me:], g) & (cons.ineq_knot_mask > 0)
        mask = torch.cat([mask[..., :cons.me], mask[..., cons.me:] + add.to(mask.dtype)], -1)
        violated = violated | add.flatten(1).any(-1)
    if cons.miN:
        g = map_state(cons.terminal_ineq, X[:, -1], params)
        add = activity.violated(maskN[..., cons.meN:], g)
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
    :func:`~torchtraj.differentiation.kkt_system.active_rows` at the starting point (with the solver's multipliers,
    by block, when given) and is kept while the rows move: a Newton step drives active rows to zero. An inactive
    inequality row that a step would violate joins the active set instead, and the instance's step is computed again
    with it (an interior-point solution leaves the rows where a bound arc begins or ends at
    ``z ≈ s ≈ √μ``, which no test on ``z`` and ``s`` alone sorts: such a row is held once the step
    shows that it binds), at most ``steps`` times. A step of an instance is taken only if its KKT
    system factorised, and the step is finite, small (``|δw|∞ ≤ 1e-1 (1 + |w|∞)``), contracts
    (smaller than the instance's previous step) and leaves every inactive inequality row satisfied;
    otherwise the instance keeps its point and stops. An instance also stops once its step is at
    round-off (``|δw|∞ ≤ 1e3 ε (1 + |w|∞)``), or, of a linear-quadratic problem
    (``Problem.linear_quadratic``), once it has taken a step: the KKT conditions of an active set are then
    linear, and one step solves them. Only the instances in ``mask (B,)`` (default: all) move.
    ``cuda_graphs``: on a GPU, each step's system and solve are replayed from a CUDA graph
    (:mod:`torchtraj.core.graphs`), where the rows are control bounds alone or there are none.
    """
    cons = constraints_of(problem, constrained)
    B = X.shape[0]
    # of a linear-quadratic problem the KKT conditions of an active set are linear: one step solves them
    exact = problem.linear_quadratic
    moving = torch.ones(B, dtype=torch.bool, device=X.device) if mask is None else mask.clone()
    previous = X.new_full((B,), float("inf"))
    taken = torch.zeros(B, dtype=torch.long, device=X.device)
    eps = float(torch.finfo(X.dtype).eps)

    multipliers = None
    active = active_rows(problem, X, U, params, constrained, active_tolerance, solver_multipliers)
    joined = torch.zeros(B, dtype=torch.long, device=X.device)  # rounds in which an instance's set grew
    step = graphed_where_capturable(_newton_step, cuda_graphs, cons)
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
            active = tuple(None if m is None else where_rows(grew, a, m)
                           for m, a in zip((kkt.lqr.mask, kkt.lqr.maskN), more))
            joined = joined + grew.long()
        take = candidate & ~violated
        if steps == 0:
            take = torch.zeros_like(take)
        X, U = where_rows(take, Xn, X), where_rows(take, Un, U)
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


def _newton_step(problem: Problem, cons: Constraints, x0: Tensor, X: Tensor, U: Tensor, params, constrained: bool,
                 active_tolerance: Optional[float], multipliers: Optional[Multipliers], active: tuple,
                 need_multipliers: bool) -> tuple:
    """``(kkt, step)``: :func:`refine`'s KKT system at ``(X, U)`` and its Newton step, with the multipliers."""
    kkt = kkt_system(problem, x0, X, U, params, constrained, active_tolerance, multipliers, active,
                     need_multipliers=need_multipliers, cons=cons)
    return kkt, kkt.factor.solve(kkt.newton, multipliers=True)
