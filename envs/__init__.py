"""Gymnasium environments whose dynamics are torchtraj's models, each with a batched twin stepped in torch.

This folder is the package ``torchtraj.envs``: installed, ``pyproject.toml`` maps it there (no top-level package
named ``envs`` is installed); in a source checkout ``torchtraj/envs/__init__.py`` loads it under that name.

Importing ``torchtraj`` registers::

    torchtraj/Pendulum-v0          PendulumEnv / PendulumVectorEnv                 (torchtraj.models pendulum)
    torchtraj/CartPoleSwingUp-v0   CartPoleSwingUpEnv / CartPoleSwingUpVectorEnv   (torchtraj.models cartpole)
    torchtraj/Car-v0               CarEnv / CarVectorEnv                           (torchtraj.models unicycle)

``gymnasium.make(id)`` builds the single environment and ``gymnasium.make_vec(id, num_envs=B)`` the batched one
(its ``vector_entry_point``; ``vectorization_mode="sync"`` still gives Gymnasium's SyncVectorEnv). The batched one
steps all B sub-environments as one torch operation and returns numpy arrays, as Gymnasium's vector environments
do; ``gymnasium.make_vec(id, num_envs=B, array_type="torch", device=...)`` returns torch tensors on ``device``
instead (:class:`~torchtraj.envs.vector.ModelVectorEnv`). Every episode is
truncated after ``max_episode_steps`` steps (200 by default, 10 s at dt = 0.05) inside the environment itself, so
the vector environment truncates too; the registered ``max_episode_steps`` is the same number, so the TimeLimit
wrapper that ``gymnasium.make`` adds agrees with it. ``gymnasium.make(id, max_episode_steps=k)`` can only shorten
episodes (its TimeLimit sits on top of the environment's own limit); to lengthen them, construct the class
directly or pass ``max_episode_steps`` to ``make_vec``.

Each task module is also the task as pure functions (:mod:`torchtraj.envs.core`):
``torchtraj.envs.pendulum.dynamics`` (the step the environment takes), ``torchtraj.envs.pendulum.reward`` (the reward
it pays), ``torchtraj.envs.pendulum.problem(params, horizon)`` (the MPC
controller's :class:`torchtraj.Problem`, built on the same functions), likewise for ``torchtraj.envs.cartpole`` and
``torchtraj.envs.car``; ``env.problem(...)`` is the problem of an environment instance, single or vector.
"""

from __future__ import annotations

from torchtraj.registration import IDS, MAX_EPISODE_STEPS, register

from .car import CarEnv, CarParams, CarVectorEnv
from .cartpole import CartPoleParams, CartPoleSwingUpEnv, CartPoleSwingUpVectorEnv
from .core import ModelEnv, upright_error
from .pendulum import PendulumEnv, PendulumParams, PendulumVectorEnv
from .vector import ModelVectorEnv

__all__ = [
    "CarEnv", "CarParams", "CarVectorEnv", "CartPoleParams", "CartPoleSwingUpEnv", "CartPoleSwingUpVectorEnv",
    "ModelEnv", "ModelVectorEnv", "PendulumEnv", "PendulumParams", "PendulumVectorEnv", "IDS", "upright_error",
]

register()  # ``import torchtraj`` has done it already (this package imports torchtraj first): a no-op then
