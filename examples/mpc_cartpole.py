"""Swing up and balance cart-poles on a finite rail with MPC, one batched solve per control step.

Run:  python examples/mpc_cartpole.py [--seeds 4] [--quick]     (saves mpc_cartpole.png when matplotlib is installed)

The environment is ``torchtraj/CartPoleSwingUp-v0`` (|F| ≤ 3 N; the episode ends if the cart leaves the rail
|x| ≤ 2.4), one sub-environment per seed. The controller's problem is the environment's own (``venv.problem()``,
i.e. envs.cartpole.problem, on the step the environment takes): it minimises x² + wrap(θ − π)² + 0.01 (ẋ² + θ̇² +
F²) over a 2 s horizon (N = 40) plus x² + wrap(θ − π)² + 0.1 (ẋ² + θ̇²) at its end, with the force bound and
|x| ≤ 2 as constraints (the interior point, at most 3 iterations per control step, warm-started). An
episode succeeds when the cart never leaves the rail and the pole is within 0.1 rad of upright at every step of the
last 2.5 s of the 10 s episode.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import torchtraj as tt  # importing torchtraj registers torchtraj/CartPoleSwingUp-v0 and the other environments
from torchtraj.bench import mpc as bench  # the episode runner and the success tests


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--output", default="mpc_cartpole.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 seeds, 20-step episodes (1 s)")
    args = parser.parse_args(argv)
    seeds, steps = (2, 20) if args.quick else (args.seeds, None)

    venv = gym.make_vec("torchtraj/CartPoleSwingUp-v0", num_envs=seeds,
                        **({"max_episode_steps": steps} if steps else {}))
    problem = venv.problem()  # the environment hands over its controller's problem: its own step and cost
    mpc = tt.MPC(problem, iterations=3)  # warm-started from the previous step's shifted solution
    print(f"MPC: {mpc}")
    run = bench.run_episodes(venv, mpc, seed=args.seed, progress=True)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.cartpole_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:7.2f}  largest |x| "
              f"{np.abs(episode.observations[:, 0]).max():.2f}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    params = venv.single_env.params
    fig = figure(run, venv.dt, params.rail_limit, params.force_limit)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"picture saved to {args.output}")
    return fig


def figure(run, dt, rail, force_limit):
    """Pole angle from upright, cart position and force against time, one line per episode: a matplotlib
    ``Figure``, or ``None`` without matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return None
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    ax = fig.subplots(1, 3)
    for episode in sorted(run.episodes, key=lambda e: e.env):
        t = np.arange(len(episode.observations)) * dt
        label = f"episode {episode.env}"
        line, = ax[0].plot(t, episode.observations[:, 1] - np.pi, lw=1.2, label=label)  # θ = 0 hangs down
        ax[1].plot(t, episode.observations[:, 0], lw=1.2, color=line.get_color(), label=label)
        ax[2].step(t[:-1], episode.actions[:, 0], where="post", lw=1.2, color=line.get_color(), label=label)
    low, high = ax[0].get_ylim()
    low, high = min(low, -np.pi - 0.3), max(high, 0.3)  # hanging (−π) and upright (0) always in view
    for k in range(int(np.ceil(low / (2 * np.pi))), int(np.floor(high / (2 * np.pi))) + 1):  # φ = 2πk is upright
        ax[0].axhline(2 * np.pi * k, color="tab:green", lw=1, ls=":", label="upright" if k == 0 else None)
    ax[0].set_ylim(low, high)
    for limit in (-rail, rail):
        ax[1].axhline(limit, color="tab:red", lw=1, ls="--", label=f"rail ends ±{rail:g} m" if limit > 0 else None)
    for bound in (-force_limit, force_limit):
        ax[2].axhline(bound, color="tab:red", lw=1, ls="--",
                      label=f"force bound ±{force_limit:g} N" if bound > 0 else None)
    ax[0].set(xlabel="time t [s]", ylabel="pole angle from upright φ = θ − π [rad]",
              title="pole angle (0: upright, −π: hanging)")
    ax[1].set(xlabel="time t [s]", ylabel="cart position x [m]", title="cart position on the rail")
    ax[2].set(xlabel="time t [s]", ylabel="force F [N]", title="MPC control (first move of each plan)")
    for a in ax:
        a.legend(fontsize=7, loc="best")
    fig.suptitle(f"MPC swing-up of the cart-pole on a finite rail (torchtraj/CartPoleSwingUp-v0), "
                 f"{len(run.episodes)} episodes")
    return fig


if __name__ == "__main__":
    main()
