"""Small problems shared by several test files."""

import torch

import torchtraj as tt

F64 = torch.float64


def pendulum10(N=10, **changes):
    """The pendulum swinging to 2 rad with O(1) weights (well conditioned, N = 10)."""
    model = tt.models.get("pendulum")

    def stage_cost(x, u, p):
        e = x - p["goal"]
        return 0.5 * (e @ p["Q"] @ e) + 0.5 * p["R"] * (u @ u)

    def terminal_cost(x, p):
        e = x - p["goal"]
        return 0.5 * (e @ p["Qf"] @ e)

    params = dict(model.params, goal=torch.tensor([2.0, 0.0], dtype=F64),
                  Q=torch.diag(torch.tensor([1.0, 0.1], dtype=F64)), R=torch.tensor(0.1, dtype=F64),
                  Qf=10 * torch.eye(2, dtype=F64))
    problem = tt.Problem(dynamics=model.discrete(0.1), stage_cost=stage_cost, terminal_cost=terminal_cost,
                         x0=torch.zeros(2, dtype=F64), horizon=N, nu=1, params=params, name="pendulum10")
    return problem.replace(**changes)
