r"""Minimum-time problems as FATROP writes them (Vanroye et al. 2023 §V, "Minimum Total Time Problems").

FATROP adds an auxiliary state ``T_k``, the total time, constant over the horizon (``T_{k+1} = T_k``),
positive (``T_0 ≥ 0``) and setting the uniform integration step ``Δt = T_k / N``; its objective is the
total time. There ``T_0`` is a free variable. A :class:`~torchtraj.Problem` fixes its whole initial
state, so here the first value of ``T`` is chosen by an extra control ``s`` that acts at stage 0 only.
The state becomes ``z = (x, T, ε)``, the control ``v = (u, s)``, with ``ε`` the first-stage flag of
:mod:`torchtraj.time_penalty` (``ε_0 = 0``, ``ε_{k+1} = 1``), and

.. math::

    T_{k+1} = T_k + \sigma_k s_k, \qquad
    x_{k+1} = F\big(x_k, u_k;\ \Delta t = T_{k+1} / N\big), \qquad \varepsilon_{k+1} = 1,
    \qquad \sigma_k = \mathbb{1}[\varepsilon_k < \tfrac12] = \mathbb{1}[k = 0],

.. math::

    \min\ w_T\, T_N + \ell_N(x_N) + \sum_{k<N} \Big[ \ell(x_k, u_k)\, \frac{T_{k+1}}{N\,\Delta t_0}
        + \tfrac{\rho}{2}\, (1 - \sigma_k)\, s_k^2 \Big]
    \quad \text{s.t.}\quad T_{\min} - T_g \le s_k \le T_{\max} - T_g,

with ``T_0 = T_g`` (the guess of the total time, ``N Δt_0`` by default) in the initial state. So
``T_1 = T_g + s_0`` is free within ``[T_min, T_max]`` and ``T_k = T_1`` for every ``k ≥ 1``: the FATROP
structure (T a state, constant, ``Δt = T/N`` in the integrator; stage 0 integrates with ``T_1``).

Why this form and not an equality ``s_k = 0`` for ``k ≥ 1``: a stage equality switched off at stage 0
(``ε_k s_k = 0``) is an identically zero constraint row there, a rank-deficient Jacobian that the
interior point must regularise. Here the later ``s_k`` enter nothing but ``ρ/2 s_k²`` (the flag gates
them out of the dynamics), so their minimiser is exactly ``s_k = 0``, their Hessian block is ``ρ > 0``,
and the transformed problem has the same optimum as FATROP's NLP, with no constraint added. The gate
``σ_k`` is a step in ``ε``, flat where ``ε`` lives (0 or 1), not the smooth ``1 − ε_k``: on multiple
shooting the states are iterates, and a step that moves ``ε`` off 1 (the IPM's restoration phase relaxes
every defect) would turn the later ``s_k`` into levers on ``T`` through ``(1 − ε_k) s_k`` — measured on
the cart-pendulum swing, ``T`` then drifted along the horizon and the solve ended ``MAX_REGULARIZATION``. The bound
on ``T`` is a control bound on ``s``: at stage 0 it is ``T_min ≤ T_1 ≤ T_max``; at ``k ≥ 1`` it is
inactive at ``s_k = 0`` because ``T_g`` lies inside ``[T_min, T_max]``. A control bound suits every method
that takes constraints (ipm, altro, al-ilqr, eilqr, hm-ilqr); none needs a free initial state.

The problem's stage cost, written for intervals of length ``Δt_0 = problem.dt``, is scaled by
``Δt / Δt_0`` so that it keeps meaning "integral over time" (as :func:`torchtraj.time_penalized`
does); its terminal cost and constraints are kept as they are. Terminal equalities ("reach the goal")
are the usual terminal conditions of a minimum-time problem and pass through unchanged.
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
class MinimumTime:
    """A minimum-time version of ``original``: solve ``problem`` and read the answer with :meth:`split`.

    Attributes:
        original: the fixed-time problem.
        problem: the transformed problem (state ``(x, T, ε)``, control ``(u, s)``, module docstring).
        time_guess: ``T_g``, the value of ``T`` in the initial state.
        time_bounds: ``(T_min, T_max)``.
    """

    original: Problem
    problem: Problem
    time_guess: float
    time_bounds: tuple

    def split(self, X: Tensor, U: Tensor):
        """``(X (B, N+1, nx), U (B, N, nu), T (B,))`` of the original problem from a solution of ``problem``."""
        nx, nu = self.original.nx, self.original.nu
        return X[..., :nx], U[..., :nu], self.duration(X)

    def duration(self, X: Tensor) -> Tensor:
        """Total time ``T = T_N`` ``(B,)`` from states ``X (B, N+1, nx + 2)`` of ``problem``."""
        return X[..., -1, self.original.nx]

    def time_grid(self, X: Tensor) -> Tensor:
        """Times ``t_k = k T / N`` ``(B, N+1)`` of the knots."""
        N = self.original.N
        steps = torch.arange(N + 1, dtype=X.dtype, device=X.device) / N
        return self.duration(X)[..., None] * steps

    def initial_state(self, x0: Tensor) -> Tensor:
        """Initial states ``(..., nx)`` of the original problem as states of ``problem``: ``(x0, T_g, ε = 0)``."""
        return _extend_state(x0, self.time_guess)


def _extend_state(x0: Tensor, time_guess: float) -> Tensor:
    extra = x0.new_tensor([time_guess, 0.0]).expand(*x0.shape[:-1], 2)
    return torch.cat([x0, extra], -1)


def _time_bounds(time_bounds: Optional[tuple], time_guess: float) -> tuple:
    lo, hi = (0.0, math.inf) if time_bounds is None else (float(time_bounds[0]), float(time_bounds[1]))
    if not 0.0 <= lo < hi:
        raise ValueError(f"time_bounds must satisfy 0 <= T_min < T_max, got {(lo, hi)}")
    if not lo < time_guess < hi:
        raise ValueError(f"time_guess must lie strictly inside time_bounds {(lo, hi)}, got {time_guess}")
    return lo, hi


def minimum_time(problem: Problem, continuous_dynamics: Callable, time_weight: float = 1.0,
                 time_bounds: Optional[tuple] = None, time_guess: Optional[float] = None,
                 integrator: str = "rk4", hold_weight: float = 1.0) -> MinimumTime:
    """Make the total time of ``problem`` a decision variable, FATROP's way (module docstring).

    Args:
        problem: the fixed-time problem: its horizon ``N`` is kept and its ``dt`` is the step that its stage cost
            is written for (and the default guess ``T_g = N dt``).
        continuous_dynamics: ``f(x, u, p) -> ẋ`` whose ``integrator`` step is the problem's dynamics.
        time_weight: ``w_T``, the weight of the total time in the objective.
        time_bounds: ``(T_min, T_max)``; default ``(0, inf)``, FATROP's ``T_0 ≥ 0``.
        time_guess: ``T_g``, strictly inside the bounds; default ``N dt``.
        integrator: ``"rk4"`` or ``"euler"``.
        hold_weight: ``ρ``, the curvature that holds ``s_k = 0`` at the stages after the first.
    """
    if problem.dt is None:
        raise ValueError("minimum_time needs problem.dt (the step its stage cost is written for)")
    if hold_weight <= 0.0:
        raise ValueError(f"hold_weight must be positive, got {hold_weight}")
    dt, N, nx, nu = float(problem.dt), problem.N, problem.nx, problem.nu
    guess = N * dt if time_guess is None else float(time_guess)
    lo, hi = _time_bounds(time_bounds, guess)
    combinator = getattr(integrators, integrator)
    orig = problem

    def first_stage(z):
        # the indicator 1[k = 0], flat in ε: a smooth gate (1 − ε) would let a step that moves ε (restoration
        # relaxes every defect) turn the later s_k into levers on T
        return (z[nx + 1] < 0.5).to(z.dtype)

    def total_time(z, v):
        return z[nx] + first_stage(z) * v[nu]

    def dynamics(z, v, p):
        T_next = total_time(z, v)
        x_next = combinator(continuous_dynamics, T_next / N)(z[:nx], v[:nu], p)
        return torch.cat([x_next, T_next.reshape(1), torch.ones_like(T_next).reshape(1)])

    def stage_cost(z, v, p):
        hold = 0.5 * hold_weight * (1.0 - first_stage(z)) * v[nu] * v[nu]
        return orig.stage_cost(z[:nx], v[:nu], p) * (total_time(z, v) / (N * dt)) + hold

    def terminal_cost(z, p):
        return orig.terminal_cost(z[:nx], p) + time_weight * z[nx]

    def wrap_stage(fn):
        return None if fn is None else (lambda z, v, p: fn(z[:nx], v[:nu], p))

    def wrap_state(fn):
        return None if fn is None else (lambda z, p: fn(z[:nx], p))

    like = dict(dtype=orig.dtype, device=orig.device)
    inf = math.inf
    u_lower = torch.cat([orig.u_lower if orig.u_lower is not None else torch.full((nu,), -inf, **like),
                         torch.tensor([lo - guess], **like)])
    u_upper = torch.cat([orig.u_upper if orig.u_upper is not None else torch.full((nu,), inf, **like),
                         torch.tensor([hi - guess], **like)])
    free = torch.full((2,), inf, **like)
    x_lower = None if orig.x_lower is None else torch.cat([orig.x_lower, -free])
    x_upper = None if orig.x_upper is None else torch.cat([orig.x_upper, free])
    u_init = torch.cat([orig.u_init, orig.u_init.new_zeros(N, 1)], -1)
    X_init = None
    if orig.X_init is not None:
        flag = (torch.arange(N + 1, **like) > 0).to(orig.dtype)[:, None]
        X_init = torch.cat([orig.X_init, torch.full((N + 1, 1), guess, **like), flag], -1)
    transformed = orig.replace(
        dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost, x0=_extend_state(orig.x0, guess),
        nu=nu + 1, stage_eq=wrap_stage(orig.stage_eq), stage_ineq=wrap_stage(orig.stage_ineq),
        state_ineq=wrap_state(orig.state_ineq), terminal_eq=wrap_state(orig.terminal_eq),
        terminal_ineq=wrap_state(orig.terminal_ineq), u_lower=u_lower, u_upper=u_upper, x_lower=x_lower,
        x_upper=x_upper, u_init=u_init, X_init=X_init, dt=None, linear_quadratic=False,
        name=f"{orig.name} (minimum time)",
    )
    return MinimumTime(original=orig, problem=transformed, time_guess=guess, time_bounds=(lo, hi))
