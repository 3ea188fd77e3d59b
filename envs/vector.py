"""Native batched environments: ``B`` copies of one torchtraj environment stepped as one torch operation.

For sub-environments ``i = 0..B−1`` with states ``X: (B, nx)`` and actions ``U: (B, nu)`` one step is::

    X' = vmap(F)(X, clip(U)),   r = r(X, U, X'),   terminated = T(X'),   truncated = (k_i + 1 ≥ max_episode_steps)

with ``F = model.discrete(dt, "rk4")`` and the task functions of the single environment class
(:mod:`torchtraj.envs.core`),
on CPU or CUDA (``device=``), in float64. There is no Python loop over sub-environments in a step; the only loop is
over the sub-environments that restart, to draw their initial states from their own generators (below).

Autoreset is Gymnasium's default ``AutoresetMode.NEXT_STEP`` (``metadata["autoreset_mode"]``): a sub-environment
whose episode ended (terminated or truncated) on step ``k`` ignores its action on step ``k + 1`` and returns the
first observation of its next episode there, with reward 0, ``terminated = truncated = False``.

Seeding follows :class:`gymnasium.vector.SyncVectorEnv`: ``reset(seed=s)`` seeds sub-environment ``i`` with
``s + i`` (a list seeds each one; ``None`` keeps the current generators), and each sub-environment draws its episodes
from its own numpy generator exactly as the single environment does. So this environment matches ``B`` single
environments seeded ``s + i`` step for step, autoresets included.
"""

from __future__ import annotations

from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from torch import Tensor

from torchtraj.core.problem import Problem

from .core import DTYPE, ModelEnv, clip_actions


class ModelVectorEnv(VectorEnv):
    """``num_envs`` copies of ``env_class`` (set by subclasses) stepped together (module docstring).

    Args:
        num_envs: number of sub-environments ``B``.
        device: torch device of the states and of the returned tensors.
        array_type: ``"numpy"`` (Gymnasium's convention) returns numpy arrays; ``"torch"`` returns tensors on
            ``device`` so a GPU controller never copies to the host. Actions may be either in both modes.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render` returns one frame per sub-environment).
        **env_kwargs: the single environment's arguments (``max_episode_steps`` and the task's own).

    Attributes a controller reads: ``params`` (the task's parameters, shared by all sub-environments), ``model``,
    ``model_params`` (float64 tensors on ``device``), ``dt``, ``max_episode_steps``, ``state`` ``(B, nx)``,
    ``elapsed_steps`` ``(B,)``, :meth:`observation_to_state`, and :meth:`problem`, the controller's
    :class:`torchtraj.Problem` (one instance; the controller batches it over the sub-environments).
    """

    env_class: type[ModelEnv] = ModelEnv
    metadata = {"render_modes": ["rgb_array"], "render_fps": 20, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, *, device: Union[str, torch.device] = "cpu", array_type: str = "numpy",
                 render_mode: Optional[str] = None, **env_kwargs: Any):
        if int(num_envs) != num_envs or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if array_type not in ("numpy", "torch"):
            raise ValueError(f"array_type must be 'numpy' or 'torch', got {array_type!r}")
        # a never-reset single environment: the configuration and the task functions both classes share
        self.single_env = env = self.env_class(render_mode=render_mode, **env_kwargs)
        self.num_envs = int(num_envs)
        self.device = torch.device(device)
        self.array_type = array_type
        self.render_mode = render_mode
        self.model, self.dt, self.max_episode_steps, self.params = env.model, env.dt, env.max_episode_steps, env.params
        self.model_params = {k: v.to(self.device) for k, v in env.model_params.items()}
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._step_fn = torch.func.vmap(env._step_fn, in_dims=(0, 0, None))
        self._low, self._high = env._low.to(self.device), env._high.to(self.device)
        self._rngs: list[Optional[np.random.Generator]] = [None] * self.num_envs
        self._x: Optional[Tensor] = None
        self._layout: dict[str, Tensor] = {}
        self._elapsed = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        self._restart = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)

    # ------------------------------------------------------------------ what a controller reads
    @property
    def state(self) -> Tensor:
        """Model states ``(B, nx)`` (float64 tensor on ``device``, a copy)."""
        if self._x is None:
            raise RuntimeError("the environment has no state before reset()")
        return self._x.clone()

    @property
    def elapsed_steps(self) -> Tensor:
        """Steps taken in the current episode of each sub-environment ``(B,)``."""
        return self._elapsed.clone()

    def observation_to_state(self, obs):
        """The model states ``(..., nx)`` of observations ``(..., observation_size)``, numpy or torch."""
        return self.single_env.observation_to_state(obs)

    def problem(self, **options) -> Problem:
        """The controller's problem, the single environment's :meth:`~torchtraj.envs.core.ModelEnv.problem` (CPU)."""
        return self.single_env.problem(**options)

    # ------------------------------------------------------------------ Gymnasium API
    def reset(self, *, seed: Union[int, Sequence[Optional[int]], None] = None, options: Optional[dict] = None):
        """Reset all sub-environments, or those of ``options["reset_mask"]`` (a ``(B,)`` bool array).

        ``options["state"]``: initial states, broadcastable to ``(B, nx)``, instead of drawn ones (the draws still
        happen, as in the single environment).
        """
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)):
            super().reset(seed=int(seed))
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(f"seed must be an int, None or a list of {self.num_envs} seeds, got {len(seeds)} seeds")
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, dtype=bool)))
        given = options.pop("state", None)
        if options:
            raise ValueError(f"unknown reset options {sorted(options)}; known ones are 'reset_mask' and 'state'")
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), got "
                             f"{mask.dtype} {mask.shape}")
        if self._x is None and not mask.all():
            raise ValueError("the first reset() must reset every sub-environment")
        indices = np.flatnonzero(mask)
        for i in indices:
            if seeds[i] is not None or self._rngs[i] is None:
                self._rngs[i], _ = seeding.np_random(seeds[i])
        x0, layout = self._draw_episodes(indices)
        if given is not None:
            x0 = torch.broadcast_to(torch.as_tensor(given, dtype=DTYPE, device=self.device),
                                    (self.num_envs, self.model.nx))[torch.as_tensor(indices, device=self.device)]
            if not bool(torch.isfinite(x0).all()):
                raise ValueError(f"options['state'] must be finite, got {x0.tolist()}")
        self._restart_at(indices, x0, layout)
        return self._out(self.single_env._observe(self._x, self._layout)), {}

    def step(self, actions):
        if self._x is None:
            raise RuntimeError("call reset() before step()")
        u = torch.as_tensor(np.asarray(actions) if not isinstance(actions, Tensor) else actions)
        u = u.to(device=self.device, dtype=DTYPE)
        if u.shape != (self.num_envs, self.model.nu):
            raise ValueError(f"actions must have shape ({self.num_envs}, {self.model.nu}), got {tuple(u.shape)}")
        u = clip_actions(u, self._low, self._high)
        env, x, layout = self.single_env, self._x, self._layout
        x_next = self._step_fn(x, u, self.model_params)
        reward = env._reward(x, u, x_next, layout)
        terminated = env._terminated(x_next, layout)
        info = env._info(x_next, layout)
        self._x, self._elapsed = x_next, self._elapsed + 1
        restart = self._restart
        indices = torch.nonzero(restart).flatten().cpu().numpy()
        if len(indices):
            # next-step autoreset: these ended last step, so their action is ignored and they start over
            x0, layout0 = self._draw_episodes(indices)
            self._restart_at(indices, x0, layout0)
            reward = torch.where(restart, torch.zeros_like(reward), reward)
            terminated = terminated & ~restart
        truncated = self._elapsed >= self.max_episode_steps
        self._restart = terminated | truncated
        obs = env._observe(self._x, self._layout)
        infos: dict[str, Any] = {}
        for key, value in info.items():
            infos[key], infos[f"_{key}"] = self._out(value), self._out(~restart)
        return self._out(obs), self._out(reward), self._out(terminated), self._out(truncated), infos

    def render(self):
        if self.render_mode is None:
            return None
        x = self._x.cpu().numpy()
        layout = {k: v.cpu().numpy() for k, v in self._layout.items()}
        draw = self.single_env._draw
        return tuple(draw(x[i], {k: v[i] for k, v in layout.items()}) for i in range(self.num_envs))

    # ------------------------------------------------------------------ helpers
    def _draw_episodes(self, indices: np.ndarray) -> tuple[Tensor, dict[str, Tensor]]:
        """Initial states ``(k, nx)`` and layouts of sub-environments ``indices``, each from its own generator."""
        draws = [self.single_env._sample(self._rngs[i]) for i in indices]
        x0 = torch.as_tensor(np.stack([d[0] for d in draws]), dtype=DTYPE, device=self.device)
        layout = {k: torch.as_tensor(np.stack([d[1][k] for d in draws]), dtype=DTYPE, device=self.device)
                  for k in draws[0][1]}
        return x0, layout

    def _restart_at(self, indices: np.ndarray, x0: Tensor, layout: dict[str, Tensor]) -> None:
        """Start new episodes at ``indices`` (writes into fresh tensors: returned ones are never changed later)."""
        rows = torch.as_tensor(indices, dtype=torch.long, device=self.device)
        if self._x is None:
            self._x = x0.clone()
            self._layout = {k: v.clone() for k, v in layout.items()}
        else:
            self._x = self._x.index_put((rows,), x0)
            self._layout = {k: v.index_put((rows,), layout[k]) for k, v in self._layout.items()}
        self._elapsed = self._elapsed.index_put((rows,), torch.zeros_like(rows))
        self._restart = self._restart.index_put((rows,), torch.zeros_like(rows, dtype=torch.bool))

    def _out(self, value: Tensor):
        if self.array_type == "torch":
            return value.clone()
        return value.detach().cpu().numpy().copy()
