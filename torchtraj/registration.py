"""The Gymnasium ids of torchtraj's environments, registered by ``import torchtraj``.

Registration only records strings (``gymnasium.register`` imports an entry point when ``gymnasium.make`` builds
the environment), so ``import torchtraj`` stays cheap and ``gymnasium.make("torchtraj/Pendulum-v0")`` works
without importing :mod:`torchtraj.envs` first::

    torchtraj/Pendulum-v0          torchtraj.envs.pendulum:PendulumEnv / PendulumVectorEnv
    torchtraj/CartPoleSwingUp-v0   torchtraj.envs.cartpole:CartPoleSwingUpEnv / CartPoleSwingUpVectorEnv
    torchtraj/Car-v0               torchtraj.envs.car:CarEnv / CarVectorEnv
"""

from __future__ import annotations

#: Steps after which every episode is truncated (10 s at dt = 0.05), also the registered ``max_episode_steps``.
MAX_EPISODE_STEPS = 200

#: ``id -> (module, environment class)`` of each registered environment; the vector class is ``<Name>VectorEnv``.
ENVIRONMENTS = {
    "torchtraj/Pendulum-v0": ("pendulum", "PendulumEnv"),
    "torchtraj/CartPoleSwingUp-v0": ("cartpole", "CartPoleSwingUpEnv"),
    "torchtraj/Car-v0": ("car", "CarEnv"),
}
IDS = tuple(ENVIRONMENTS)


def register() -> None:
    """Register :data:`IDS` with Gymnasium; a second call (e.g. after ``importlib.reload``) changes nothing."""
    import gymnasium as gym

    for env_id, (module, name) in ENVIRONMENTS.items():
        if env_id in gym.registry:
            continue
        gym.register(id=env_id, entry_point=f"torchtraj.envs.{module}:{name}",
                     vector_entry_point=f"torchtraj.envs.{module}:{name.replace('Env', 'VectorEnv')}",
                     max_episode_steps=MAX_EPISODE_STEPS)
