"""ALTRO's infeasible start (papers/altro.md §III-B) on the car-escape problem.

The car must leave one walled room for the next. Started from a rollout of constant controls,
AL-iLQR stays in the first room; started from six waypoints (a state trajectory the dynamics
cannot follow), ALTRO's slack controls let it pass through the door and end collision-free at the
goal. Prints both outcomes and saves ``car_escape.png`` when matplotlib is installed.
"""

from __future__ import annotations

import time

import torch

import torchtraj as tt


def collision_margin(X: torch.Tensor, walls: torch.Tensor) -> float:
    """Smallest ``d² − r²`` over knots 1..N-1 and wall circles (negative: inside a wall)."""
    d2 = (X[1:-1, None, :2] - walls[:, :2]).pow(2).sum(-1) - walls[:, 2] ** 2
    return float(d2.min())


def main() -> None:
    problem = tt.problems.get("car_escape")
    walls, goal = problem.params["obstacles"], problem.params["goal"]
    options = tt.problems.altro_options("car_escape")

    start = time.perf_counter()
    rolled = tt.solve(problem, method="al-ilqr", options=tt.problems.altro_options("car_escape", iterations_outer=5))
    t_rolled = time.perf_counter() - start
    start = time.perf_counter()
    escaped = tt.solve(problem, method="altro", X0=problem.X_init, options=options)
    t_escaped = time.perf_counter() - start

    for label, sol, seconds in (("from a rollout (al-ilqr)", rolled, t_rolled),
                                ("from waypoints (altro, infeasible start)", escaped, t_escaped)):
        X = sol.X[0]
        print(f"{label}: status {tt.Status(int(sol.status[0])).name.lower()}, cost {float(sol.cost[0]):.6g}, "
              f"max violation {float(sol.max_violation[0]):.1e}, furthest x {float(X[:, 0].max()):.2f} "
              f"(door at x = 5), distance to goal {float((X[-1, :2] - goal[:2]).norm()):.2e}, "
              f"collision margin {collision_margin(X, walls):.2e}, {seconds:.1f} s")
    _plot(problem, rolled, escaped)


def _plot(problem, rolled, escaped) -> None:
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle
    except ImportError:
        print("matplotlib is not installed: no picture (pip install torchtraj[plot])")
        return
    fig = Figure(figsize=(8, 4.5))
    ax = fig.add_subplot()
    for cx, cy, r in problem.params["obstacles"].tolist():
        ax.add_patch(Circle((cx, cy), r, color="0.8"))
    ax.plot(problem.X_init[:, 0], problem.X_init[:, 1], "k:", label="waypoint guess")
    ax.plot(rolled.X[0, :, 0], rolled.X[0, :, 1], "C1", label="AL-iLQR from a rollout")
    ax.plot(escaped.X[0, :, 0], escaped.X[0, :, 1], "C0", label="ALTRO, infeasible start")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    fig.savefig("car_escape.png", dpi=120)
    print("saved car_escape.png")


if __name__ == "__main__":
    main()
