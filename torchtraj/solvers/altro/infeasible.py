r"""Infeasible state initialisation (Howell et al. 2019 §III-B, eqs. 30-32).

Given a state guess ``X̃`` that the dynamics do not reproduce, slack controls ``s_k ∈ R^{nx}`` make
the system fully actuated,

.. math::  x_{k+1} = f(x_k, u_k) + s_k, \qquad s_k = \tilde x_{k+1} - f(\tilde x_k, u_k) \quad (30, 31)

so the rollout of ``(U, s)`` from ``x_0`` is exactly ``X̃``. The transformed problem adds the cost
``½ sᵀ R_s s`` (eq. 32) and the equality constraints ``s_k = 0``, which the augmented Lagrangian drives
to zero. When the AL stage ends, the slacks are dropped and the projection (§III-D) works on the
original problem with the dynamics as constraints: it removes the remaining defects
``f(x_k, u_k) − x_{k+1} = s_k`` together with the violations of the active constraints.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from ...core.batching import concat, map_stage, rollout
from ...core.constraints import Constraints
from ...core.problem import Problem
from .augmented_lagrangian import AugmentedLagrangian, Duals
from .stages import ALStage, al_stage, finish, initial_duals


def slack_problem(problem: Problem, slack_cost: float) -> Problem:
    """``problem`` with controls ``(u, s)``: dynamics (30), slack cost (32) and constraints ``s = 0``."""
    nx, nu = problem.nx, problem.nu
    f, cost, eq, ineq = problem.dynamics, problem.stage_cost, problem.stage_eq, problem.stage_ineq

    def dynamics(x, u, p):
        return f(x, u[:nu], p) + u[nu:]

    def stage_cost(x, u, p):
        s = u[nu:]
        return cost(x, u[:nu], p) + 0.5 * slack_cost * (s @ s)

    def stage_eq(x, u, p):
        return u[nu:] if eq is None else concat([eq(x, u[:nu], p), u[nu:]])

    def stage_ineq(x, u, p):
        return ineq(x, u[:nu], p)

    def extend(bound, fill):
        if bound is None:
            return None
        return torch.cat([bound, torch.full((nx,), fill, dtype=bound.dtype, device=bound.device)])

    u_init = problem.u_init
    if u_init is not None:
        u_init = torch.cat([u_init, u_init.new_zeros(*u_init.shape[:-1], nx)], -1)
    return problem.replace(
        dynamics=dynamics, stage_cost=stage_cost, nu=nu + nx, stage_eq=stage_eq,
        stage_ineq=None if ineq is None else stage_ineq,
        u_lower=extend(problem.u_lower, -float("inf")), u_upper=extend(problem.u_upper, float("inf")),
        u_init=u_init, X_init=None, name=f"{problem.name} (infeasible start)",
    )


def solve_infeasible(problem: Problem, x0: Tensor, U0: Tensor, X0: Tensor, params, opts, method: str,
                     warm: Optional[dict] = None):
    """ALTRO from the state guess ``X0 (B, N+1, nx)`` (its first knot is replaced by ``x0``).

    ``warm`` (:func:`torchtraj.solve`'s ``duals``) starts the multipliers and penalties of the problem's own
    constraints; the slack rows start at ``penalty_initial`` and at zero, or, given ``warm["costate"]``, at
    ``ν_k = −λ_{k+1}``: stationarity in ``s_k`` of ``½ R_s |s_k|² + λ_{k+1}ᵀ(f + s_k − x_{k+1}) + ν_kᵀ s_k`` at
    ``s = 0``."""
    nu = problem.nu
    X0 = torch.cat([x0.unsqueeze(1), X0[:, 1:]], 1)
    slack = X0[:, 1:] - map_stage(problem.dynamics, X0[:, :-1], U0, params)  # (31)
    augmented = slack_problem(problem, opts.slack_cost)
    Ua = torch.cat([U0, slack], -1)
    X = rollout(augmented.dynamics, x0, Ua, params)
    constraints = Constraints.of(problem)
    own = initial_duals(constraints, opts, x0, warm)
    # the slack rows s = 0 come last among the stage equalities (slack_problem), after the problem's own rows
    zeros = slack.new_zeros(slack.shape)
    costate = (warm or {}).get("costate")
    slack_rows = zeros if costate is None else -costate[:, 1:].to(zeros)
    start = Duals(torch.cat([own.stage, slack_rows], -1), own.terminal,
                  torch.cat([own.stage_penalty, zeros + opts.penalty_initial], -1), own.terminal_penalty)
    stage = al_stage(augmented, x0, X, Ua, params, opts, method, start)
    # back to the original problem: drop the slacks and their multipliers (the last nx equality rows)
    d = stage.al.duals
    m = constraints.mi + constraints.me
    duals = Duals(d.stage[..., :m], d.terminal, d.stage_penalty[..., :m], d.terminal_penalty)
    al = AugmentedLagrangian(constraints, duals, opts.square_root, opts.ilqr.record)
    original = ALStage(problem, al, stage.X, stage.U[..., :nu], stage.status, stage.al_done, stage.iterations,
                       stage.rows, stage.K[..., :nu, :], stage.stalled)
    return finish(original, x0, params, opts, method)
