"""Swing up 64 pendulums at once with batched iLQR and show what happened.

Run:  python examples/swing_up.py [--quick]   (saves swing_up.png when matplotlib is installed)

Each instance starts from its own initial state, drawn with the benchmark rule of
torchtraj.problems.sample_x0; one call to tt.solve solves them all together.
"""

import argparse
import time

import torch

import torchtraj as tt


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64, help="number of pendulums solved together")
    parser.add_argument("--output", default="swing_up.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 4 pendulums, at most 10 iterations")
    args = parser.parse_args(argv)
    batch = 4 if args.quick else args.batch

    problem = tt.problems.get("pendulum_unconstrained")
    x0 = tt.problems.sample_x0("pendulum_unconstrained", batch, seed=0)
    options = tt.ILQROptions(iterations=10 if args.quick else 300)
    start = time.perf_counter()
    sol = tt.solve(problem, x0, method="ilqr", options=options)
    seconds = time.perf_counter() - start

    print(sol.summary())
    final_angle = sol.X[:, -1, 0]
    upright = (final_angle - torch.pi).abs() < 0.05
    print(f"solved {batch} swing-ups in {seconds:.2f} s ({1e3 * seconds / batch:.1f} ms per instance)")
    print(f"ended upright (|theta - pi| < 0.05): {int(upright.sum())} of {batch}")
    fig = figure(problem, sol)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"picture saved to {args.output}")
    return fig


def figure(problem, sol):
    """Every instance's angle from upright and torque against time: a matplotlib ``Figure``, or ``None`` without
    matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return None
    t = (torch.arange(problem.N + 1) * problem.dt).numpy()
    fig = Figure(figsize=(11, 3.8), layout="constrained")
    axes = fig.subplots(1, 2)
    for i, (X, U) in enumerate(zip(sol.X.detach(), sol.U.detach())):
        label = "one instance each" if i == 0 else None
        axes[0].plot(t, (X[:, 0] - torch.pi).numpy(), color="tab:blue", alpha=0.3, lw=1, label=label)
        axes[1].step(t[:-1], U[:, 0].numpy(), where="post", color="tab:orange", alpha=0.3, lw=1, label=label)
    axes[0].axhline(0.0, color="tab:green", ls=":", lw=1.2, label="upright (the goal)")
    axes[0].axhline(-torch.pi, color="0.4", ls="--", lw=1, label="hanging")
    axes[0].set(xlabel="time t [s]", ylabel="angle from upright φ = θ − π [rad]",
                title="pendulum angle (0: upright, −π: hanging)")
    axes[1].set(xlabel="time t [s]", ylabel="torque τ [N m]", title="optimal torques (no bound in this problem)")
    axes[0].legend(loc="lower right", fontsize=8)
    axes[1].legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{sol.batch_size} pendulum swing-ups solved together by batched iLQR "
                 f"(pendulum_unconstrained, each from its own initial state)")
    return fig


if __name__ == "__main__":
    main()
