"""Learn a pendulum's mass and damping by imitation on several processes, with DistributedDataParallel.

The experiment of ``examples/learn_dynamics.py`` (Amos et al. 2018, §5.3), its batch of demonstrations shared out
over the ranks of a process group: rank r of W holds instances ``torchtraj.distributed.shard(B, r, W)`` and solves
them with :func:`torchtraj.solve` *with gradients* (implicit differentiation of the KKT conditions). The loss of the
whole batch is

    loss(θ) = (1/B) Σ_b |U_b(θ) − U_b*|² + |X_b(θ) − X_b*|²  =  Σ_r loss_r(θ),
    loss_r(θ) = (1/B) Σ_{b in shard r} |U_b(θ) − U_b*|² + |X_b(θ) − X_b*|²,

so each rank backpropagates ``W · loss_r``: DistributedDataParallel averages the ranks' gradients (divides by W)
into exactly ∇loss, and the loss values that L-BFGS's line search compares are summed by one ``all_reduce``. Every
rank then takes the same L-BFGS step, and the learned parameters are those of a one-process run on the same data
(to round-off: the sums are grouped differently).

Run on one machine with two CPU processes::

    torchrun --nproc-per-node 2 examples/learn_dynamics_ddp.py

or as one process, ``python examples/learn_dynamics_ddp.py``. The script runs on CPUs (Gloo); on several GPU nodes
the same training loop runs with ``init_process_group("nccl")``, the problem and the data moved to ``cuda:LOCAL_RANK``
and the launcher's ``--nnodes`` and rendezvous arguments (see :mod:`torchtraj.distributed`).
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from learn_dynamics import TRUE, swing_up  # noqa: E402

import torchtraj as tt  # noqa: E402
from torchtraj import distributed  # noqa: E402

LEARNED = ("mass", "damping")
START = {"mass": 1.6, "damping": 0.25}
#: The interior point (its default options): it reaches points the KKT certificate calls converged on this problem, and
#: only converged instances get implicit gradients.
METHOD, OPTIONS = "ipm", tt.IPOptions()


class Learner(torch.nn.Module):
    """The learnt parameters (in log space: they stay positive) and the solve of a batch with them."""

    def __init__(self, problem: tt.Problem):
        super().__init__()
        self.problem = problem
        self.log_theta = torch.nn.Parameter(torch.tensor([START[k] for k in LEARNED], dtype=torch.float64).log())

    def forward(self, x0: torch.Tensor, U0: torch.Tensor) -> tuple:
        params = dict(zip(LEARNED, self.log_theta.exp()))
        sol = tt.solve(self.problem.with_params(**params), x0, METHOD, U0=U0, options=OPTIONS)
        return sol.X, sol.U


def initial_states(batch: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, 2, generator=g, dtype=torch.float64) - 0.5)


def demonstrations(problem: tt.Problem, x0: torch.Tensor) -> tuple:
    """The expert's ``(X*, U*)`` with the true model, each rank solving its shard (refined by the Newton steps of a
    differentiable solve, so exact to round-off), gathered on every rank."""
    true = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True) for k, v in TRUE.items()}
    expert = distributed.solve(problem.with_params(**true), x0, METHOD, options=OPTIONS, gather="all")
    if not bool(expert.converged.all()):
        raise RuntimeError(f"the expert did not converge: status {expert.status.tolist()}")
    return expert.X.detach(), expert.U.detach()


def train(x0: torch.Tensor, expert_X: torch.Tensor, expert_U: torch.Tensor, problem: tt.Problem, epochs: int,
          max_iter: int = 4, say=print) -> dict:
    """L-BFGS on the imitation loss; returns ``{"theta": learnt parameters (len(LEARNED),), "loss": [per epoch]}``.
    With a process group, every rank calls it with the same data and solves only its shard."""
    rank, size = distributed.world()
    B = x0.shape[0]
    part = distributed.shard(B, rank, size)
    x0, expert_X, expert_U = x0[part], expert_X[part], expert_U[part]
    learner = Learner(problem)
    model = DistributedDataParallel(learner) if size > 1 else learner
    warm = {"U": torch.zeros_like(expert_U) + problem.u_init}  # each solve starts from the previous solution

    def global_loss(X, U) -> torch.Tensor:
        local = (((U - expert_U) ** 2).sum((1, 2)) + ((X - expert_X) ** 2).sum((1, 2))).sum() / B
        total = local.detach().clone()
        if size > 1:
            dist.all_reduce(total)
        return local, total

    def closure():
        optimizer.zero_grad()
        X, U = model(x0, warm["U"])
        warm["U"] = U.detach()
        local, total = global_loss(X, U)
        (local * size).backward()  # DDP divides the summed gradients by size: this leaves ∇ of the global loss
        return total

    optimizer = torch.optim.LBFGS([learner.log_theta], lr=1.0, max_iter=max_iter, line_search_fn="strong_wolfe")
    history = []
    for epoch in range(epochs + 1):
        if epoch:
            optimizer.step(closure)
        with torch.no_grad():
            X, U = learner(x0, warm["U"])
            history.append(float(global_loss(X, U)[1]))
        theta = learner.log_theta.detach().exp()
        say(f"{epoch:5d}  {history[-1]:10.3e}   " + "  ".join(f"{k} {float(v):.9f}" for k, v in zip(LEARNED, theta)))
    return {"theta": learner.log_theta.detach().exp(), "loss": history}


def main(epochs: int = 10, batch: int = 8, seed: int = 0, horizon: int = 25, max_iter: int = 4) -> dict:
    rank, size = distributed.world()
    say = print if rank == 0 else (lambda *a: None)
    problem = swing_up(N=horizon, dt=2.0 / horizon)
    x0 = initial_states(batch, seed)
    expert_X, expert_U = demonstrations(problem, x0)
    say(f"{size} process(es), {batch} demonstrations; true {dict((k, TRUE[k]) for k in LEARNED)}, start {START}")
    result = train(x0, expert_X, expert_U, problem, epochs, max_iter, say)
    truth = torch.tensor([TRUE[k] for k in LEARNED], dtype=torch.float64)
    say(f"final parameter error {float(((result['theta'] - truth).abs() / truth).max()):.2e}")
    return result


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--horizon", type=int, default=25)
    args = parser.parse_args()
    launched = int(os.environ.get("WORLD_SIZE", "1")) > 1
    if launched:
        dist.init_process_group("gloo", timeout=datetime.timedelta(minutes=30))
    try:
        main(args.epochs, args.batch, args.seed, args.horizon)
    finally:
        if launched:
            dist.destroy_process_group()
