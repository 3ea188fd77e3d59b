r"""MPC on the torchtraj environments: the controllers, their acceptance runs and their timing.

``python -m torchtraj.bench --mpc`` prints, for every task, the success rate over seeded episodes (episode ``i``
of a run seeded ``s`` is the single environment seeded ``s + i``; a vector environment of B sub-environments plays
them with one batched :class:`~torchtraj.MPC` call per step), and the time per control step at B = 1 and B = 64.

Controllers (:func:`controller`), all ``method="altro"`` without projection, stage costs times ``dt``, and
``e = wrap(θ − π)`` the angle from upright (smooth except at hanging, so the cost pulls towards the nearer upright
side and never treats a full turn as progress)::

    pendulum  N = 30 (1.5 s), 3 iterations:   ℓ = dt (e² + 0.1 ω² + 0.001 τ²),   ℓ_N = e² + 0.1 ω²,   |τ| ≤ 3
    cartpole  N = 40 (2 s),   3 iterations:   ℓ = dt (x² + e² + 0.01 ẋ² + 0.01 θ̇² + 0.01 F²),
                                              ℓ_N = 10 (x² + e² + 0.1 ẋ² + 0.1 θ̇²),   |F| ≤ 3,   |x| ≤ 2 (rail 2.4)
    car       N = 30 (1.5 s), 3 iterations:   ℓ = dt (‖p − g‖² + 0.01 ‖u‖²),   ℓ_N = 10 ‖p − g‖²,
                                              0 ≤ v ≤ 3,  |ω| ≤ 3,  ‖p − c_i‖ ≥ r_i + 0.05 (each sub-environment's
                                              observed obstacles, a per-instance parameter)

The pendulum cost is the environment's own reward (negated); terminal costs stand in for the rest of the episode,
with no terminal equality (the receding horizon cannot always reach the goal within N steps). The cart-pole's rail
is a state bound 0.4 inside the rail, since the augmented Lagrangian meets it only approximately in 3 iterations.
The car's obstacles are inflated by 0.05 for the same reason.

Success of an episode (200 steps, 10 s):

    pendulum  |wrap(θ − π)| ≤ 0.1 at every step of the second half (from 5 s on): upright, and kept there;
    cartpole  never left the rail (not terminated) and |wrap(θ − π)| ≤ 0.1 at every step of the last 2.5 s;
    car       reached the goal (terminated with ``reached_goal``) without a collision.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from ..mpc import MPC
from ..problem import Problem

IDS = {"pendulum": "torchtraj/Pendulum-v0", "cartpole": "torchtraj/CartPoleSwingUp-v0", "car": "torchtraj/Car-v0"}


def upright_error(theta: Tensor) -> Tensor:
    """``wrap(θ − π) ∈ [−π, π)``: the angle from upright of a pendulum that hangs at θ = 0."""
    return torch.remainder(theta, 2.0 * torch.pi) - torch.pi


def _bounds(env) -> tuple[Tensor, Tensor]:
    space = env.single_action_space if hasattr(env, "single_action_space") else env.action_space
    return torch.as_tensor(space.low, dtype=torch.float64), torch.as_tensor(space.high, dtype=torch.float64)


# ---------------------------------------------------------------------------------------------- problems
def pendulum_problem(env, horizon: int = 30) -> Problem:
    """The pendulum controller's problem for a ``torchtraj/Pendulum-v0`` environment (module docstring)."""
    dt = env.dt

    def stage(x, u, p):
        e = upright_error(x[0])
        return dt * (e * e + 0.1 * x[1] * x[1] + 0.001 * u[0] * u[0])

    def terminal(x, p):
        e = upright_error(x[0])
        return e * e + 0.1 * x[1] * x[1]

    low, high = _bounds(env)
    return Problem(dynamics=env.model.discrete(dt, "rk4"), stage_cost=stage, terminal_cost=terminal,
                   x0=torch.zeros(2, dtype=torch.float64), horizon=horizon, nu=1, params=dict(env.model_params),
                   u_lower=low, u_upper=high, dt=dt, name="pendulum_mpc")


def cartpole_problem(env, horizon: int = 40, rail_margin: float = 0.4) -> Problem:
    """The cart-pole controller's problem for a ``torchtraj/CartPoleSwingUp-v0`` environment (module docstring)."""
    dt, limit, inf = env.dt, env.single_env.rail_limit if hasattr(env, "single_env") else env.rail_limit, np.inf

    def stage(x, u, p):
        e = upright_error(x[1])
        return dt * (x[0] * x[0] + e * e + 0.01 * (x[2] * x[2] + x[3] * x[3] + u[0] * u[0]))

    def terminal(x, p):
        e = upright_error(x[1])
        return 10.0 * (x[0] * x[0] + e * e + 0.1 * (x[2] * x[2] + x[3] * x[3]))

    low, high = _bounds(env)
    box = torch.tensor([limit - rail_margin, inf, inf, inf], dtype=torch.float64)
    return Problem(dynamics=env.model.discrete(dt, "rk4"), stage_cost=stage, terminal_cost=terminal,
                   x0=torch.zeros(4, dtype=torch.float64), horizon=horizon, nu=1, params=dict(env.model_params),
                   u_lower=low, u_upper=high, x_lower=-box, x_upper=box, dt=dt, name="cartpole_mpc")


def car_problem(env, horizon: int = 30, margin: float = 0.05) -> Problem:
    """The car controller's problem for a ``torchtraj/Car-v0`` environment (module docstring); its ``obstacles``
    parameter ``(n, 3)`` is a placeholder far away, replaced per call by the observed layouts ``(B, n, 3)``."""
    dt = env.dt
    n = env.single_env.num_obstacles if hasattr(env, "single_env") else env.num_obstacles

    def stage(x, u, p):
        d = x[:2] - p["goal"]
        return dt * ((d * d).sum() + 0.01 * (u * u).sum())

    def terminal(x, p):
        d = x[:2] - p["goal"]
        return 10.0 * (d * d).sum()

    def outside_obstacles(x, p):
        c = p["obstacles"]
        return (c[:, 2] + margin) ** 2 - (x[0] - c[:, 0]) ** 2 - (x[1] - c[:, 1]) ** 2

    low, high = _bounds(env)
    far = torch.tensor([1e3, 1e3, 0.1], dtype=torch.float64).expand(n, 3)
    return Problem(dynamics=env.model.discrete(dt, "rk4"), stage_cost=stage, terminal_cost=terminal,
                   x0=torch.zeros(3, dtype=torch.float64), horizon=horizon, nu=2,
                   params={"goal": env.goal.to(torch.float64).cpu(), "obstacles": far},
                   state_ineq=outside_obstacles if n else None, u_lower=low, u_upper=high,
                   u_init=torch.tensor([1.0, 0.0], dtype=torch.float64), dt=dt, name="car_mpc")


def controller(task: str, env, horizon: Optional[int] = None, iterations: int = 3, **options) -> MPC:
    """The :class:`~torchtraj.MPC` of ``task`` (``"pendulum"``, ``"cartpole"``, ``"car"``) for ``env``, a single or
    vector environment of that task; ``options`` are :class:`~torchtraj.ALTROOptions` fields to change."""
    build = {"pendulum": pendulum_problem, "cartpole": cartpole_problem, "car": car_problem}
    if task not in build:
        raise ValueError(f"unknown task {task!r}; known tasks are {sorted(build)}")
    problem = build[task](env) if horizon is None else build[task](env, horizon=horizon)
    from ..mpc import DEFAULT_ALTRO

    opts = dataclasses.replace(DEFAULT_ALTRO, **options)
    if task != "car":
        return MPC(problem, "altro", iterations, opts)
    n = problem.params["obstacles"].shape[0]
    return MPC(problem, "altro", iterations, opts, observation_to_state=lambda obs: obs[:, :3],
               observation_to_params=lambda obs: {"obstacles": obs[:, 3:].reshape(obs.shape[0], n, 3)})


# ---------------------------------------------------------------------------------------------- episodes
@dataclass
class Episode:
    """One finished episode of sub-environment ``env``: observations ``(T+1, n_obs)`` (first to final), rewards
    ``(T,)``, per-step ``info`` entries ``{name: (T,)}``, and how it ended."""

    env: int
    observations: np.ndarray
    rewards: np.ndarray
    infos: dict
    terminated: bool

    @property
    def total(self) -> float:
        return float(self.rewards.sum())


@dataclass
class Run:
    """Episodes of a vector run, the seconds of each batched policy call, and the policy's last solver status."""

    episodes: list
    step_seconds: list

    def rate(self, success: Callable[[Episode], bool]) -> float:
        return float(np.mean([success(e) for e in self.episodes]))


def run_episodes(venv, policy, episodes_per_env: int = 1, seed: int = 0, on_step: Optional[Callable] = None) -> Run:
    """Play ``episodes_per_env`` episodes on each sub-environment of ``venv`` (next-step autoreset), calling
    ``policy`` once per step on the whole batch of observations and ``policy.reset(mask)`` with the
    sub-environments that just restarted. Sub-environments that are done wait (their extra episodes are dropped)."""
    B = venv.num_envs
    obs, _ = venv.reset(seed=seed)
    history, rewards, infos = [np.asarray(obs)], [np.zeros(B)], [{}]
    start, count = np.zeros(B, dtype=int), np.zeros(B, dtype=int)
    restarted = np.zeros(B, dtype=bool)
    episodes, seconds = [], []
    while (count < episodes_per_env).any():
        tick = time.perf_counter()
        actions = policy(obs)
        seconds.append(time.perf_counter() - tick)
        obs, reward, terminated, truncated, info = venv.step(actions)
        if hasattr(policy, "reset"):
            policy.reset(restarted)
        history.append(np.asarray(obs))
        rewards.append(np.asarray(reward, dtype=np.float64))
        infos.append({k: np.asarray(v) for k, v in info.items() if not k.startswith("_")})
        if on_step is not None:
            on_step(len(history) - 1)
        t = len(history) - 1
        start = np.where(restarted, t, start)
        done = (np.asarray(terminated) | np.asarray(truncated)) & ~restarted
        for i in np.flatnonzero(done & (count < episodes_per_env)):
            a = start[i]
            episodes.append(Episode(
                env=int(i), observations=np.stack([h[i] for h in history[a:t + 1]]),
                rewards=np.array([r[i] for r in rewards[a + 1:t + 1]]),
                infos={k: np.array([inf[k][i] for inf in infos[a + 1:t + 1]]) for k in infos[t]},
                terminated=bool(np.asarray(terminated)[i])))
        count = count + done
        restarted = done
    return Run(episodes, seconds)


# ---------------------------------------------------------------------------------------------- success
def pendulum_success(episode: Episode, tolerance: float = 0.1) -> bool:
    """Upright (``|wrap(θ − π)| ≤ tolerance``) at every step of the episode's second half."""
    theta = torch.as_tensor(episode.observations[:, 0])
    half = len(theta) // 2
    return bool((upright_error(theta[half:]).abs() <= tolerance).all())


def cartpole_success(episode: Episode, tolerance: float = 0.1, hold_steps: int = 50) -> bool:
    """Never left the rail, and upright at every step of the last ``hold_steps`` steps (2.5 s)."""
    theta = torch.as_tensor(episode.observations[-hold_steps:, 1])
    return not episode.terminated and bool((upright_error(theta).abs() <= tolerance).all())


def car_success(episode: Episode) -> bool:
    """Reached the goal without touching an obstacle."""
    return bool(episode.infos["reached_goal"].any()) and not bool(episode.infos["collided"].any())


SUCCESS = {"pendulum": pendulum_success, "cartpole": cartpole_success, "car": car_success}
