"""ALTRO's infeasible start (Howell et al. 2019 §III-B) on the car-escape problem.

The car must leave one walled room for the next. The plain rollout of the initial controls from x0 stays
in the first room (the usual start of iLQR-type solvers; AL-iLQR from it, measured with 5 outer iterations,
reaches the goal only by cutting through a wall, violation 0.24, after 119 s). Started from waypoints (a
state trajectory the dynamics cannot follow), ALTRO's slack controls let it pass through the door and end
collision-free at the goal. Prints both and saves ``car_escape.png`` when matplotlib is installed.

Run:  python examples/car_escape.py [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch

import torchtraj as tt
from torchtraj.core import batching


def collision_margin(X: torch.Tensor, walls: torch.Tensor) -> float:
    """Smallest ``d² − r²`` over knots 1..N-1 and wall circles (negative: inside a wall)."""
    d2 = (X[1:-1, None, :2] - walls[:, :2]).pow(2).sum(-1) - walls[:, 2] ** 2
    return float(d2.min())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", default="car_escape.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: ALTRO stopped after 2 outer x 10 inner iterations (not converged)")
    args = parser.parse_args(argv)
    problem = tt.problems.get("car_escape")
    walls, goal = problem.params["obstacles"], problem.params["goal"]
    options = tt.problems.altro_options("car_escape")
    if args.quick:
        options = dataclasses.replace(options, iterations_outer=2, iterations_inner=10)

    U_init = problem.u_init.expand(problem.N, problem.nu)[None]  # (1, N, nu)
    X_rolled = batching.rollout(  # what iLQR-type solvers start from
        problem.dynamics, problem.x0[None], U_init, problem.batched_params(1))[0]
    start = time.perf_counter()
    escaped = tt.solve(problem, method="altro", X0=problem.X_init, options=options)
    seconds = time.perf_counter() - start

    print(f"rollout of u_init from x0: furthest x {float(X_rolled[:, 0].max()):.2f} (door at x = 5), distance to "
          f"goal {float((X_rolled[-1, :2] - goal[:2]).norm()):.2f}, collision margin {collision_margin(X_rolled, walls):.2e}")
    X = escaped.X[0]
    print(f"ALTRO from the waypoints (infeasible start): status {tt.Status(int(escaped.status[0])).name.lower()}, "
          f"cost {float(escaped.cost[0]):.6g}, max violation {float(escaped.max_violation[0]):.1e}, furthest x "
          f"{float(X[:, 0].max()):.2f}, distance to goal {float((X[-1, :2] - goal[:2]).norm()):.2e}, collision margin "
          f"{collision_margin(X, walls):.2e}, {seconds:.1f} s")
    fig = figure(problem, X_rolled, escaped)
    if fig is not None:
        fig.savefig(args.output, dpi=120)
        print(f"saved {args.output}")
    return fig


def figure(problem, X_rolled, escaped):
    """The walls, the start, the goal, the waypoint guess, the rollout of ``u_init`` and ALTRO's path: a matplotlib
    ``Figure``, or ``None`` without matplotlib."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle
    except ImportError:
        print("matplotlib is not installed: no picture (pip install torchtraj[plot])")
        return None
    fig = Figure(figsize=(9, 5), layout="constrained")
    ax = fig.add_subplot()
    for i, (cx, cy, r) in enumerate(problem.params["obstacles"].tolist()):
        ax.add_patch(Circle((cx, cy), r, color="0.8", label="wall (circles)" if i == 0 else None))
    x0, goal = problem.x0.tolist(), problem.params["goal"].tolist()
    ax.plot(problem.X_init[:, 0], problem.X_init[:, 1], "k:", label="waypoint guess (X0)")
    ax.plot(X_rolled[:, 0], X_rolled[:, 1], "C1", label="rollout of u_init from x0")
    status = tt.Status(int(escaped.status[0])).name.lower()
    ax.plot(escaped.X[0, :, 0].detach(), escaped.X[0, :, 1].detach(), "C0", lw=2,
            label=f"ALTRO from the waypoints ({status})")
    ax.plot(x0[0], x0[1], "o", color="k", ms=6, label="start")
    ax.plot(goal[0], goal[1], "*", color="tab:green", ms=14, label="goal")
    ax.set(aspect="equal", xlabel="x [m]", ylabel="y [m]",
           title="car_escape: leaving the walled room through its door (ALTRO infeasible start)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return fig


if __name__ == "__main__":
    main()
