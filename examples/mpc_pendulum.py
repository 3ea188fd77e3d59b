"""Swing up and hold torque-limited pendulums with MPC, one batched solve per control step.

Run:  python examples/mpc_pendulum.py [--seeds 4]      (saves mpc_pendulum.png when matplotlib is installed)

The environment is ``torchtraj/Pendulum-v0`` (|τ| ≤ 3 < m g l, so the pendulum must be pumped up), as a vector
environment of one sub-environment per seed. The controller's problem is the environment's own (``venv.problem()``,
i.e. envs.pendulum.problem): the step the environment takes, and its reward negated, wrap(θ − π)² + 0.1 ω² +
0.001 τ², over a 1.5 s horizon (N = 30), solved with ALTRO, 3 iterations per control step, warm-started from the
previous step's shifted solution. An episode succeeds when the pendulum is within 0.1 rad of upright at every step
of its second half (5 s to 10 s).
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from torchtraj import envs  # registers the torchtraj environments; each builds its controller's problem
from torchtraj.bench import mpc as bench  # the controllers' options, the episode runner, the success tests

PLAN_STEPS = (0, 15, 30)  # control steps whose predicted trajectories are drawn


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="mpc_pendulum.png", help="where the picture goes")
    args = parser.parse_args(argv)

    venv = gym.make_vec("torchtraj/Pendulum-v0", num_envs=args.seeds)
    mpc = bench.controller("pendulum", venv)
    print(f"MPC: {mpc}")
    plans = {}

    def keep_plan(t):  # after step t, mpc.X is the plan made from the observation of step t - 1
        if t - 1 in PLAN_STEPS:
            plans[t - 1] = mpc.X[0, :, 0].clone()

    run = bench.run_episodes(venv, mpc, seed=args.seed, on_step=keep_plan)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.pendulum_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:8.2f}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    _plot(run, plans, venv.dt, args.output)


def _plot(run, plans, dt, path):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return
    fig = Figure(figsize=(10, 3.6))
    FigureCanvasAgg(fig)
    ax = fig.subplots(1, 2)
    for episode in sorted(run.episodes, key=lambda e: e.env):
        t = np.arange(len(episode.observations)) * dt
        error = envs.upright_error(torch.as_tensor(episode.observations[:, 0])).abs()
        ax[0].plot(t, error, lw=1, label=f"episode {episode.env}")
        ax[1].plot(t, episode.observations[:, 1], lw=1)
    for step, theta in plans.items():  # episode 0's predictions, 1.5 s ahead
        t = (step + np.arange(len(theta))) * dt
        label = "predicted (episode 0)" if step == 0 else None
        ax[0].plot(t, envs.upright_error(theta).abs(), "k--", lw=0.8, label=label)
    ax[0].set(xlabel="time [s]", ylabel="|wrap(θ − π)| [rad]", title="angle from upright (π: hanging)")
    ax[0].legend(fontsize=7, loc="upper right")
    ax[1].set(xlabel="time [s]", ylabel="ω [rad/s]", title="angular velocity")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"picture saved to {path}")


if __name__ == "__main__":
    main()
