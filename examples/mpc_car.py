"""Drive unicycles to a goal through seeded obstacle fields with MPC, one batched solve per control step.

Run:  python examples/mpc_car.py [--seeds 4]      (saves mpc_car.png when matplotlib is installed)

The environment is ``torchtraj/Car-v0``: each seed draws its own layout of four circles between the start and the
goal (3, 3); the episode ends on reaching the goal (within 0.2) or on a collision. The controller's problem is
the environment's own (``venv.problem()``, i.e. torchtraj.envs.car.problem, on the step the environment takes):
it minimises the squared distance to the goal over a 1.5 s horizon (N = 30), ten times more at its end, with
0 ≤ v ≤ 3, |ω| ≤ 3 and every circle (inflated by 0.15) as constraints. The circles are a per-instance parameter read from
each observation, so one batched ALTRO solve (3 iterations, warm-started) serves every layout. An episode
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
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default="mpc_car.png", help="where the picture goes")
    args = parser.parse_args(argv)

    venv = gym.make_vec("torchtraj/Car-v0", num_envs=args.seeds)
    mpc = bench.controller("car", venv)
    print(f"MPC: {mpc}")
    run = bench.run_episodes(venv, mpc, seed=args.seed)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.car_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:6.2f}  steps {len(episode.rewards):3d}  "
              f"collided: {bool(episode.infos['collided'].any())}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    _plot(run, venv.goal.numpy(), venv.single_env.goal_radius, args.output)


def _plot(run, goal, goal_radius, path):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return
    episodes = sorted(run.episodes, key=lambda e: e.env)[:4]
    fig = Figure(figsize=(3.2 * len(episodes), 3.4))
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(1, len(episodes)))
    for ax, episode in zip(axes, episodes):
        for cx, cy, r in episode.observations[0, 3:].reshape(-1, 3):  # this episode's layout
            ax.add_patch(Circle((cx, cy), r, color="0.6"))
        ax.add_patch(Circle(goal, goal_radius, color="tab:green", alpha=0.5))
        ax.plot(episode.observations[:, 0], episode.observations[:, 1], lw=1.5)
        ax.set(xlim=(-0.5, 3.7), ylim=(-0.5, 3.7), aspect="equal",
               title=f"episode {episode.env}: {'reached' if bench.car_success(episode) else 'failed'}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"picture saved to {path}")


if __name__ == "__main__":
    main()
