"""Swing up and hold torque-limited pendulums with MPC, one batched solve per control step.

Run:  python examples/mpc_pendulum.py [--seeds 4] [--quick]     (saves mpc_pendulum.png when matplotlib is installed)

The environment is ``torchtraj/Pendulum-v0`` (|τ| ≤ 3 < m g l, so the pendulum must be pumped up), as a vector
environment of one sub-environment per seed. The controller's problem is the environment's own (``venv.problem()``,
i.e. envs.pendulum.problem): the step the environment takes, and its reward negated, wrap(θ − π)² + 0.1 ω² +
0.001 τ², over a 1.5 s horizon (N = 30), solved by ``tt.MPC``'s default, the interior point (at most 3 iterations
per control step, one where the plan is feasible after it), warm-started from the previous step's shifted solution. An episode succeeds when the pendulum is within 0.1 rad of upright at every step
of its second half (5 s to 10 s).
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
import torch

import torchtraj as tt  # importing torchtraj registers torchtraj/Pendulum-v0 and the other environments
from torchtraj import envs
from torchtraj.bench import mpc as bench  # the episode runner and the success tests

PLAN_STEPS = (0, 15, 30)  # control steps whose predicted trajectories are drawn


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="episodes, seeded seed .. seed + seeds - 1")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    parser.add_argument("--output", default="mpc_pendulum.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 seeds, 20-step episodes (1 s)")
    args = parser.parse_args(argv)
    seeds, steps = (2, 20) if args.quick else (args.seeds, None)

    venv = gym.make_vec("torchtraj/Pendulum-v0", num_envs=seeds, **({"max_episode_steps": steps} if steps else {}))
    problem = venv.problem()  # the environment hands over its controller's problem: its own step and cost
    mpc = tt.MPC(problem, iterations=3)  # warm-started from the previous step's shifted solution
    print(f"MPC: {mpc}")
    plans = {}

    def keep_plan(t):  # after step t, mpc.X is the plan made from the observation of step t - 1
        if t - 1 in PLAN_STEPS:
            plans[t - 1] = mpc.X[0, :, 0].clone()

    run = bench.run_episodes(venv, mpc, seed=args.seed, on_step=keep_plan, progress=True)
    wins = 0
    for episode in sorted(run.episodes, key=lambda e: e.env):
        ok = bench.pendulum_success(episode)
        wins += ok
        print(f"seed {args.seed + episode.env}: return {episode.total:8.2f}  success: {ok}")
    print(f"success in {wins} of {len(run.episodes)} episodes; {1e3 * np.median(run.step_seconds):.0f} ms per "
          f"batched control step (median)")
    fig = figure(run, plans, venv.dt, venv.single_env.params.torque_limit)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"picture saved to {args.output}")
    return fig


def figure(run, plans, dt, torque_limit):
    """The episodes' angle from upright, angular velocity and torque against time, and episode 0's plans: a
    matplotlib ``Figure``, or ``None`` without matplotlib. The time axis ends 2 s after the last episode settled
    (the rest of each episode holds upright, as the printed success says)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return None
    episodes = sorted(run.episodes, key=lambda e: e.env)
    away = [np.flatnonzero(envs.upright_error(torch.as_tensor(e.observations[:, 0])).abs().numpy() > 0.1)
            for e in episodes]
    settled = max((a[-1] + 1 if len(a) else 0) for a in away)  # the first step after which all stay upright
    shown = min(max(len(e.observations) for e in episodes), settled + int(2.0 / dt))
    fig = Figure(figsize=(13, 3.8), layout="constrained")
    ax = fig.subplots(1, 3)
    for episode in episodes:
        t = np.arange(len(episode.observations))[:shown] * dt
        phi = episode.observations[:shown, 0] - np.pi  # angle from upright: θ = 0 hangs down in the model
        line, = ax[0].plot(t, phi, lw=1.2, label=f"episode {episode.env}")
        ax[1].plot(t, episode.observations[:shown, 1], lw=1.2, color=line.get_color(), label=f"episode {episode.env}")
        ax[2].step(t[:-1][:len(episode.actions)], episode.actions[:shown - 1, 0], where="post", lw=1.2,
                   color=line.get_color(), label=f"episode {episode.env}")
    for step, theta in plans.items():  # episode 0's predictions, 1.5 s ahead
        t = (step + np.arange(len(theta))) * dt
        keep = t <= (shown - 1) * dt
        ax[0].plot(t[keep], (theta - torch.pi).numpy()[keep], "k--", lw=0.8,
                   label="plan of episode 0 (1.5 s)" if step == PLAN_STEPS[0] else None)
    low, high = ax[0].get_ylim()
    low, high = min(low, -np.pi - 0.3), max(high, 0.3)  # hanging (−π) and upright (0) always in view
    for k in range(int(np.ceil(low / (2 * np.pi))), int(np.floor(high / (2 * np.pi))) + 1):  # φ = 2πk is upright
        ax[0].axhline(2 * np.pi * k, color="tab:green", lw=1, ls=":", label="upright" if k == 0 else None)
    ax[0].set_ylim(low, high)
    for bound in (-torque_limit, torque_limit):
        ax[2].axhline(bound, color="tab:red", lw=1, ls="--", label="torque bound ±3 N m" if bound > 0 else None)
    ax[0].set(xlabel="time t [s]", ylabel="angle from upright φ = θ − π [rad]",
              title="pendulum angle (0: upright, −π: hanging)")
    ax[1].set(xlabel="time t [s]", ylabel="angular velocity ω [rad/s]", title="angular velocity")
    ax[2].set(xlabel="time t [s]", ylabel="torque τ [N m]", title="MPC control (first move of each plan)")
    ax[0].legend(fontsize=7, loc="center right")
    ax[1].legend(fontsize=7, loc="upper right")
    ax[2].legend(fontsize=7, loc="lower right")
    length = (max(len(e.observations) for e in episodes) - 1) * dt
    trimmed = f"; first {(shown - 1) * dt:.1f} s of {length:.0f} s shown (then held)" if shown * dt < length else ""
    fig.suptitle(f"MPC swing-up of the torque-limited pendulum (torchtraj/Pendulum-v0), {len(episodes)} episodes"
                 + trimmed)
    return fig


if __name__ == "__main__":
    main()
