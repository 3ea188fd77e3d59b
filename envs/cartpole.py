"""Cart-pole swing-up on ``torchtraj.models.cartpole`` (the problem set's ``cartpole`` row), on a finite rail.

State ``x = [x, θ, ẋ, θ̇]`` with θ = 0 hanging down, force ``F`` on the cart, ``mc = 1``, ``mp = 0.2``, ``l = 0.5``,
``D = mc + mp sin²θ``::

    ẍ = (F + mp sθ (l θ̇² + g cθ)) / D,   θ̈ = −(F cθ + mp l θ̇² sθ cθ + (mc + mp) g sθ) / (l D),   |F| ≤ 3

The episode terminates when the cart leaves the rail ``|x| ≤ 2.4``; the problem set's optimal swing-up stays
within |x| ≤ 0.31, so the rail leaves an MPC swing-up with the same weights a factor of eight of room. Because
crossing the rail ends the episode, the reward is non-negative (ending early can only lose reward)::

    r_k = ½ (1 − cos θ_k) · exp(−(0.1 x_k² + 0.01 ẋ_k² + 0.01 θ̇_k² + 0.001 F_k²)) ∈ [0, 1]

on the state before the step: 1 only upright, centred, still and unforced; 0 hanging down.
"""

from __future__ import annotations

from typing import Mapping, Optional

import numpy as np
import torch
from torch import Tensor

from torchtraj import models

from .core import Layout, ModelEnv
from .render import Canvas
from .vector import ModelVectorEnv

FORCE_LIMIT = 3.0  # the problem set's bound
START_NOISE = 0.05  # half-width of the uniform draw of every state component about hanging at rest, centred


class CartPoleSwingUpEnv(ModelEnv):
    """Swing a pole up by pushing its cart along a finite rail, and balance it.

    ## Description

    A 1 kg cart with a 0.2 kg point mass on a 0.5 m massless pole: the model ``torchtraj.models.get("cartpole")``,
    stepped with RK4 at ``dt = 0.05`` s (``model.discrete(dt, "rk4")``), the problem set's step. The force bound
    |F| ≤ 3 N is the problem set's, under which its optimal swing-up takes 5 s. θ is not wrapped; upright is
    θ = π + 2πk.

    ## Action Space

    ``Box(-3, 3, (1,), float64)``: the horizontal force F on the cart. Out-of-bounds actions are clipped to the
    bounds; a NaN action raises ``ValueError``.

    ## Observation Space

    ``Box(-inf, inf, (4,), float64)``: the model state ``[x, θ, ẋ, θ̇]`` (m, rad, m/s, rad/s);
    ``observation_to_state`` is the identity (a copy).

    ## Rewards

    ``r = ½ (1 − cos θ) · exp(−(0.1 x² + 0.01 ẋ² + 0.01 θ̇² + 0.001 F²))`` ∈ [0, 1] on the state before the step
    and the clipped force.

    ## Starting State

    Every component uniform in [−0.05, 0.05]: centred, hanging down, nearly still.

    ## Episode End

    Terminated when the cart leaves the rail, ``|x| > rail_limit`` (default 2.4 m). Truncated after
    ``max_episode_steps`` steps (default 200, i.e. 10 s, twice the problem set's horizon).

    ## Arguments

    ``gymnasium.make("torchtraj/CartPoleSwingUp-v0", render_mode=None, rail_limit=2.4)``, or
    ``CartPoleSwingUpEnv(max_episode_steps=200, rail_limit=2.4, render_mode=None)``. ``render_mode="rgb_array"``
    draws a 600 × 300 frame. ``reset(options={"state": x0})`` starts from a given state. ``gymnasium.make_vec``
    gives :class:`CartPoleSwingUpVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, rail_limit: float = 2.4, render_mode: Optional[str] = None):
        if not rail_limit > START_NOISE:
            raise ValueError(f"rail_limit must exceed the start noise {START_NOISE}, got {rail_limit!r}")
        super().__init__(models.get("cartpole"), [-FORCE_LIMIT], [FORCE_LIMIT], 4, max_episode_steps, render_mode)
        self.rail_limit = float(rail_limit)

    def _sample(self, rng: np.random.Generator):
        return rng.uniform(-START_NOISE, START_NOISE, size=4), {}

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        upright = 0.5 * (1.0 - torch.cos(x[:, 1]))
        penalty = 0.1 * x[:, 0] ** 2 + 0.01 * x[:, 2] ** 2 + 0.01 * x[:, 3] ** 2 + 0.001 * u[:, 0] ** 2
        return upright * torch.exp(-penalty)

    def _terminated(self, x_next: Tensor, layout: Layout) -> Tensor:
        return x_next[:, 0].abs() > self.rail_limit

    def _draw(self, x: np.ndarray, layout: Mapping[str, np.ndarray]) -> np.ndarray:
        length, rail = float(self.model_params["pole_length"]), self.rail_limit
        canvas = Canvas(600, 300, (-rail - 0.3, rail + 0.3, -0.9, 0.9))
        canvas.segment((-rail, 0.0), (rail, 0.0), 0.02, (90, 90, 90))
        for end in (-rail, rail):  # rail stops: crossing them ends the episode
            canvas.segment((end, -0.1), (end, 0.1), 0.04, (200, 0, 0))
        cart = (x[0], 0.0)
        canvas.segment((x[0] - 0.15, 0.0), (x[0] + 0.15, 0.0), 0.16, (60, 90, 160))
        tip = (x[0] + length * np.sin(x[1]), -length * np.cos(x[1]))  # θ = 0 hangs down
        canvas.segment(cart, tip, 0.04, (200, 140, 60))
        canvas.disc(tip, 0.05, (150, 90, 30))
        canvas.disc(cart, 0.03, (30, 30, 30))
        return canvas.image


class CartPoleSwingUpVectorEnv(ModelVectorEnv):
    """``num_envs`` :class:`CartPoleSwingUpEnv` stepped as one batched torch operation (see :mod:`envs.vector`).

    ``CartPoleSwingUpVectorEnv(num_envs, device="cpu", array_type="numpy", render_mode=None,
    max_episode_steps=200, rail_limit=2.4)``; ``gymnasium.make_vec("torchtraj/CartPoleSwingUp-v0", ...)`` builds it.
    """

    env_class = CartPoleSwingUpEnv
