"""Swing up and balance cart-poles on a finite rail with MPC, one batched solve per control step.

Run:  python examples/mpc_cartpole.py [--seeds 4]      (saves mpc_cartpole.png when matplotlib is installed)

The environment is ``torchtraj/CartPoleSwingUp-v0`` (|F| ≤ 3 N; the episode ends if the cart leaves the rail
|x| ≤ 2.4), one sub-environment per seed. The controller's problem is the environment's own (``venv.problem()``,
i.e. envs.cartpole.problem, on the step the environment takes): it minimises x² + wrap(θ − π)² + 0.01 (ẋ² + θ̇² +
F²) over a 2 s horizon (N = 40) plus x² + wrap(θ − π)² + 0.1 (ẋ² + θ̇²) at its end, with the force bound and
|x| ≤ 2 as constraints (ALTRO, 3 iterations per control step, warm-started). An
episode succeeds when the cart never leaves the rail and the pole is within 0.1 rad of upright at every step of the
last 2.5 s of the 10 s episode.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

from torchtraj import envs  # registers the torchtraj environments; each builds its controller's problem
from torchtraj.bench import mpc as bench  # the controllers' options, the episode runner, the success tests


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="mpc_cartpole.png", help="where the picture goes")
    args = parser.parse_args(argv)

    venv = gym.make_vec("torchtraj/CartPoleSwingUp-v0", num_envs=args.seeds)
    mpc = bench.controller("cartpole", venv)
    print(f"MPC: {mpc}")
    run = bench.run_episodes(venv, mpc, seed=args.seed)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.cartpole_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:7.2f}  largest |x| "
              f"{np.abs(episode.observations[:, 0]).max():.2f}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    _plot(run, venv.dt, venv.single_env.rail_limit, args.output)


def _plot(run, dt, rail, path):
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
        error = envs.upright_error(torch.as_tensor(episode.observations[:, 1])).abs()
        ax[0].plot(t, error, lw=1, label=f"episode {episode.env}")
        ax[1].plot(t, episode.observations[:, 0], lw=1)
    for limit in (-rail, rail):
        ax[1].axhline(limit, color="r", lw=1)
    ax[0].set(xlabel="time [s]", ylabel="|wrap(θ − π)| [rad]", title="pole angle from upright (π: hanging)")
    ax[0].legend(fontsize=7, loc="upper right")
    ax[1].set(xlabel="time [s]", ylabel="x [m]", title="cart position (red: rail ends)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"picture saved to {path}")


if __name__ == "__main__":
    main()
