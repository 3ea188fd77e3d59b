"""FATROP's minimum-time benchmark (Vanroye et al. 2023 §V, Tables II–III) in kind, on the project's own models.

Each problem is, with ``Δt = T / N`` and ``F`` the RK4 step of a model in :mod:`torchtraj.models`::

    minimize    w_T T + sum_{k<N} 0.5 u_kᵀ R u_k Δt
    subject to  x_{k+1} = F(x_k, u_k; Δt),  x_0 = x0,  T_min <= T <= T_max
                u_lower <= u_k <= u_upper                k = 0..N-1
                x_lower <= x_k <= x_upper                k = 1..N-1
                x_N[i] = goal[i]  for i in terminal       (reach the goal)

* ``cartpole_swing``: FATROP's "cart pendulum swing" — the pendulum starts hanging at rest and ends upright
  with the cart and the pendulum at rest (three terminal equalities: θ, ẋ, θ̇; the cart's position is free),
  bounds on the cart's position, its velocity and the force; K = 100 intervals.
* ``quadrotor_p2p``: FATROP's "quadrotor point-to-point" on the planar quadrotor — hover at one point to hover
  at another (six terminal equalities), the problem set's thrust and tilt bounds; K = 25 intervals.

The total time is bounded by ``T_g / 10 ≤ T ≤ 10 T_g``, inactive at the optima: FATROP's ``T ≥ 0`` lets the
augmented-Lagrangian methods, whose early iterates violate bounds, reach ``T < 0``, where the dynamics run
backwards, and stay there. The numbers are the problem set's where it has them (:mod:`torchtraj.problems`: the
cart-pole's force bound, the quadrotor's thrust and tilt bounds and its start and goal positions). ``R`` is zero: the
objective is the total time alone, as in FATROP's benchmark. :func:`get` builds the :class:`~torchtraj.MinimumTime`
transform; :mod:`torchtraj.bench.minimum_time_reference` transcribes the same spec for IPOPT and FATROP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .. import integrators, models
from ..core.problem import Problem
from ..minimum_time import MinimumTime, minimum_time


@dataclass(frozen=True, eq=False)
class MinimumTimeSpec:
    """The numbers of one minimum-time problem (module docstring).

    Args:
        name: problem name; model: a model of :mod:`torchtraj.models` (default parameters).
        N: number of intervals; x0, goal: ``(nx,)``; terminal: the components of ``goal`` imposed at ``x_N``.
        u_lower, u_upper: ``(nu,)``; x_lower, x_upper: ``(nx,)`` on knots 1..N-1 (±inf where unbounded).
        time_guess: ``T_g``, the initial guess of the total time; time_bounds: ``(T_min, T_max)``.
        time_weight: ``w_T``; control_weight: ``R`` per unit time, a number (times the identity).
        u_init: ``(nu,)`` constant control guess (states: its rollout over ``T_g``).
    """

    name: str
    model: str
    N: int
    x0: tuple
    goal: tuple
    terminal: tuple
    u_lower: tuple
    u_upper: tuple
    x_lower: tuple
    x_upper: tuple
    time_guess: float
    time_bounds: tuple = (0.0, math.inf)
    time_weight: float = 1.0
    control_weight: float = 0.0
    u_init: tuple = ()

    @property
    def nx(self) -> int:
        return len(self.x0)

    @property
    def nu(self) -> int:
        return len(self.u_lower)

    def array(self, field: str) -> np.ndarray:
        return np.asarray(getattr(self, field), dtype=np.float64)


_INF = math.inf
SPECS = {
    "cartpole_swing": MinimumTimeSpec(
        name="cartpole_swing", model="cartpole", N=100, x0=(0.0, 0.0, 0.0, 0.0), goal=(0.0, math.pi, 0.0, 0.0),
        terminal=(1, 2, 3), u_lower=(-3.0,), u_upper=(3.0,),
        x_lower=(-1.0, -_INF, -2.0, -_INF), x_upper=(1.0, _INF, 2.0, _INF), time_guess=5.0, time_bounds=(0.5, 50.0),
        u_init=(0.0,)),
    "quadrotor_p2p": MinimumTimeSpec(
        name="quadrotor_p2p", model="quadrotor2d", N=25, x0=(4.5, 2.5, 0.0, 0.0, 0.0, 0.0),
        goal=(1.0, 1.5, 0.0, 0.0, 0.0, 0.0), terminal=(0, 1, 2, 3, 4, 5), u_lower=(0.0, 0.0), u_upper=(15.0, 15.0),
        x_lower=(-_INF, -_INF, -math.pi / 6, -_INF, -_INF, -_INF),
        x_upper=(_INF, _INF, math.pi / 6, _INF, _INF, _INF), time_guess=6.0, time_bounds=(0.6, 60.0),
        u_init=(9.81 / 2, 9.81 / 2)),
}


def names() -> list:
    return list(SPECS)


def spec(name: str) -> MinimumTimeSpec:
    if name not in SPECS:
        raise ValueError(f"unknown minimum-time problem {name!r}; known: {names()}")
    return SPECS[name]


def get(name, dtype: torch.dtype = torch.float64, device=None) -> MinimumTime:
    """Problem ``name`` (or a :class:`MinimumTimeSpec`) as the :func:`~torchtraj.minimum_time` transform of its
    fixed-time problem over ``T_g``."""
    s = name if isinstance(name, MinimumTimeSpec) else spec(name)
    model = models.get(s.model)
    like = dict(dtype=dtype, device=device)
    dt = s.time_guess / s.N
    goal = torch.tensor(s.goal, **like)[list(s.terminal)]
    index = torch.tensor(s.terminal, device=device)
    R = s.control_weight * dt

    def bound(values):
        t = torch.tensor(values, **like)
        return t if bool(torch.isfinite(t).any()) else None

    problem = Problem(
        dynamics=integrators.rk4(model.dynamics, dt),
        stage_cost=lambda x, u, p: 0.5 * R * (u * u).sum(),
        terminal_cost=lambda x, p: 0.0 * x[0],
        terminal_eq=lambda x, p: x[index] - goal,
        x0=torch.tensor(s.x0, **like), horizon=s.N, nu=s.nu,
        params={k: v.to(**like) for k, v in model.params.items()},
        u_lower=bound(s.u_lower), u_upper=bound(s.u_upper), x_lower=bound(s.x_lower), x_upper=bound(s.x_upper),
        u_init=torch.tensor(s.u_init, **like), dt=dt, name=s.name,
    )
    return minimum_time(problem, model.dynamics, time_weight=s.time_weight, time_bounds=s.time_bounds,
                        time_guess=s.time_guess)
