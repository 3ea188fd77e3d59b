"""Learn a pendulum's mass, length and damping by imitation, backpropagating through the solver.

The imitation experiment of Amos et al. 2018 ("Differentiable MPC for End-to-end Planning and
Control", §5.3): an expert solves the swing-up with the true model and produces optimal trajectories
from a batch of initial states; a learner with the same cost but wrong physical parameters solves
from the same states, and its parameters are fitted by minimising

    loss(θ) = mean_b |U_b(θ) − U_b*|² + |X_b(θ) − X_b*|²,

whose gradient flows through ``tt.solve`` by implicit differentiation of the KKT conditions
(``torchtraj.differentiation.implicit``). Parameters are learnt in log space (they stay positive) by L-BFGS; every
epoch prints the largest relative parameter error (target: below 1e-3). With matplotlib installed the
loss and error curves are saved to ``learn_dynamics.png``.

Run: ``python examples/learn_dynamics.py [--quick]`` (about a minute on a laptop CPU).
"""

from __future__ import annotations

import argparse
import sys
import time

import torch

import torchtraj as tt
from torchtraj.core.progress import Progress

TRUE = {"mass": 1.0, "length": 0.5, "damping": 0.1}
START = {"mass": 1.6, "length": 0.35, "damping": 0.25}


def swing_up(N: int = 25, dt: float = 0.08) -> tt.Problem:
    """Swing-up to θ = π with unit-scale weights (a well-conditioned version of the problem set's)."""
    model = tt.models.get("pendulum")
    goal = torch.tensor([torch.pi, 0.0], dtype=torch.float64)

    def stage_cost(x, u, p):
        e = x - goal
        return 0.5 * dt * (e[0] ** 2 + 0.1 * e[1] ** 2) + 0.5 * dt * 0.1 * u[0] ** 2

    def terminal_cost(x, p):
        e = x - goal
        return 5.0 * (e @ e)

    return tt.Problem(dynamics=model.discrete(dt), stage_cost=stage_cost, terminal_cost=terminal_cost,
                      x0=torch.zeros(2, dtype=torch.float64), horizon=N, nu=1, params=dict(model.params),
                      u_init=torch.tensor([0.5], dtype=torch.float64), dt=dt, name="swing_up")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=15, help="L-BFGS steps at most")
    parser.add_argument("--batch", type=int, default=8, help="initial states of the demonstrations")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial states")
    parser.add_argument("--plot", default="learn_dynamics.png", help="where the picture goes")
    parser.add_argument("--quick", action="store_true", help="a smoke run: one epoch on two demonstrations")
    args = parser.parse_args(argv)
    epochs, batch = (1, 2) if args.quick else (args.epochs, args.batch)
    torch.manual_seed(args.seed)
    problem = swing_up()
    x0 = torch.stack([torch.empty(batch).uniform_(-0.5, 0.5), torch.empty(batch).uniform_(-0.5, 0.5)], -1)
    x0 = x0.to(torch.float64)
    options = tt.ILQROptions()  # the defaults: solves the KKT certificate accepts (tt.solve calls them CONVERGED)
    # a differentiable solve is refined to round-off by Newton steps: so the expert is exact too
    true_params = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True) for k, v in TRUE.items()}
    expert = tt.solve(problem.with_params(**true_params), x0, options=options)
    assert bool(expert.converged.all()), expert.status
    expert_X, expert_U = expert.X.detach(), expert.U.detach()
    names = list(TRUE)
    log_theta = torch.tensor([START[k] for k in names], dtype=torch.float64).log().requires_grad_(True)
    true = torch.tensor([TRUE[k] for k in names], dtype=torch.float64)
    warm = {"U": torch.zeros_like(expert_U) + problem.u_init}  # each solve starts from the learner's previous solution

    def loss_fn():
        params = dict(zip(names, log_theta.exp()))
        sol = tt.solve(problem.with_params(**params), x0, U0=warm["U"], options=options)
        warm["U"], warm["solution"] = sol.U.detach(), sol
        return ((sol.U - expert_U) ** 2).sum((1, 2)).mean() + ((sol.X - expert_X) ** 2).sum((1, 2)).mean()

    optimizer = torch.optim.LBFGS([log_theta], lr=1.0, max_iter=4, line_search_fn="strong_wolfe")
    history = {"loss": [], "error": [], "X": []}
    start = time.perf_counter()
    print(f"true {TRUE}; learner starts at {START}")
    print("epoch        loss   max rel. parameter error   mass      length    damping")
    with Progress(epochs + 1, "learn_dynamics", unit="epochs") as bar:
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
                theta = log_theta.exp()
                error = float(((theta - true).abs() / true).max())
            sol = warm["solution"]
            history["loss"].append(loss)
            history["error"].append(error)
            history["X"].append(sol.X.detach())
            values = "  ".join(f"{float(v):.6f}" for v in theta)
            bar.write(f"{epoch:5d}  {loss:10.3e}   {error:24.2e}   {values}", file=sys.stdout)
            bar.update(converged=sol.converged, violation=sol.max_violation, loss=loss)
            if error < 1e-8 or (epoch > 1 and loss >= history["loss"][-2]):
                break  # at the truth, or L-BFGS makes no more progress
    print(f"final parameter error {history['error'][-1]:.2e} (target < 1e-3) after "
          f"{time.perf_counter() - start:.0f} s")
    fig = figure(problem, expert_X, history)
    if fig is not None:
        fig.savefig(args.plot, dpi=120)
        print(f"saved {args.plot}")
    history["figure"] = fig
    return history


def figure(problem, expert_X, history):
    """Left: the expert's swing-ups and the learner's before and after learning (angle from upright against time).
    Right: loss and parameter error per epoch. A matplotlib ``Figure``, or ``None`` without matplotlib."""
    try:
        from matplotlib.figure import Figure
        from matplotlib.ticker import MaxNLocator
    except ImportError:
        print("matplotlib is not installed: no picture")
        return None
    t = (torch.arange(problem.N + 1) * problem.dt).numpy()
    fig = Figure(figsize=(12, 4.2), layout="constrained")
    paths, curves = fig.subplots(1, 2)
    for name, X, style in (("expert (true parameters)", expert_X, dict(color="k", lw=2.5, alpha=0.5)),
                           ("learner before", history["X"][0], dict(color="tab:orange", ls=":", lw=1.5)),
                           (f"learner after {len(history['loss']) - 1} epoch(s)", history["X"][-1],
                            dict(color="tab:blue", ls="--", lw=1.5))):
        for b, x in enumerate(X):
            paths.plot(t, (x[:, 0] - torch.pi).numpy(), label=name if b == 0 else None, **style)
    paths.axhline(0.0, color="tab:green", ls=":", lw=1, label="upright (the goal)")
    paths.set(xlabel="time t [s]", ylabel="angle from upright φ = θ − π [rad]",
              title="swing-ups: the learner imitates the expert")
    paths.legend(fontsize=8, loc="lower right")
    epochs = range(len(history["loss"]))
    curves.semilogy(epochs, history["loss"], "o-", label="imitation loss (|U − U*|² + |X − X*|²)")
    curves.semilogy(epochs, history["error"], "s-", label="parameter error, max relative [1]")
    curves.axhline(1e-3, color="gray", ls="--", lw=1, label="target 1e-3")
    curves.set(xlabel="epoch [L-BFGS steps]", ylabel="loss [rad², (rad/s)², (N m)²], rel. error [1]",
               title="learning curves")
    curves.xaxis.set_major_locator(MaxNLocator(integer=True))
    curves.legend(fontsize=8, loc="center right")
    fig.suptitle("Learning a pendulum's mass, length and damping by imitation, through tt.solve's gradients")
    return fig


if __name__ == "__main__":
    main()
