r"""The linear-quadratic model of a problem at a trajectory ``(X, U)``.

The objective ``J = Σ_k l(x_k, u_k, p) + l_N(x_N, p)`` and its LQR model around ``(X, U)``: the dynamics
linearised, ``δx_{k+1} = A_k δx_k + B_k δu_k``, the costs quadratised, ``½ δzᵀ ∇²l δz + ∇lᵀ δz`` with
``z = (x, u)`` (ALTRO §II-A eqs. 7-12 without the constraint terms).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..core.batching import map_stage, map_state
from ..core.derivatives import linearize_dynamics, quadratize_cost
from ..core.problem import Problem
from ..riccati import LQR, LQRVectors


def total_cost(problem: Problem, X: Tensor, U: Tensor, params) -> Tensor:
    """Objective of ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``: ``(B, *E)``, differentiable in all inputs."""
    stage = map_stage(problem.stage_cost, X[..., :-1, :], U, params).sum(-1)
    return stage + map_state(problem.terminal_cost, X[..., -1, :], params)


def cost_model(problem: Problem, X: Tensor, U: Tensor, params):
    """The LQR model of ``problem``'s objective around ``(X, U)``: matrices and gradient right-hand sides."""
    nx = X.shape[-1]
    _, A, Bm = linearize_dynamics(problem.dynamics, X, U, params)
    cost = quadratize_cost(problem.stage_cost, problem.terminal_cost, X, U, params)
    lzz, lz = cost.hessian, cost.gradient
    lqr = LQR(A=A, B=Bm, Q=lzz[..., :nx, :nx], R=lzz[..., nx:, nx:], S=lzz[..., nx:, :nx], QN=cost.terminal_hessian)
    rhs = LQRVectors(
        q=lz[..., :nx], r=lz[..., nx:], qN=cost.terminal_gradient, c=torch.zeros_like(X[:, 1:]),
        x0=torch.zeros_like(X[:, 0])
    )
    return lqr, rhs
