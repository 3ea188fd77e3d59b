"""Drive unicycles to a goal through seeded obstacle fields with MPC, one batched solve per control step.

Run:  python examples/mpc_car.py [--seeds 4] [--quick]     (saves mpc_car.png when matplotlib is installed)

The environment is ``torchtraj/Car-v0``: each seed draws its own layout of four circles between the start and the
goal (3, 3); the episode ends on reaching the goal (within 0.2) or on a collision. The controller's problem is
the environment's own (``venv.problem()``, i.e. torchtraj.envs.car.problem, on the step the environment takes):
it minimises the squared distance to the goal over a 1.5 s horizon (N = 30), ten times more at its end, with
0 ≤ v ≤ 3, |ω| ≤ 3 and every circle (inflated by 0.15) as constraints. The circles are a per-instance parameter
read from each observation, so one batched interior-point solve (at most 3 iterations, warm-started) serves every
layout. An episode
succeeds when the car reaches the goal without a collision.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

from torchtraj.bench import mpc as bench  # the controllers' options, the episode runner, the success tests


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--output", default="mpc_car.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 seeds, 20-step episodes (1 s)")
    args = parser.parse_args(argv)
    seeds, steps = (2, 20) if args.quick else (args.seeds, None)

    venv = gym.make_vec("torchtraj/Car-v0", num_envs=seeds, **({"max_episode_steps": steps} if steps else {}))
    mpc = bench.controller("car", venv)
    print(f"MPC: {mpc}")
    run = bench.run_episodes(venv, mpc, seed=args.seed, progress=True)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.car_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:6.2f}  steps {len(episode.rewards):3d}  "
              f"collided: {bool(episode.infos['collided'].any())}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    fig = figure(run, venv.goal.numpy(), venv.single_env.goal_radius)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"picture saved to {args.output}")
    return fig


def figure(run, goal, goal_radius):
    """The path of each of the first four episodes in its own obstacle layout, start and goal marked: a matplotlib
    ``Figure``, or ``None`` without matplotlib."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return None
    episodes = sorted(run.episodes, key=lambda e: e.env)[:4]
    fig = Figure(figsize=(3.4 * len(episodes) + 0.6, 3.9), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(episodes), sharey=True))
    for ax, episode in zip(axes, episodes):
        for i, (cx, cy, r) in enumerate(episode.observations[0, 3:].reshape(-1, 3)):  # this episode's layout
            ax.add_patch(Circle((cx, cy), r, color="0.6", label="obstacle" if i == 0 else None))
        ax.add_patch(Circle(goal, goal_radius, color="tab:green", alpha=0.5, label=f"goal (radius {goal_radius:g} m)"))
        ax.plot(*goal, "*", color="tab:green", ms=10)
        ax.plot(episode.observations[:, 0], episode.observations[:, 1], lw=1.5, color="tab:blue", label="path")
        ax.plot(episode.observations[0, 0], episode.observations[0, 1], "o", color="tab:blue", ms=4, label="start")
        outcome = "reached the goal" if bench.car_success(episode) else (
            "collided" if episode.infos["collided"].any() else "did not arrive")
        ax.set(xlim=(-0.6, 3.8), ylim=(-0.8, 3.8), aspect="equal", xlabel="x [m]",
               title=f"episode {episode.env}: {outcome}")
    axes[0].set_ylabel("y [m]")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("MPC car among seeded obstacles (torchtraj/Car-v0): each episode draws its own layout")
    return fig


if __name__ == "__main__":
    main()
