"""Control Gymnasium's own Pendulum-v1 with torchtraj's MPC, given a torch model of its step.

Run:  python examples/gym_pendulum_v1.py [--seeds 4] [--quick]    (saves gym_pendulum_v1.png when matplotlib is installed)

Nothing here is specific to torchtraj's environments: any Gymnasium environment can be controlled once its step is
written in torch. Pendulum-v1 (gymnasium/envs/classic_control/pendulum.py), with θ = 0 upright, g = 10, m = l = 1,
dt = 0.05, steps by semi-implicit Euler with a speed clip::

    ω' = clip(ω + (3 g / (2 l) sin θ + 3 / (m l²) τ) dt, −8, 8),   θ' = θ + ω' dt,   |τ| ≤ 2

and its reward is −(wrap(θ)² + 0.1 ω² + 0.001 τ²). The MPC minimises that cost, times dt, over N = 20 steps (1 s)
plus the terminal cost wrap(θ)² + 0.1 ω², with the torque bound as a constraint (ALTRO, 5 iterations per step).
Measured over seeds 0-39: N = 20 with 5 iterations averages −150; N = 30 (the torchtraj pendulum's horizon) −182
with 5 and −188 with 3 iterations, N = 50 −287: within a small iteration budget the short horizon is solved better,
and the speed clip, whose derivative is 0 once it binds, hides more of a long plan from the solver.
The observation is [cos θ, sin θ, ω]; the state is (atan2(sin θ, cos θ), ω). All seeds run as one vector
environment (Gymnasium's SyncVectorEnv, seed s + i for episode i) with one batched MPC call per step.

An episode ends upright when |wrap(θ)| ≤ 0.1 at its last step.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

import torchtraj as tt

MAX_SPEED, MAX_TORQUE, DT = 8.0, 2.0, 0.05
PARAMS = {"gravity": torch.tensor(10.0, dtype=torch.float64), "mass": torch.tensor(1.0, dtype=torch.float64),
          "length": torch.tensor(1.0, dtype=torch.float64)}


def wrap(theta):
    """Gymnasium's ``angle_normalize``: θ wrapped into [−π, π)."""
    return torch.remainder(theta + torch.pi, 2.0 * torch.pi) - torch.pi


def pendulum_v1_step(x, u, p):
    """One step of Pendulum-v1 (module docstring): ``x = [θ, ω]``, ``u = [τ]`` (already within the bound)."""
    g, m, l = p["gravity"], p["mass"], p["length"]
    omega = x[1] + (3.0 * g / (2.0 * l) * torch.sin(x[0]) + 3.0 / (m * l * l) * u[0]) * DT
    omega = torch.clamp(omega, -MAX_SPEED, MAX_SPEED)
    return torch.stack([x[0] + omega * DT, omega])


def observation_to_state(obs):
    """``[cos θ, sin θ, ω] (B, 3)`` → ``[θ, ω] (B, 2)``."""
    return torch.stack([torch.atan2(obs[:, 1], obs[:, 0]), obs[:, 2]], -1)


def controller(horizon: int = 20, iterations: int = 5) -> tt.MPC:
    """The MPC of the module docstring."""

    def stage(x, u, p):
        return DT * (wrap(x[0]) ** 2 + 0.1 * x[1] ** 2 + 0.001 * u[0] ** 2)

    def terminal(x, p):
        return wrap(x[0]) ** 2 + 0.1 * x[1] ** 2

    bound = torch.full((1,), MAX_TORQUE, dtype=torch.float64)
    problem = tt.Problem(dynamics=pendulum_v1_step, stage_cost=stage, terminal_cost=terminal,
                         x0=torch.zeros(2, dtype=torch.float64), horizon=horizon, nu=1, params=PARAMS,
                         u_lower=-bound, u_upper=bound, dt=DT, name="pendulum_v1_mpc")
    return tt.MPC(problem, "altro", iterations, observation_to_state=observation_to_state)


def run(seeds: int = 4, seed: int = 0, horizon: int = 20, iterations: int = 5, steps: int = 200):
    """Play one episode of ``steps`` steps per seed ``seed .. seed + seeds − 1``; returns ``(returns (S,),
    θ (S, steps + 1), τ (S, steps))``, θ unwrapped (continuous over full turns, 0 upright as in Pendulum-v1)."""
    env = gym.make_vec("Pendulum-v1", num_envs=seeds, vectorization_mode="sync", max_episode_steps=steps)
    mpc = controller(horizon, iterations)
    obs, _ = env.reset(seed=seed)
    thetas, torques, returns = [observation_to_state(torch.as_tensor(obs, dtype=torch.float64))[:, 0]], [], 0.0
    for _ in range(steps):
        action = mpc(obs.astype(np.float64))
        obs, reward, terminated, truncated, _ = env.step(action)
        returns = returns + reward
        thetas.append(observation_to_state(torch.as_tensor(obs, dtype=torch.float64))[:, 0])
        torques.append(torch.as_tensor(action[:, 0]))
    env.close()  # the episodes are all truncated at the same step: nothing after this is an autoreset
    theta = torch.from_numpy(np.unwrap(torch.stack(thetas, 1).numpy(), axis=1))  # no jumps of 2π at ±π
    return np.asarray(returns), theta, torch.stack(torques, 1)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--horizon", type=int, default=20, help="MPC horizon N (steps of 0.05 s)")
    parser.add_argument("--iterations", type=int, default=5, help="solver iterations per control step")
    parser.add_argument("--output", default="gym_pendulum_v1.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 seeds, 20-step episodes (1 s)")
    args = parser.parse_args(argv)
    seeds, steps = (2, 20) if args.quick else (args.seeds, 200)
    returns, theta, torque = run(seeds, args.seed, args.horizon, args.iterations, steps)
    upright = wrap(theta[:, -1]).abs() <= 0.1
    for i, (r, ok) in enumerate(zip(returns, upright.tolist())):
        print(f"seed {args.seed + i}: return {r:8.2f}  ends upright: {ok}")
    print(f"average return {returns.mean():.2f} over {seeds} seeds; ended upright: {int(upright.sum())} of {seeds}")
    fig = figure(theta, torque)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"picture saved to {args.output}")
    return fig


def figure(theta, torque):
    """Angle from upright (unwrapped) and torque of each episode against time: a matplotlib ``Figure``, or
    ``None`` without matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return None
    t = np.arange(theta.shape[1]) * DT
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    ax = fig.subplots(1, 2)
    for i, (th, tau) in enumerate(zip(theta, torque)):
        line, = ax[0].plot(t, th, lw=1.2, label=f"episode {i}")
        ax[1].step(t[:-1], tau, where="post", lw=1.2, color=line.get_color(), label=f"episode {i}")
    low, high = ax[0].get_ylim()
    low, high = min(low, -np.pi - 0.3), max(high, np.pi + 0.3)  # upright (0) and hanging (±π) in view
    for k in range(int(np.ceil(low / (2 * np.pi))), int(np.floor(high / (2 * np.pi))) + 1):  # 2πk is upright
        ax[0].axhline(2 * np.pi * k, color="tab:green", lw=1, ls=":", label="upright" if k == 0 else None)
    ax[0].set_ylim(low, high)
    for bound in (-MAX_TORQUE, MAX_TORQUE):
        ax[1].axhline(bound, color="tab:red", lw=1, ls="--",
                      label=f"torque bound ±{MAX_TORQUE:g} N m" if bound > 0 else None)
    ax[0].set(xlabel="time t [s]", ylabel="angle from upright θ [rad], unwrapped",
              title="pendulum angle (0: upright, ±π: hanging)")
    ax[1].set(xlabel="time t [s]", ylabel="torque τ [N m]", title="MPC control (first move of each plan)")
    ax[0].legend(fontsize=7, loc="center right")
    ax[1].legend(fontsize=7, loc="best")
    fig.suptitle("Gymnasium's Pendulum-v1 under torchtraj MPC (a torch model of its step, ALTRO)")
    return fig


if __name__ == "__main__":
    main()
