r"""Time-penalised problems (Howell et al. 2019 §III-C, eqs. 33-34).

The step length becomes a decision: ``τ_k = √Δt_k`` is an extra control (its square keeps
``Δt_k ≥ 0`` without a constraint), the state carries the previous step's ``δ_k = τ_{k-1}``, and

.. math::

    \begin{bmatrix} x_{k+1} \\ \delta_{k+1} \end{bmatrix}
        = \begin{bmatrix} F(x_k, u_k; \Delta t = \tau_k^2) \\ \tau_k \end{bmatrix}  \quad (33),
    \qquad J_\tau = J + \sum_k R_\tau \tau_k^2 \quad (34),

subject to ``δ_k = τ_k`` (``k = 1..N-1``: every step has the same length, so the solver cannot
exploit the integrator's discretisation error) and bounds ``τ_min ≤ τ_k ≤ τ_max``. A third state
component ``ε`` (``ε_0 = 0``, ``ε_{k+1} = 1``) switches the equalities off at ``k = 0``:
``ε_k (τ_k − δ_k) = 0``.

The problem's stage cost, written for steps of length ``Δt``, is scaled by ``Δt_k / Δt`` so that
it keeps meaning "integral over time". ``F`` is the integrator (``rk4`` by default) applied to the
continuous dynamics, which the transform needs because the discrete step of the original problem is
fixed to its ``Δt``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from . import integrators
from .core.problem import Problem


@dataclass
class TimePenalized:
    """A time-penalised version of ``original``: solve ``problem`` and read the answer with :meth:`split`."""

    original: Problem
    problem: Problem

    def split(self, X: Tensor, U: Tensor):
        """``(X (B, N+1, nx), U (B, N, nu), dt (B, N))`` of the original problem from a solution of ``problem``."""
        nx, nu = self.original.nx, self.original.nu
        return X[..., :nx], U[..., :nu], U[..., nu] ** 2

    def duration(self, U: Tensor) -> Tensor:
        """Total time ``Σ τ_k²`` ``(B,)``."""
        return (U[..., self.original.nu] ** 2).sum(-1)

    def initial_state(self, x0: Tensor) -> Tensor:
        """Initial states ``(..., nx)`` of the original problem as states of ``problem``: ``(x0, √Δt, ε = 0)``."""
        return _extend_state(x0, float(self.original.dt))


def _extend_state(x0: Tensor, dt: float) -> Tensor:
    extra = x0.new_tensor([math.sqrt(dt), 0.0]).expand(*x0.shape[:-1], 2)
    return torch.cat([x0, extra], -1)


def time_penalized(problem: Problem, continuous_dynamics: Callable, time_weight: float = 1.0,
                   dt_bounds: Optional[tuple] = None, integrator: str = "rk4") -> TimePenalized:
    """Make the step length of ``problem`` a decision variable (ALTRO §III-C).

    Args:
        problem: the fixed-time problem (its ``dt`` must be set).
        continuous_dynamics: ``f(x, u, p) -> ẋ`` whose ``integrator`` step with ``dt`` is ``problem.dynamics``.
        time_weight: ``R_τ`` of eq. (34).
        dt_bounds: ``(Δt_min, Δt_max)``; default ``(Δt / 10, 2 Δt)``.
        integrator: ``"rk4"`` or ``"euler"``.
    """
    if problem.dt is None:
        raise ValueError("time_penalized needs problem.dt (the nominal step length)")
    dt = float(problem.dt)
    lo, hi = dt_bounds if dt_bounds is not None else (dt / 10.0, 2.0 * dt)
    if not 0.0 < lo <= dt <= hi:
        raise ValueError(f"dt_bounds must satisfy 0 < dt_min <= dt ({dt}) <= dt_max, got {(lo, hi)}")
    combinator = getattr(integrators, integrator)
    nx, nu = problem.nx, problem.nu
    orig = problem

    def dynamics(x, u, p):
        tau = u[nu]
        step = combinator(continuous_dynamics, tau * tau)
        x_next = step(x[:nx], u[:nu], p)
        return torch.cat([x_next, tau.reshape(1), torch.ones_like(tau).reshape(1)])

    def stage_cost(x, u, p):
        tau = u[nu]
        return orig.stage_cost(x[:nx], u[:nu], p) * (tau * tau / dt) + time_weight * tau * tau

    def terminal_cost(x, p):
        return orig.terminal_cost(x[:nx], p)

    def stage_eq(x, u, p):
        same_step = (x[nx + 1] * (u[nu] - x[nx])).reshape(1)
        return same_step if orig.stage_eq is None else torch.cat([orig.stage_eq(x[:nx], u[:nu], p), same_step])

    def wrap_stage(fn):
        return None if fn is None else (lambda x, u, p: fn(x[:nx], u[:nu], p))

    def wrap_state(fn):
        return None if fn is None else (lambda x, p: fn(x[:nx], p))

    like = dict(dtype=orig.dtype, device=orig.device)
    inf = float("inf")
    u_lower = torch.cat([orig.u_lower if orig.u_lower is not None else torch.full((nu,), -inf, **like),
                         torch.tensor([math.sqrt(lo)], **like)])
    u_upper = torch.cat([orig.u_upper if orig.u_upper is not None else torch.full((nu,), inf, **like),
                         torch.tensor([math.sqrt(hi)], **like)])
    x_lower = None if orig.x_lower is None else torch.cat([orig.x_lower, torch.full((2,), -inf, **like)])
    x_upper = None if orig.x_upper is None else torch.cat([orig.x_upper, torch.full((2,), inf, **like)])
    tau0 = torch.tensor([math.sqrt(dt)], **like)
    u_init = None if orig.u_init is None else torch.cat([orig.u_init, tau0.expand(*orig.u_init.shape[:-1], 1)], -1)
    x0 = _extend_state(orig.x0, dt)
    transformed = orig.replace(
        dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost, x0=x0, nu=nu + 1,
        stage_eq=stage_eq, stage_ineq=wrap_stage(orig.stage_ineq), state_ineq=wrap_state(orig.state_ineq),
        terminal_eq=wrap_state(orig.terminal_eq), terminal_ineq=wrap_state(orig.terminal_ineq),
        u_lower=u_lower, u_upper=u_upper, x_lower=x_lower, x_upper=x_upper, u_init=u_init, X_init=None,
        name=f"{orig.name} (time-penalised)",
    )
    return TimePenalized(original=orig, problem=transformed)
