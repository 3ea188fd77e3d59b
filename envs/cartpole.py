"""Cart-pole swing-up on ``torchtraj.models.cartpole`` (the problem set's ``cartpole`` row), on a finite rail.

State ``x = [x, θ, ẋ, θ̇]`` with θ = 0 hanging down, force ``F`` on the cart, ``mc = 1``, ``mp = 0.2``, ``l = 0.5``,
``D = mc + mp sin²θ``::

    ẍ = (F + mp sθ (l θ̇² + g cθ)) / D,   θ̈ = −(F cθ + mp l θ̇² sθ cθ + (mc + mp) g sθ) / (l D),   |F| ≤ 3

The episode terminates when the cart leaves the rail ``|x| ≤ 2.4``; the problem set's optimal swing-up stays
within |x| ≤ 0.31, so the rail leaves an MPC swing-up with the same weights a factor of eight of room. Because
crossing the rail ends the episode, the reward is non-negative (ending early can only lose reward)::

    r_k = ½ (1 − cos θ_k) · exp(−(0.1 x_k² + 0.01 ẋ_k² + 0.01 θ̇_k² + 0.001 F_k²)) ∈ [0, 1]

on the state before the step: 1 only upright, centred, still and unforced; 0 hanging down.

The task as pure functions (:mod:`torchtraj.envs.core`), which the environment itself calls::

    dynamics(x, u, p)                          the RK4 step over dt = 0.05 of the model, p = env.model_params
    reward(x, u, x_next, layout, params)       r_k above
    terminated(x_next, layout, params)         |x_{k+1}| > rail_limit
    problem(params, horizon=40, ...)           the controller's Problem (CartPoleSwingUpEnv docstring)
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

FORCE_LIMIT = 3.0  # the problem set's bound
START_NOISE = 0.05  # half-width of the uniform draw of every state component about hanging at rest, centred


@dataclass(frozen=True)
class CartPoleParams:
    """The cart-pole task's parameters (the physics is ``torchtraj.models.get("cartpole")``'s).

    Args:
        rail_limit: the rail's half-length; the episode ends when ``|x| > rail_limit``.
        force_limit: the bound ``|F| ≤ force_limit``, the action space.
        start_noise: half-width of the uniform draw of every state component about hanging at rest.
    """

    rail_limit: float = 2.4
    force_limit: float = FORCE_LIMIT
    start_noise: float = START_NOISE

    def __post_init__(self):
        if not self.rail_limit > self.start_noise:
            raise ValueError(f"rail_limit must exceed the start noise {self.start_noise}, got {self.rail_limit!r}")
        object.__setattr__(self, "rail_limit", float(self.rail_limit))


#: The per-instance step ``(x (4,), u (1,), p) -> x_next (4,)`` the environment takes, ``p = env.model_params``.
dynamics = models.get("cartpole").discrete(DT, "rk4")


def reward(x: Tensor, u: Tensor, x_next: Tensor, layout: Layout, params: CartPoleParams) -> Tensor:
    """The environment's reward ``(...)`` of ``x: (..., 4)``, ``u: (..., 1)`` (module docstring), in [0, 1]."""
    upright = 0.5 * (1.0 - torch.cos(x[..., 1]))
    penalty = 0.1 * x[..., 0] ** 2 + 0.01 * x[..., 2] ** 2 + 0.01 * x[..., 3] ** 2 + 0.001 * u[..., 0] ** 2
    return upright * torch.exp(-penalty)


def terminated(x_next: Tensor, layout: Layout, params: CartPoleParams) -> Tensor:
    """Whether ``x_next: (..., 4)`` is off the rail, ``|x| > rail_limit`` ``(...)``."""
    return x_next[..., 0].abs() > params.rail_limit


def problem(params: Optional[CartPoleParams] = None, horizon: int = 40, rail_margin: float = 0.4,
            terminal_weight: float = 1.0) -> Problem:
    """The controller's :class:`~torchtraj.Problem` for a cart-pole of ``params`` (default ``CartPoleParams()``):
    ``horizon`` steps of :data:`dynamics` with the quadratic costs of :class:`CartPoleSwingUpEnv` ("Controller
    problem"), ``terminal_weight`` on the terminal cost, the force bound and the rail ``rail_margin`` inside its
    ends as a state bound. ``x0`` is a placeholder: the controller passes the state."""
    params = CartPoleParams() if params is None else params
    if not isinstance(params, CartPoleParams):
        raise TypeError(f"params must be a CartPoleParams, got {type(params).__name__}")
    dt, inf = DT, np.inf

    def stage(x, u, p):
        e = upright_error(x[1])
        return dt * (x[0] * x[0] + e * e + 0.01 * (x[2] * x[2] + x[3] * x[3] + u[0] * u[0]))

    def terminal(x, p):
        e = upright_error(x[1])
        return terminal_weight * (x[0] * x[0] + e * e + 0.1 * (x[2] * x[2] + x[3] * x[3]))

    model_params = {k: v.to(torch.float64) for k, v in models.get("cartpole").params.items()}
    limit = torch.tensor([params.force_limit], dtype=torch.float64)
    box = torch.tensor([params.rail_limit - rail_margin, inf, inf, inf], dtype=torch.float64)
    return Problem(dynamics=dynamics, stage_cost=stage, terminal_cost=terminal,
                   x0=torch.zeros(4, dtype=torch.float64), horizon=horizon, nu=1, params=model_params,
                   u_lower=-limit, u_upper=limit, x_lower=-box, x_upper=box, dt=dt, name="cartpole_mpc")


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

    ## Controller Problem

    ``env.problem(horizon=40, rail_margin=0.4, terminal_weight=1.0)``
    (``torchtraj.envs.cartpole.problem(env.params, ...)``)
    is the MPC controller's :class:`torchtraj.Problem`, on the environment's own step (:data:`dynamics`), with
    ``e = wrap(θ − π)``::

        minimise  Σ_k dt (x_k² + e_k² + 0.01 (ẋ_k² + θ̇_k² + F_k²)) + w (x_N² + e_N² + 0.1 (ẋ_N² + θ̇_N²)),
        |F_k| ≤ 3,   |x_k| ≤ rail_limit − rail_margin,   N = 40 (2 s),   w = terminal_weight = 1

    Its costs are not the reward, negated, but a quadratic in its place with the same optimum (upright, centred,
    still, unforced): the reward's ``1 − cos θ`` is flat hanging down and its ``exp`` flattens far from the goal, so
    its gradient gives a short-horizon solver little to follow. Measured choices: the pole is up in 4-6 s with
    ``w = 1`` (32 seeds); ``w = 3`` takes 5-6.5 s, ``w = 10`` 6-7 s with the cart out to |x| ≈ 2.1, and horizons
    of 30 or 60 steps do worse than 40. The rail is a state bound ``rail_margin`` inside its ends, as an augmented
    Lagrangian meets a bound only approximately within 3 iterations. Its parameters are ``env.model_params``.

    ## Arguments

    ``gymnasium.make("torchtraj/CartPoleSwingUp-v0", render_mode=None, rail_limit=2.4)``, or
    ``CartPoleSwingUpEnv(max_episode_steps=200, rail_limit=2.4, render_mode=None)``. ``render_mode="rgb_array"``
    draws a 600 × 300 frame. ``reset(options={"state": x0})`` starts from a given state. ``gymnasium.make_vec``
    gives :class:`CartPoleSwingUpVectorEnv`.
    """

    def __init__(self, max_episode_steps: int = 200, rail_limit: float = 2.4, render_mode: Optional[str] = None):
        self.params = CartPoleParams(rail_limit=rail_limit)
        limit = self.params.force_limit
        super().__init__(models.get("cartpole"), [-limit], [limit], 4, max_episode_steps, render_mode, dynamics)

    @property
    def rail_limit(self) -> float:
        """The rail's half-length (m): ``params.rail_limit``."""
        return self.params.rail_limit

    def problem(self, horizon: int = 40, rail_margin: float = 0.4, terminal_weight: float = 1.0) -> Problem:
        """The controller's problem (``## Controller Problem``): ``cartpole.problem(self.params, ...)``."""
        return problem(self.params, horizon, rail_margin, terminal_weight)

    def _sample(self, rng: np.random.Generator):
        noise = self.params.start_noise
        return rng.uniform(-noise, noise, size=4), {}

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        return reward(x, u, x_next, layout, self.params)

    def _terminated(self, x_next: Tensor, layout: Layout) -> Tensor:
        return terminated(x_next, layout, self.params)

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
    """``num_envs`` :class:`CartPoleSwingUpEnv` stepped as one batched torch operation (:mod:`torchtraj.envs.vector`).

    ``CartPoleSwingUpVectorEnv(num_envs, device="cpu", array_type="numpy", render_mode=None,
    max_episode_steps=200, rail_limit=2.4)``; ``gymnasium.make_vec("torchtraj/CartPoleSwingUp-v0", ...)`` builds it.
    """

    env_class = CartPoleSwingUpEnv
