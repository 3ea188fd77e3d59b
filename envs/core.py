"""What every torchtraj environment shares: one :mod:`torchtraj.models` model, stepped in float64 torch.

Each environment is the Markov decision process of a model ``ẋ = f(x, u, p)`` under zero-order hold::

    x_{k+1} = F(x_k, ū_k),   F = rk4(f, dt) = model.discrete(dt, "rk4"),   ū_k = clip(u_k, u_low, u_high)
    r_k = r(x_k, ū_k, x_{k+1}),   terminated_k = T(x_{k+1}),   truncated_k = (k + 1 ≥ max_episode_steps)

A model-based controller that plans with ``env.model``, ``env.model_params`` and ``env.dt`` therefore plans with the
dynamics the environment steps, not with a copy that could drift from it. Quantities drawn at reset that stay fixed
for the episode (the car's obstacles) form the episode's *layout*.

Each task module (:mod:`torchtraj.envs.pendulum`, :mod:`torchtraj.envs.cartpole`, :mod:`torchtraj.envs.car`) is
written as pure functions, in
the manner of Gymnasium's ``phys2d`` environments, around a frozen dataclass of the task's parameters
(``env.params``)::

    dynamics(x, u, p) -> x_next                      the step F the environment takes (per instance)
    reward(x, u, x_next, layout, params) -> r        the reward the environment pays
    terminated(x_next, layout, params) -> bool       where the task ends episodes (cart-pole, car)
    problem(params, horizon, ...) -> Problem         the MPC controller's problem, built on ``dynamics``

The functions broadcast over leading batch dimensions, so one definition serves a controller (one instance, no
batch dimension, as torchtraj's per-instance functions are written) and the environments (``(B, nx)``): the class
methods below call them. ``env.problem(...)`` is ``problem(env.params, ...)``.

The task functions of a subclass (``_observe``, ``_reward``, ``_terminated``, ``_info``) take batch-first tensors
``x: (B, nx)``, ``u: (B, nu)``, layout ``{name: (B, ...)}``, so the native vector environment
(:mod:`torchtraj.envs.vector`)
runs the same definitions over all its sub-environments at once; a single environment calls them with ``B = 1``.
``_sample(rng)`` draws ``(x0, layout)`` for one episode from a numpy generator, in a fixed order, so that a vector
environment that owns one generator per sub-environment reproduces the single environments draw for draw.

Actions are clipped to the action space: an out-of-bounds value (±inf included) acts at the bound, as a saturating
actuator would. A NaN action raises ``ValueError``: no bound is the right answer for it, and stepping it would turn
the state into NaN silently.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Optional

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from torch import Tensor

from torchtraj.core.problem import Problem
from torchtraj.models import Model

DTYPE = torch.float64
Layout = Mapping[str, Tensor]
StepFn = Callable[[Tensor, Tensor, Mapping[str, Tensor]], Tensor]

# every environment here steps at 20 Hz: the cart-pole and car problems' dt (tf / N = 5 / 100), close to the
# pendulum problem's 3 / 50, and one clock for all keeps render_fps a class constant
DT = 0.05


def upright_error(theta: Tensor) -> Tensor:
    """``wrap(θ − π) ∈ [−π, π)``: the angle from upright of a pendulum that hangs at θ = 0 (any shape)."""
    return torch.remainder(theta, 2.0 * torch.pi) - torch.pi


def clip_actions(u: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """``u: (..., nu)`` clipped to ``[low, high]``; raises ``ValueError`` on NaN (module docstring)."""
    nan = torch.isnan(u)
    if bool(nan.any()):
        where = torch.nonzero(nan.reshape(-1, u.shape[-1]).any(-1)).flatten().tolist()
        raise ValueError(f"action contains NaN (rows {where} of the action batch); actions must be numbers")
    return torch.clamp(u, low, high)


class ModelEnv(gym.Env[np.ndarray, np.ndarray]):
    """Base of the torchtraj environments (module docstring); subclasses define the task.

    Args:
        model: the :mod:`torchtraj.models` model the environment steps.
        action_low, action_high: ``(nu,)`` control bounds, the action space.
        observation_size: length of the observation vector.
        max_episode_steps: steps after which an episode is truncated.
        render_mode: ``None`` or ``"rgb_array"``.
        step: the per-instance step ``(x, u, p) -> x_next`` (the task module's ``dynamics``); by default
            ``model.discrete(dt, "rk4")``.

    Attributes a controller reads: ``params`` (the task's frozen parameter dataclass), ``model``,
    ``model_params`` (dict of 0-dim float64 tensors), ``dt``, ``max_episode_steps``, ``state`` (``(nx,)``
    float64 tensor), ``elapsed_steps``, :meth:`observation_to_state`, and :meth:`problem`, the controller's
    :class:`torchtraj.Problem`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    dt = DT
    params: Any = None  # the task's frozen parameter dataclass, set by subclasses

    def __init__(self, model: Model, action_low, action_high, observation_size: int, max_episode_steps: int,
                 render_mode: Optional[str] = None, step: Optional[StepFn] = None):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if int(max_episode_steps) != max_episode_steps or max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}")
        self.model = model
        self.model_params = {k: v.to(DTYPE) for k, v in model.params.items()}
        self.max_episode_steps = int(max_episode_steps)
        self.render_mode = render_mode
        self._step_fn = step if step is not None else model.discrete(self.dt, "rk4")
        low, high = np.asarray(action_low, np.float64), np.asarray(action_high, np.float64)
        self.action_space = spaces.Box(low, high, dtype=np.float64)
        self.observation_space = spaces.Box(-np.inf, np.inf, (observation_size,), dtype=np.float64)
        self._low, self._high = torch.as_tensor(low), torch.as_tensor(high)
        self._x: Optional[Tensor] = None
        self._layout: dict[str, Tensor] = {}
        self.elapsed_steps = 0

    # ------------------------------------------------------------------ task: defined by subclasses
    def _sample(self, rng: np.random.Generator) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Initial state ``(nx,)`` and layout ``{name: array}`` of one episode."""
        raise NotImplementedError

    def _observe(self, x: Tensor, layout: Layout) -> Tensor:
        """Observations ``(B, observation_size)`` of states ``x: (B, nx)``; the state itself by default."""
        return x.clone()

    def _reward(self, x: Tensor, u: Tensor, x_next: Tensor, layout: Layout) -> Tensor:
        """Rewards ``(B,)`` of the transitions ``x → x_next`` under the clipped actions ``u``."""
        raise NotImplementedError

    def _terminated(self, x_next: Tensor, layout: Layout) -> Tensor:
        """Whether ``x_next: (B, nx)`` ends the episode ``(B,)``; never, by default."""
        return torch.zeros(x_next.shape[0], dtype=torch.bool, device=x_next.device)

    def _info(self, x_next: Tensor, layout: Layout) -> dict[str, Tensor]:
        """Per-step diagnostics ``{name: (B,)}``; none by default."""
        return {}

    def _draw(self, x: np.ndarray, layout: Mapping[str, np.ndarray]) -> np.ndarray:
        """An ``(H, W, 3)`` uint8 picture of state ``x: (nx,)``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ what a controller reads
    @property
    def state(self) -> Tensor:
        """The model state ``(nx,)`` (float64 tensor, a copy)."""
        if self._x is None:
            raise RuntimeError("the environment has no state before reset()")
        return self._x.clone()

    def observation_to_state(self, obs):
        """The model state ``(..., nx)`` of observations ``(..., observation_size)``, numpy or torch, as given."""
        state = obs[..., : self.model.nx]
        return state.clone() if isinstance(state, Tensor) else np.array(state, dtype=np.float64)

    def problem(self, **options) -> Problem:
        """The controller's problem for this environment: the task module's ``problem(self.params, **options)``."""
        raise NotImplementedError

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None):
        """Start an episode: ``options={"state": x0}`` starts from ``x0: (nx,)`` instead of a drawn state (the draw
        still happens, so the generator advances as in an ordinary reset)."""
        super().reset(seed=seed)
        options = dict(options or {})
        given = options.pop("state", None)
        if options:
            raise ValueError(f"unknown reset options {sorted(options)}; the only option is 'state'")
        x0, layout = self._sample(self.np_random)
        if given is not None:
            x0 = np.asarray(given, dtype=np.float64)
            if x0.shape != (self.model.nx,):
                raise ValueError(f"options['state'] must have shape ({self.model.nx},), got {x0.shape}")
            if not np.isfinite(x0).all():
                raise ValueError(f"options['state'] must be finite, got {x0.tolist()}")
        self._x = torch.as_tensor(x0, dtype=DTYPE).clone()
        self._layout = {k: torch.as_tensor(v, dtype=DTYPE).clone() for k, v in layout.items()}
        self.elapsed_steps = 0
        return self._observation(), {}

    def step(self, action):
        if self._x is None:
            raise RuntimeError("call reset() before step()")
        u = np.asarray(action, dtype=np.float64)
        if u.size != self.model.nu:
            raise ValueError(f"action must have shape ({self.model.nu},), got {u.shape}")
        u = clip_actions(torch.as_tensor(u.reshape(self.model.nu)), self._low, self._high)
        x_next = self._step_fn(self._x, u, self.model_params)
        x, u1, x1, layout = self._x[None], u[None], x_next[None], self._batched_layout()
        reward = float(self._reward(x, u1, x1, layout)[0])
        terminated = bool(self._terminated(x1, layout)[0])
        info = {k: v[0].item() for k, v in self._info(x1, layout).items()}
        self._x = x_next
        self.elapsed_steps += 1
        truncated = self.elapsed_steps >= self.max_episode_steps
        return self._observation(), reward, terminated, truncated, info

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; make the environment with render_mode='rgb_array'")
            return None
        if self._x is None:
            raise RuntimeError("call reset() before render()")
        return self._draw(self._x.numpy(), {k: v.numpy() for k, v in self._layout.items()})

    # ------------------------------------------------------------------ helpers
    def _batched_layout(self) -> dict[str, Tensor]:
        return {k: v[None] for k, v in self._layout.items()}

    def _observation(self) -> np.ndarray:
        return self._observe(self._x[None], self._batched_layout())[0].numpy().copy()
