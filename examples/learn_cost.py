"""Recover the goal of a cost from demonstrations that skirt an obstacle.

A car (unicycle) drives to a goal while keeping out of a circle that lies across its way, so the
obstacle constraint is active in every demonstration. The demonstrations are the optimal trajectories
for the true goal ``(x_g, y_g)`` of the cost; a learner that starts from a wrong goal fits them by
minimising the distance of its own optimal trajectories to the demonstrations,

    loss(θ) = mean_b |X_b(θ) − X_b*|²,

with gradients through ``tt.solve(..., method="altro")`` by implicit differentiation of the KKT
conditions, the active obstacle rows held as equalities (``torchtraj.differentiation.implicit``). Every epoch (one
L-BFGS step) prints the loss and the parameter error; with matplotlib installed the curves are saved
to ``learn_cost.png``.

Run: ``python examples/learn_cost.py [--quick]`` (a few minutes on a laptop CPU).
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

import torchtraj as tt
from torchtraj.core.constraints import Constraints
from torchtraj.core.progress import Progress
from torchtraj.solvers.altro.options import ALTROOptions

F64 = torch.float64
TRUE = {"goal": [2.0, 0.3]}
START = {"goal": [1.6, -0.2]}
OBSTACLE = (1.0, -0.1, 0.3)  # centre x, centre y, radius [m]
# ALTRO's defaults reach the KKT points the implicit gradients need (Altro.jl's cost tolerance of 1e-4,
# ALTROOptions.fast(), stops this problem up to 5e-3 above its optimum); the projection to 1e-8
OPTIONS = ALTROOptions(constraint_tolerance=1e-8)


def car_among_obstacle(N: int = 12, dt: float = 0.2) -> tt.Problem:
    """``x = (px, py, θ)``, ``u = (v, ω)``; cost ``½ w |p − g|² + ¼ |u|²``, terminal ``5 |p − g|²``;
    a circle of radius 0.3 at (1, −0.1) on knots 1..N-1: the demonstrations pass above it."""
    model = tt.models.get("unicycle")

    def stage_cost(x, u, p):
        e = x[:2] - p["goal"]
        return 0.5 * p["w"] * (e @ e) + 0.25 * (u @ u)

    def terminal_cost(x, p):
        e = x[:2] - p["goal"]
        return 5.0 * (e @ e)

    def outside(x, p):
        cx, cy, r = OBSTACLE
        return (r * r - (x[0] - cx) ** 2 - (x[1] - cy) ** 2).reshape(1)

    params = {"goal": torch.tensor(START["goal"], dtype=F64), "w": torch.tensor(0.3, dtype=F64)}
    return tt.Problem(dynamics=model.discrete(dt), stage_cost=stage_cost, terminal_cost=terminal_cost,
                      x0=torch.zeros(3, dtype=F64), horizon=N, nu=2, params=params, state_ineq=outside,
                      u_init=torch.tensor([0.5, 0.0], dtype=F64), name="car_obstacle")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=12, help="L-BFGS steps at most")
    parser.add_argument("--plot", default="learn_cost.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: one epoch")
    args = parser.parse_args(argv)
    epochs = 1 if args.quick else args.epochs
    problem = car_among_obstacle()
    x0 = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.05, 0.1], [-0.1, 0.0, -0.1]], dtype=F64)
    true = {"goal": torch.tensor(TRUE["goal"], dtype=F64, requires_grad=True)}
    demo = tt.solve(problem.with_params(**true), x0, method="altro", options=OPTIONS)  # refined to round-off
    assert bool(demo.converged.all()), demo.status
    demo_X = demo.X.detach()
    g = Constraints(problem).evaluate(demo_X, demo.U.detach(), problem.batched_params(x0.shape[0])).ineq
    active = (g > -1e-6).flatten(1).sum(-1).tolist()
    print(f"{x0.shape[0]} demonstrations; obstacle rows active per demonstration: {active}")
    goal = torch.tensor(START["goal"], dtype=F64, requires_grad=True)
    truth = torch.tensor(TRUE["goal"], dtype=F64)
    last = {}

    def loss_fn():
        # cold starts: the loss is then a function of the parameters alone (warm starts may switch between
        # the local optima on either side of the obstacle, which L-BFGS cannot cope with)
        sol = tt.solve(problem.with_params(goal=goal), x0, method="altro", options=OPTIONS)
        last["solution"] = sol
        return ((sol.X - demo_X) ** 2).sum((1, 2)).mean()

    optimizer = torch.optim.LBFGS([goal], lr=1.0, max_iter=3, line_search_fn="strong_wolfe")
    history = {"loss": [], "error": [], "X": []}
    start = time.perf_counter()
    print(f"true goal {TRUE['goal']}; learner starts at goal {START['goal']}")
    print("epoch        loss   max rel. error    goal x    goal y")
    with Progress(epochs + 1, "learn_cost", unit="epochs") as bar:
        for epoch in range(epochs + 1):
            if epoch:
                def closure():
                    optimizer.zero_grad()
                    loss = loss_fn()
                    loss.backward()
                    return loss

                optimizer.step(closure)
            with torch.no_grad():
                loss = float(loss_fn())
                theta = goal.detach()
                error = float(((theta - truth).abs() / truth.abs()).max())
            history["loss"].append(loss)
            history["error"].append(error)
            history["X"].append(last["solution"].X.detach())
            sol = last["solution"]
            bar.write(f"{epoch:5d}  {loss:10.3e}   {error:14.2e}   " + "  ".join(f"{float(v):8.5f}" for v in theta),
                      file=sys.stdout)
            bar.update(converged=sol.converged, violation=sol.max_violation, loss=loss)
            if error < 1e-8 or (epoch > 1 and loss >= history["loss"][-2]):
                break  # at the truth, or L-BFGS makes no more progress
    print(f"final parameter error {history['error'][-1]:.2e} after {time.perf_counter() - start:.0f} s")
    history["goal"] = goal.detach().clone()
    fig = figure(problem, demo_X, history)
    if fig is not None:
        fig.savefig(args.plot, dpi=120)
        print(f"saved {args.plot}")
    history["figure"] = fig
    return history


def figure(problem, demo_X, history):
    """Left: the obstacle, the demonstrations, the learner's trajectories before and after learning, and the true,
    starting and learned goals. Right: loss and parameter error per epoch. A matplotlib ``Figure``, or ``None``
    without matplotlib."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle
        from matplotlib.ticker import MaxNLocator
    except ImportError:
        print("matplotlib is not installed: no picture")
        return None
    fig = Figure(figsize=(13, 5), layout="constrained")
    plane, curves = fig.subplots(1, 2, width_ratios=[2, 1])
    plane.add_patch(Circle(OBSTACLE[:2], OBSTACLE[2], color="0.75", label="obstacle"))
    for b, X in enumerate(demo_X):
        plane.plot(X[:, 0], X[:, 1], "k-", lw=2.5, alpha=0.5, label="demonstrations (true goal)" if b == 0 else None)
    for b, X in enumerate(history["X"][0]):
        plane.plot(X[:, 0], X[:, 1], ":", color="tab:orange", lw=1.5,
                   label="learner before (starting goal)" if b == 0 else None)
    for b, X in enumerate(history["X"][-1]):
        plane.plot(X[:, 0], X[:, 1], "--", color="tab:blue", lw=1.5,
                   label=f"learner after {len(history['loss']) - 1} epoch(s)" if b == 0 else None)
    plane.plot(*TRUE["goal"], "*", color="k", ms=14, label="true goal")
    plane.plot(*START["goal"], "X", color="tab:orange", ms=9, label="starting goal")
    plane.plot(*history["goal"].tolist(), "P", color="tab:blue", ms=9, label="learned goal")
    plane.set(aspect="equal", ylim=(-0.7, 0.7), xlabel="x [m]", ylabel="y [m]",
              title="car paths: demonstrations skirt the obstacle; the learner fits them")
    plane.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=4)
    epochs = range(len(history["loss"]))
    curves.semilogy(epochs, history["loss"], "o-", label="imitation loss mean |X − X*|² [m²]")
    curves.semilogy(epochs, history["error"], "s-", label="goal error, max relative [1]")
    curves.set(xlabel="epoch [L-BFGS steps]", ylabel="loss [m²], relative error [1] (log scale)",
               title="learning curves")
    curves.xaxis.set_major_locator(MaxNLocator(integer=True))
    curves.legend(fontsize=8, loc="center right")
    fig.suptitle("Learning a cost's goal from demonstrations, through tt.solve's implicit gradients")
    return fig


if __name__ == "__main__":
    main()
