"""Swing up 64 pendulums at once with batched iLQR and show what happened.

Run:  python examples/swing_up.py            (saves swing_up.png when matplotlib is installed)

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
    args = parser.parse_args(argv)

    problem = tt.problems.get("pendulum_unconstrained")
    x0 = tt.problems.sample_x0("pendulum_unconstrained", args.batch, seed=0)
    options = tt.ILQROptions(cost_tolerance=1e-8, gradient_tolerance=1e-6)
    start = time.perf_counter()
    sol = tt.solve(problem, x0, method="ilqr", options=options)
    seconds = time.perf_counter() - start

    print(sol.summary())
    final_angle = sol.X[:, -1, 0]
    upright = (final_angle - torch.pi).abs() < 0.05
    print(f"solved {args.batch} swing-ups in {seconds:.2f} s ({1e3 * seconds / args.batch:.1f} ms per instance)")
    print(f"ended upright (|theta - pi| < 0.05): {int(upright.sum())} of {args.batch}")
    _plot(problem, sol, args.output)


def _plot(problem, sol, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed (pip install 'torchtraj[plot]'): no picture")
        return
    t = torch.arange(problem.N + 1) * problem.dt
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for X, U in zip(sol.X, sol.U):
        axes[0].plot(t, X[:, 0], color="tab:blue", alpha=0.3, lw=1)
        axes[1].step(t[:-1], U[:, 0], where="post", color="tab:orange", alpha=0.3, lw=1)
    axes[0].axhline(torch.pi, color="k", ls="--", lw=1, label="upright")
    axes[0].set(xlabel="time [s]", ylabel="angle θ [rad]", title=f"{sol.batch_size} pendulum swing-ups")
    axes[0].legend(loc="lower right")
    axes[1].set(xlabel="time [s]", ylabel="torque τ [N m]", title="controls")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"picture saved to {path}")


if __name__ == "__main__":
    main()
