"""Torque-limited pendulum swing-up on ``torchtraj.models.pendulum`` (the problem set's ``pendulum`` row).

State ``x = [θ, ω]`` with θ = 0 hanging down, torque ``τ``, ``m = 1``, ``l = 0.5``, ``b = 0.1``, ``g = 9.81``::

    θ̇ = ω,   ω̇ = (τ − m g l sin θ − b ω) / (m l²),   |τ| ≤ 3 < m g l = 4.905

so the pendulum cannot be lifted directly and must be pumped up. The reward is Gymnasium Pendulum-v1's running cost
with the angle error measured from upright::

    r_k = −(e_k² + 0.1 ω_k² + 0.001 τ_k²),   e_k = wrap(θ_k − π) ∈ [−π, π)

taken on the state before the step, as the running cost ``ℓ(x_k, u_k)`` of a trajectory optimisation problem.
"""

from __future__ import annotations

from typing import Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from torchtraj import models

from .core import Layout, ModelEnv, wrap_angle
from .render import Canvas
from .vector import ModelVectorEnv

TORQUE_LIMIT = 3.0  # the problem set's bound
START_NOISE = 0.1  # half-width of the uniform draw of θ0 and ω0 about hanging at rest


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

    ## Arguments

    ``gymnasium.make("torchtraj/Pendulum-v0", render_mode=None)``, or ``PendulumEnv(max_episode_steps=200,
    render_mode=None)``. ``render_mode="rgb_array"`` draws a 400 × 400 frame. ``reset(options={"state": x0})``
    starts from a given state. ``gymnasium.make_vec`` gives :class:`PendulumVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, render_mode: Optional[str] = None):
        super().__init__(models.get("pendulum"), [-TORQUE_LIMIT], [TORQUE_LIMIT], 2, max_episode_steps, render_mode)

    def _sample(self, rng: np.random.Generator):
        return rng.uniform(-START_NOISE, START_NOISE, size=2), {}

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        error = wrap_angle(x[:, 0] - torch.pi)
        return -(error * error + 0.1 * x[:, 1] * x[:, 1] + 0.001 * u[:, 0] * u[:, 0])

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
    """``num_envs`` :class:`PendulumEnv` stepped as one batched torch operation (see :mod:`envs.vector`).

    ``PendulumVectorEnv(num_envs, device="cpu", array_type="numpy", render_mode=None, max_episode_steps=200)``;
    ``gymnasium.make_vec("torchtraj/Pendulum-v0", num_envs=...)`` builds it.
    """

    env_class = PendulumEnv
