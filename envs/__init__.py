"""Gymnasium environments whose dynamics are torchtraj's models, each with a native batched twin.

Importing ``envs`` registers::

    torchtraj/Pendulum-v0          PendulumEnv / PendulumVectorEnv                 (torchtraj.models pendulum)
    torchtraj/CartPoleSwingUp-v0   CartPoleSwingUpEnv / CartPoleSwingUpVectorEnv   (torchtraj.models cartpole)
    torchtraj/Car-v0               CarEnv / CarVectorEnv                           (torchtraj.models unicycle)

``gymnasium.make(id)`` builds the single environment and ``gymnasium.make_vec(id, num_envs=B)`` the batched one
(its ``vector_entry_point``; ``vectorization_mode="sync"`` still gives Gymnasium's SyncVectorEnv). Every episode is
truncated after ``max_episode_steps`` steps (200 by default, 10 s at dt = 0.05) inside the environment itself, so
the vector environment truncates too; the registered ``max_episode_steps`` is the same number, so the TimeLimit
wrapper that ``gymnasium.make`` adds agrees with it. ``gymnasium.make(id, max_episode_steps=k)`` can only shorten
episodes (its TimeLimit sits on top of the environment's own limit); to lengthen them, construct the class
directly or pass ``max_episode_steps`` to ``make_vec``.

Each task module is also the task as pure functions (:mod:`envs.core`): ``envs.pendulum.dynamics`` (the step the
environment takes), ``envs.pendulum.reward`` (the reward it pays), ``envs.pendulum.problem(params, horizon)`` (the MPC
controller's :class:`torchtraj.Problem`, built on the same functions), likewise for ``envs.cartpole`` and
``envs.car``; ``env.problem(...)`` is the problem of an environment instance, single or vector.
"""

from __future__ import annotations

import gymnasium as gym

from .car import CarEnv, CarParams, CarVectorEnv
from .cartpole import CartPoleParams, CartPoleSwingUpEnv, CartPoleSwingUpVectorEnv
from .core import ModelEnv, upright_error
from .pendulum import PendulumEnv, PendulumParams, PendulumVectorEnv
from .vector import ModelVectorEnv

__all__ = [
    "CarEnv", "CarParams", "CarVectorEnv", "CartPoleParams", "CartPoleSwingUpEnv", "CartPoleSwingUpVectorEnv",
    "ModelEnv", "ModelVectorEnv", "PendulumEnv", "PendulumParams", "PendulumVectorEnv", "IDS", "upright_error",
]

MAX_EPISODE_STEPS = 200
IDS = ("torchtraj/Pendulum-v0", "torchtraj/CartPoleSwingUp-v0", "torchtraj/Car-v0")

for _id, _name in zip(IDS, ("pendulum:PendulumEnv", "cartpole:CartPoleSwingUpEnv", "car:CarEnv")):
    if _id not in gym.registry:  # importing twice (e.g. through importlib.reload) must not warn
        gym.register(
            id=_id,
            entry_point=f"envs.{_name}",
            vector_entry_point=f"envs.{_name.replace('Env', 'VectorEnv')}",
            max_episode_steps=MAX_EPISODE_STEPS,
        )
