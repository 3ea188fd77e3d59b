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


def oscillator(**changes):
    """A linear oscillator (RK4 of a linear ODE is linear) with quadratic costs, ``|u| ≤ 0.6``, the state row
    ``x₀ ≥ −0.2`` (short of the goal ``x₀ = −0.5``) and a terminal velocity: a linear-quadratic problem."""
    base = dict(
        dynamics=tt.rk4(lambda x, u, p: torch.stack([x[1], u[0] - p["k"] * x[0] - 0.1 * x[1]]), 0.2),
        stage_cost=lambda x, u, p: 0.5 * ((x - p["goal"]) ** 2).sum() + 0.05 * (u * u).sum(),
        terminal_cost=lambda x, p: 5.0 * ((x - p["goal"]) ** 2).sum(),
        state_ineq=lambda x, p: (-0.2 - x[0]).reshape(1),
        terminal_eq=lambda x, p: x[1:] - p["goal"][1:],
        x0=torch.tensor([0.5, 0.0], dtype=F64), horizon=15, nu=1,
        params={"k": torch.tensor(2.0, dtype=F64), "goal": torch.tensor([-0.5, 0.0], dtype=F64)},
        u_lower=torch.tensor([-0.6], dtype=F64), u_upper=torch.tensor([0.6], dtype=F64),
    )
    base.update(changes)
    return tt.Problem(**base)


def powell_circle(x0, N=1):
    """Powell's Maratos example on the unit circle as a problem over N stages: ``x_{k+1} = x_k + u_k`` with
    ``|x_N|² = 1``, cost ``10⁻³ Σ|u_k|² + 2(|x_N|² − 1) − x_{N,1}``, from ``x0`` (a list of two numbers); the optimum
    on the circle is near ``(1, 0)``."""
    return tt.Problem(
        dynamics=lambda x, u, p: x + u,
        stage_cost=lambda x, u, p: 1e-3 * (u * u).sum(),
        terminal_cost=lambda x, p: 2.0 * ((x * x).sum() - 1.0) - x[0],
        terminal_eq=lambda x, p: ((x * x).sum() - 1.0).reshape(1),
        x0=torch.tensor(x0, dtype=F64), horizon=N, nu=2)


def velocity_bounded_double_integrator(dtype=torch.float32):
    """The constrained double integrator a README user writes (issue 23's float32 case): RK4 of ``[v, u]`` with a
    step of 0.1 over 40 steps to the goal ``(1, 0)``, ``|u| ≤ 1`` and ``v ≤ 0.5``; the NLP of
    ``tests/data/make_float32_reference.py`` and ``make_float32_di_reference.py``."""
    def dynamics(x, u, p):
        return torch.stack([x[1], u[0]])

    goal = torch.tensor([1.0, 0.0], dtype=dtype)
    return tt.Problem(
        dynamics=tt.rk4(dynamics, 0.1),
        stage_cost=lambda x, u, p: 0.1 * (u ** 2).sum() + ((x - goal) ** 2).sum(),
        terminal_cost=lambda x, p: 10.0 * ((x - goal) ** 2).sum(),
        state_ineq=lambda x, p: x[1:] - 0.5,  # v <= 0.5
        u_lower=torch.tensor([-1.0], dtype=dtype), u_upper=torch.tensor([1.0], dtype=dtype),
        x0=torch.zeros(2, dtype=dtype), horizon=40, nu=1)
