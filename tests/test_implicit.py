"""Implicit differentiation of solutions against independent references.

* a dense KKT solve of a quadratic program with a known active set, differentiated by plain autograd
  through ``torch.linalg.solve`` (no Riccati, no implicit function theorem);
* ``torch.autograd.gradcheck`` (central differences of re-solves) in float64;
* per-instance solves against the batch; the non-converged policy; float32 against float64.
"""

import dataclasses
import warnings

import pytest
import torch
from torch.func import hessian, jacrev

import torchtraj as tt
from torchtraj import implicit
from torchtraj.batching import rollout
from torchtraj.constraints import Constraints
from torchtraj.solution import History

F64 = torch.float64


# --------------------------------------------------------------------------- small problems
def oscillator(dtype=F64, u_max=None, v_max=None, goal_constraint=False, N=8):
    """A damped linear oscillator with quadratic costs: every constraint linear, so with a fixed
    active set the solution is one linear solve. ``v_max`` bounds the velocity on knots 1..N-1
    (a state-only row); ``u_max`` the control."""
    dt = 0.2

    def dynamics(x, u, p):
        return torch.stack([x[0] + dt * x[1], x[1] + dt * (-p["stiffness"] * x[0] - 0.2 * x[1] + u[0])])

    def stage_cost(x, u, p):
        e = x - p["goal"]
        return 0.5 * p["w"] * (e @ e) + 0.5 * p["r"] * (u @ u)

    def terminal_cost(x, p):
        e = x - p["goal"]
        return 2.5 * (e @ e)

    def t(v):
        return torch.tensor(v, dtype=dtype)

    params = {"stiffness": t(1.5), "goal": t([1.0, 0.0]), "w": t(1.0), "r": t(0.1),
              "v_max": t(0.0 if v_max is None else v_max)}
    return tt.Problem(
        dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost,
        x0=t([0.0, 0.0]), horizon=N, nu=1, params=params,
        state_ineq=(lambda x, p: (x[1] - p["v_max"]).reshape(1)) if v_max is not None else None,
        terminal_eq=(lambda x, p: x - p["goal"]) if goal_constraint else None,
        u_upper=None if u_max is None else t([u_max]),
        u_lower=None if u_max is None else t([-u_max]),
        name="oscillator",
    )


def dense_active_set_qp(problem, x0, params, max_rounds=30):
    """Solve the (convex) QP ``problem`` for one instance by a primal-dual active-set loop on dense KKT
    systems. Returns ``X, U, y, active`` where ``solve(active)`` below reproduces them differentiably."""
    cons = Constraints(problem)
    N, nx, nu = problem.N, problem.nx, problem.nu

    def unpack(z):
        X = z[: (N + 1) * nx].reshape(N + 1, nx)
        return X, z[(N + 1) * nx:].reshape(N, nu)

    def cost(z, p):
        X, U = unpack(z)
        stage = torch.stack([problem.stage_cost(X[k], U[k], p) for k in range(N)]).sum()
        return stage + problem.terminal_cost(X[N], p)

    def equalities(z, x0, p):
        X, U = unpack(z)
        rows = [x0 - X[0]] + [problem.dynamics(X[k], U[k], p) - X[k + 1] for k in range(N)]
        rows += [cons.stage_eq(X[k], U[k], p) for k in range(N)]
        rows.append(cons.terminal_eq(X[N], p))
        return torch.cat(rows)

    def inequalities(z, p):
        X, U = unpack(z)
        mask = cons.ineq_knot_mask
        rows = [cons.stage_ineq(X[k], U[k], p)[mask[k] > 0] for k in range(N)] + [cons.terminal_ineq(X[N], p)]
        return torch.cat(rows)

    nz = (N + 1) * nx + N * nu

    def solve(active, x0, p):
        z0 = torch.zeros(nz, dtype=x0.dtype)
        H, h = hessian(cost)(z0, p), jacrev(cost)(z0, p)
        E = jacrev(equalities)(z0, x0, p)
        e = equalities(z0, x0, p)
        if active.any():
            E = torch.cat([E, jacrev(inequalities)(z0, p)[active]])
            e = torch.cat([e, inequalities(z0, p)[active]])
        K = torch.cat([torch.cat([H, E.T], 1), torch.cat([E, torch.zeros(len(e), len(e), dtype=x0.dtype)], 1)])
        sol = torch.linalg.solve(K, -torch.cat([h, e]))
        return sol[:nz], sol[nz:]

    m = inequalities(torch.zeros(nz, dtype=x0.dtype), params).shape[0]
    active = torch.zeros(m, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(max_rounds):
            z, y = solve(active, x0, params)
            g = inequalities(z, params)
            mu = torch.zeros(m, dtype=x0.dtype)
            mu[active] = y[y.shape[0] - int(active.sum()):]
            new = (active & (mu >= 0)) | (g > 1e-12)
            if torch.equal(new, active):
                break
            active = new
        else:
            raise AssertionError("the active-set loop did not settle")
    return solve, active, g, mu, unpack


def as_solution(X, U, method="altro"):
    """A converged one-instance Solution holding ``X``, ``U`` (for attach_gradients)."""
    B = X.shape[0]
    zeros = torch.zeros(B, dtype=X.dtype)
    return tt.Solution(X=X, U=U, K=torch.zeros(B, U.shape[1], U.shape[2], X.shape[2], dtype=X.dtype), cost=zeros,
                       max_violation=zeros, status=torch.zeros(B, dtype=torch.long), iterations=zeros.long(),
                       history=History.from_rows([]), method=method)


# ---------------------------------------------------------------- the adjoint against dense KKT
QP_CASES = {
    "control_bounds": dict(u_max=0.6),
    "state_inequality": dict(v_max=0.35),
    "goal_equality_and_bounds": dict(u_max=1.6, goal_constraint=True),
    "all": dict(u_max=2.0, v_max=0.7, goal_constraint=True),
}


@pytest.mark.parametrize("case", list(QP_CASES))
def test_adjoint_matches_autograd_through_a_dense_kkt_solve(case):
    problem = oscillator(**QP_CASES[case])
    names = ["stiffness", "goal", "w", "r", "v_max"]
    leaves = {n: problem.params[n].clone().requires_grad_(True) for n in names}
    x0 = torch.tensor([0.3, -0.2], dtype=F64, requires_grad=True)
    solve, active, g, mu, unpack = dense_active_set_qp(problem, x0.detach(), {k: v.detach() for k, v in leaves.items()})
    # the case really has active and inactive inequality rows, strictly complementary
    if problem.constraint_sizes()["state_ineq"] or problem.u_upper is not None:
        assert 0 < int(active.sum()) < active.numel()
        assert mu[active].min() > 1e-6 and g[~active].max() < -1e-6
    # reference: autograd through the dense solve with the active set fixed
    z, y = solve(active, x0, leaves)
    X_ref, U_ref = unpack(z)
    gen = torch.Generator().manual_seed(0)
    X_bar = torch.randn(X_ref.shape, generator=gen, dtype=F64)
    U_bar = torch.randn(U_ref.shape, generator=gen, dtype=F64)
    ref = torch.autograd.grad((X_ref * X_bar).sum() + (U_ref * U_bar).sum(), [x0, *leaves.values()],
                              allow_unused=True)
    # implicit: the same point as a converged Solution
    p = problem.with_params(**leaves)
    sol = implicit.attach_gradients(p, x0.unsqueeze(0), p.batched_params(1),
                                    as_solution(X_ref.detach().unsqueeze(0), U_ref.detach().unsqueeze(0)))
    assert torch.allclose(sol.X[0], X_ref, atol=1e-12) and torch.allclose(sol.U[0], U_ref, atol=1e-12)
    got = torch.autograd.grad((sol.X[0] * X_bar).sum() + (sol.U[0] * U_bar).sum(), [x0, *leaves.values()],
                              allow_unused=True)
    for name, a, b, leaf in zip(["x0"] + names, got, ref, [x0, *leaves.values()]):
        a = torch.zeros_like(leaf) if a is None else a
        b = torch.zeros_like(leaf) if b is None else b
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * (1 + b.abs().max())), (name, a, b)


def test_kkt_multipliers_match_the_dense_solve():
    problem = oscillator(**QP_CASES["all"])
    x0 = torch.tensor([0.3, -0.2], dtype=F64)
    solve, active, _, _, unpack = dense_active_set_qp(problem, x0, problem.params)
    z, y = solve(active, x0, problem.params)
    X, U = unpack(z)
    kkt = implicit.kkt_system(problem, x0.unsqueeze(0), X.unsqueeze(0), U.unsqueeze(0), problem.batched_params(1))
    N, nx = problem.N, problem.nx
    lam = y[: (N + 1) * nx].reshape(N + 1, nx)
    assert torch.allclose(kkt.costate[0], lam, atol=1e-10)
    # the multipliers of the active inequality rows, in the dense solve's order (knot by knot)
    cons = Constraints(problem)
    rows = kkt.nu[0][cons.ineq_knot_mask > 0]
    mu = torch.zeros(active.numel(), dtype=F64)
    mu[active] = y[y.shape[0] - int(active.sum()):]
    goal = y[(N + 1) * nx:(N + 2) * nx]  # the goal rows come before the active inequality rows
    assert int(active.sum()) > 0 and torch.allclose(rows, mu, atol=1e-10)
    assert torch.allclose(kkt.nuN[0], goal, atol=1e-10)
