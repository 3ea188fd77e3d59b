r"""The backward pass of implicit differentiation: one adjoint solve and the parameters' products.

With the KKT conditions ``F(w, y, θ) = 0`` of :mod:`torchtraj.differentiation.kkt_system` at a solution, the
implicit function theorem gives ``∂(w, y)/∂θ = -K^{-1} ∂F/∂θ`` with the symmetric KKT matrix
``K = [[∇²_w \mathcal L, ∂c/∂w^T], [∂c/∂w, 0]]``. For a loss with cotangents ``w̄ = (X̄, Ū)`` the reverse-mode
product is therefore

.. math::

    \bar θ = (∂F/∂θ)^T s,\qquad K s = -\begin{bmatrix} \bar w \\ 0 \end{bmatrix}.

The system ``K s = -(w̄, 0)`` is exactly the KKT system of the equality-constrained LQR problem with Hessian
``∇²\mathcal L``, the linearised dynamics, the active constraint rows as stagewise equalities (inactive rows masked
off), linear terms ``(q, r, q_N) = w̄`` and zero defects, initial state and constraint offsets
(:func:`torchtraj.kkt.newton.without_offsets`). It is solved by the batched Riccati core with the factorisation of
the KKT system (:meth:`~torchtraj.riccati.RiccatiFactor.solve` with ``multipliers=True``), whose primal step and
multipliers are ``s``. The product ``(∂F/∂θ)^T s`` is ``∂/∂θ`` of the directional derivative of the Lagrangian
along ``s``,

.. math::

    \bar θ = \nabla_θ \Big[ \sum_k \tfrac{d}{dε} \mathcal L_k(z_k + ε s_{z_k},\, y_k + ε s_{y_k}, θ)
        + \tfrac{d}{dε} \mathcal L_N(\dots) \Big]_{ε=0}, \qquad \bar x_0 = s_{λ_0},

evaluated with ``torch.func.jvp`` inside ``torch.func.grad``, mapped over batch and time.

In the unrolled mode (:mod:`torchtraj.differentiation.layer`) ``K`` is replaced by iLQR's model ``M``, the cost
Hessian in place of the Lagrangian's (``gauss_newton=True``); the products are the same.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import torch
from torch import Tensor
from torch.func import grad, jvp, vmap

from ..core.constraints import Constraints
from ..core.problem import Problem
from ..kkt.newton import without_offsets
from .kkt_system import KKTSystem, Multipliers, constraints_of, kkt_system


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
    when given (from :func:`~torchtraj.differentiation.refine.refine`). ``kkt`` is returned too: ``kkt.ok`` is
    False where the KKT system could not be factorised, ``kkt.degenerate`` where its active rows are linearly
    dependent. ``gauss_newton``: the adjoint of iLQR's model instead of the KKT matrix (unrolled mode). ``cons``:
    the problem's constraints, made once by the caller (made here if not given).
    """
    cons = constraints_of(problem, constrained) if cons is None else cons
    if kkt is None:
        kkt = kkt_system(problem, x0, X, U, params, constrained, active_tolerance, multipliers, active,
                         gauss_newton, cons=cons)
    multipliers = kkt.multipliers if multipliers is None else multipliers
    # the cotangents as the gradient, no offsets
    rhs = without_offsets(dataclasses.replace(kkt.newton, q=X_bar[:, :-1], r=U_bar, qN=X_bar[:, -1]))
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
