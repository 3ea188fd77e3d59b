"""Torque-limited pendulum swing-up on ``torchtraj.models.pendulum`` (the problem set's ``pendulum`` row).

State ``x = [θ, ω]`` with θ = 0 hanging down, torque ``τ``, ``m = 1``, ``l = 0.5``, ``b = 0.1``, ``g = 9.81``::

    θ̇ = ω,   ω̇ = (τ − m g l sin θ − b ω) / (m l²),   |τ| ≤ 3 < m g l = 4.905

so the pendulum cannot be lifted directly and must be pumped up. The reward is Gymnasium Pendulum-v1's running cost
with the angle error measured from upright::

    r_k = −(e_k² + 0.1 ω_k² + 0.001 τ_k²),   e_k = wrap(θ_k − π) ∈ [−π, π)

taken on the state before the step, as the running cost ``ℓ(x_k, u_k)`` of a trajectory optimisation problem.

The task as pure functions (:mod:`torchtraj.envs.core`), which the environment itself calls::

    dynamics(x, u, p)                          the RK4 step over dt = 0.05 of the model, p = env.model_params
    running_cost(x, u)                         e² + 0.1 ω² + 0.001 τ²  (= −reward)
    reward(x, u, x_next, layout, params)       −running_cost(x, u)
    stage_cost(x, u, p), terminal_cost(x, p)   dt · running_cost(x, u) and e² + 0.1 ω²: the controller's costs
    problem(params, horizon=30)                the controller's Problem (PendulumEnv docstring)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from torchtraj import models
from torchtraj.core.problem import Problem

from .core import DT, Layout, ModelEnv, upright_error
from .render import Canvas
from .vector import ModelVectorEnv

TORQUE_LIMIT = 3.0  # the problem set's bound
START_NOISE = 0.1  # half-width of the uniform draw of θ0 and ω0 about hanging at rest


@dataclass(frozen=True)
class PendulumParams:
    """The pendulum task's parameters (the physics is ``torchtraj.models.get("pendulum")``'s).

    Args:
        torque_limit: the bound ``|τ| ≤ torque_limit``, the action space.
        start_noise: half-width of the uniform draw of θ0 and ω0 about hanging at rest.
    """

    torque_limit: float = TORQUE_LIMIT
    start_noise: float = START_NOISE


#: The per-instance step ``(x (2,), u (1,), p) -> x_next (2,)`` the environment takes, ``p = env.model_params``.
dynamics = models.get("pendulum").discrete(DT, "rk4")


def running_cost(x: Tensor, u: Tensor, p=None) -> Tensor:
    """``e² + 0.1 ω² + 0.001 τ²`` with ``e = wrap(θ − π)``, of ``x: (..., 2)``, ``u: (..., 1)``: the negated reward."""
    e = upright_error(x[..., 0])
    return e * e + 0.1 * x[..., 1] * x[..., 1] + 0.001 * u[..., 0] * u[..., 0]


def reward(x: Tensor, u: Tensor, x_next: Tensor, layout: Layout, params: PendulumParams) -> Tensor:
    """The environment's reward ``(...)``: ``−running_cost(x, u)`` on the state before the step."""
    return -running_cost(x, u)


def stage_cost(x: Tensor, u: Tensor, p) -> Tensor:
    """The controller's stage cost ``dt · running_cost(x, u)``: the reward, negated, over one step."""
    return DT * running_cost(x, u)


def terminal_cost(x: Tensor, p) -> Tensor:
    """The controller's terminal cost ``e² + 0.1 ω²``: the running cost at rest, standing in for the rest of the
    episode."""
    e = upright_error(x[..., 0])
    return e * e + 0.1 * x[..., 1] * x[..., 1]


def problem(params: Optional[PendulumParams] = None, horizon: int = 30) -> Problem:
    """The controller's :class:`~torchtraj.Problem` for a pendulum of ``params`` (default ``PendulumParams()``):
    ``horizon`` steps of :data:`dynamics` with :func:`stage_cost`, :func:`terminal_cost` and the torque bound
    (:class:`PendulumEnv`, "Controller problem"). ``x0`` is a placeholder: the controller passes the state."""
    params = PendulumParams() if params is None else params
    if not isinstance(params, PendulumParams):
        raise TypeError(f"params must be a PendulumParams, got {type(params).__name__}")
    model_params = {k: v.to(torch.float64) for k, v in models.get("pendulum").params.items()}
    limit = torch.tensor([params.torque_limit], dtype=torch.float64)
    return Problem(dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost,
                   x0=torch.zeros(2, dtype=torch.float64), horizon=horizon, nu=1, params=model_params,
                   u_lower=-limit, u_upper=limit, dt=DT, name="pendulum_mpc")


class PendulumEnv(ModelEnv):
    """Swing a torque-limited pendulum up and hold it there.

    ## Description

    A point mass on a massless rod of length 0.5 m with viscous joint damping: the model
    ``torchtraj.models.get("pendulum")``, stepped with RK4 at ``dt = 0.05`` s (``model.discrete(dt, "rk4")``).
    The torque bound |τ| ≤ 3 N m is below the 4.905 N m needed to hold the pendulum horizontal, so it has to be
    swung up. The angle is not wrapped: θ accumulates over full turns, and the upright states are θ = π + 2πk.

    ## Action Space

    ``Box(-3, 3, (1,), float64)``: the joint torque τ. Out-of-bounds actions are clipped to the bounds; a NaN
    action raises ``ValueError``.

    ## Observation Space

    ``Box(-inf, inf, (2,), float64)``: the model state ``[θ, ω]`` (rad, rad/s); ``observation_to_state`` is the
    identity (a copy).

    ## Rewards

    ``r = −(wrap(θ − π)² + 0.1 ω² + 0.001 τ²)`` on the state before the step and the clipped torque: 0 upright
    at rest, about −9.87 hanging at rest.

    ## Starting State

    θ0 and ω0 uniform in [−0.1, 0.1] (hanging down, nearly still), drawn from the environment's seeded generator.

    ## Episode End

    Never terminates; truncated after ``max_episode_steps`` steps (default 200, i.e. 10 s; the problem set swings
    up within 3 s).

    ## Controller Problem

    ``env.problem(horizon=30)`` (``torchtraj.envs.pendulum.problem(env.params, horizon)``) is the MPC controller's
    :class:`torchtraj.Problem`, on the environment's own step (:data:`dynamics`) and its own reward::

        minimise  Σ_k dt (e_k² + 0.1 ω_k² + 0.001 τ_k²) + e_N² + 0.1 ω_N²,   |τ_k| ≤ 3,   N = 30 (1.5 s)

    The stage cost is the reward, negated, times dt (:func:`stage_cost` calls :func:`running_cost`, as
    :func:`reward` does); the terminal cost stands in for the rest of the episode, with no terminal equality (a
    receding horizon cannot always reach upright within N steps). Its parameters are ``env.model_params``.

    ## Arguments

    ``gymnasium.make("torchtraj/Pendulum-v0", render_mode=None)``, or ``PendulumEnv(max_episode_steps=200,
    render_mode=None)``. ``render_mode="rgb_array"`` draws a 400 × 400 frame. ``reset(options={"state": x0})``
    starts from a given state. ``gymnasium.make_vec`` gives :class:`PendulumVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, render_mode: Optional[str] = None):
        self.params = PendulumParams()
        limit = self.params.torque_limit
        super().__init__(models.get("pendulum"), [-limit], [limit], 2, max_episode_steps, render_mode, dynamics)

    def problem(self, horizon: int = 30) -> Problem:
        """The controller's problem (``## Controller Problem``): ``pendulum.problem(self.params, horizon)``."""
        return problem(self.params, horizon)

    def _sample(self, rng: np.random.Generator):
        noise = self.params.start_noise
        return rng.uniform(-noise, noise, size=2), {}

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        return reward(x, u, x_next, layout, self.params)

    def _draw(self, x: np.ndarray, layout: Mapping[str, np.ndarray]) -> np.ndarray:
        length = float(self.model_params["length"])
        canvas = Canvas(400, 400, (-1.3 * length, 1.3 * length, -1.3 * length, 1.3 * length))
        canvas.disc((0.0, length), 0.03 * length, (0, 170, 0))  # upright target
        bob = (length * np.sin(x[0]), -length * np.cos(x[0]))  # θ = 0 hangs down
        canvas.segment((0.0, 0.0), bob, 0.08 * length, (200, 70, 60))
        canvas.disc(bob, 0.12 * length, (150, 40, 40))
        canvas.disc((0.0, 0.0), 0.05 * length, (30, 30, 30))
        return canvas.image


class PendulumVectorEnv(ModelVectorEnv):
    """``num_envs`` :class:`PendulumEnv` stepped as one batched torch operation (see :mod:`torchtraj.envs.vector`).

    ``PendulumVectorEnv(num_envs, device="cpu", array_type="numpy", render_mode=None, max_episode_steps=200)``;
    ``gymnasium.make_vec("torchtraj/Pendulum-v0", num_envs=...)`` builds it.
    """

    env_class = PendulumEnv
