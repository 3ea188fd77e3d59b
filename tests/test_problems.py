"""The benchmark problems against the problem set and the IPOPT optima it reports (tests/data)."""

import math

import numpy as np
import pytest
import torch
from torch.func import grad, vmap

from torchtraj import Problem, problems

ALL = [
    "double_integrator", "pendulum", "cartpole", "car_3obs", "parallel_park", "car_escape", "quadrotor2d",
    "pendulum_unconstrained", "cartpole_unconstrained",
]

# The problem set's numbers, copied here independently of the package:
# (finite control-bound entries, finite state-bound entries, circles, goal constraint)
CONSTRAINTS = {
    "double_integrator": (2, 2, 0, True),
    "pendulum": (2, 0, 0, True),
    "cartpole": (2, 0, 0, True),
    "car_3obs": (4, 0, 3, True),
    "parallel_park": (4, 4, 0, True),
    "car_escape": (4, 0, 170, True),
    "quadrotor2d": (4, 2, 1, True),
    "pendulum_unconstrained": (0, 0, 0, False),
    "cartpole_unconstrained": (0, 0, 0, False),
}
# Constraint kinds active at the IPOPT optimum: these bounds cannot be looser than the problem set's.
ACTIVE = {
    "double_integrator": {"u", "x"},
    "pendulum": {"u"},
    "cartpole": {"u"},
    "car_3obs": {"u", "circles"},
    "parallel_park": {"x"},
    "car_escape": {"circles"},
    "quadrotor2d": {"u", "x", "circles"},
}
SPREAD = {
    "pendulum": [0.5, 0.5], "double_integrator": [0.3, 0.2], "cartpole": [0.2, 0.3, 0.2, 0.3],
    "car_3obs": [0.2, 0.2, 0.3], "parallel_park": [0.05, 0.05, 0.1], "quadrotor2d": [0.3, 0.3, 0.1, 0.1, 0.1, 0.1],
    "pendulum_unconstrained": [0.5, 0.5], "cartpole_unconstrained": [0.2, 0.3, 0.2, 0.3],
}


def trajectory(reference, name):
    r = reference[name]["ipopt"]
    return torch.tensor(r["X"], dtype=torch.float64), torch.tensor(r["U"], dtype=torch.float64)


def total_cost(P: Problem, X, U):
    stage = vmap(P.stage_cost, in_dims=(0, 0, None))(X[:-1], U, P.params)
    return stage.sum() + P.terminal_cost(X[-1], P.params)


def constraint_values(P: Problem, X, U) -> dict:
    """Each kind of constraint as ``g <= 0`` rows over the knots where it applies."""
    out = {}
    if P.u_lower is not None:
        out["u"] = torch.cat([P.u_lower - U, U - P.u_upper], 1)
    if P.x_lower is not None:
        out["x"] = torch.cat([P.x_lower - X[1:-1], X[1:-1] - P.x_upper], 1)
    if P.state_ineq is not None:
        out["circles"] = vmap(P.state_ineq, in_dims=(0, None))(X[1:-1], P.params)
    if P.terminal_eq is not None:
        out["goal"] = P.terminal_eq(X[-1], P.params).abs()
    return out


def test_names():
    assert problems.names() == ALL
    with pytest.raises(ValueError, match="unknown problem"):
        problems.spec("car_4obs")


def test_a_problem_given_where_its_name_is_expected_is_told_so():
    # a Problem is unhashable, so the lookup itself raised "unhashable type: 'dict'" before
    with pytest.raises(TypeError, match="pass that name"):
        problems.sample_x0(problems.get("pendulum"), 4, 0)


@pytest.mark.parametrize("name", ALL)
def test_reference_satisfies_our_dynamics(reference, name):
    P = problems.get(name)
    X, U = trajectory(reference, name)
    assert X.shape == (P.N + 1, P.nx) and U.shape == (P.N, P.nu)
    tol = 2 * reference[name]["ipopt"]["max_violation"] + 1e-13
    torch.testing.assert_close(X[0], P.x0, rtol=0, atol=tol)
    residual = vmap(P.dynamics, in_dims=(0, 0, None))(X[:-1], U, P.params) - X[1:]
    assert float(residual.abs().max()) < min(tol, 1e-8)


@pytest.mark.parametrize("name", ALL)
def test_reference_cost(reference, name):
    P = problems.get(name)
    X, U = trajectory(reference, name)
    assert float(total_cost(P, X, U)) == pytest.approx(reference[name]["ipopt"]["cost"], rel=1e-10)


@pytest.mark.parametrize("name", ALL)
def test_reference_satisfies_our_constraints(reference, name):
    P = problems.get(name)
    X, U = trajectory(reference, name)
    tol = 2 * reference[name]["ipopt"]["max_violation"] + 1e-13
    values = constraint_values(P, X, U)
    for kind, g in values.items():
        assert float(g.max()) <= tol, kind
    for kind in ACTIVE.get(name, ()):
        assert float(values[kind].max()) > -1e-5, f"{kind} constraints are all inactive at the optimum"


@pytest.mark.parametrize("name", ALL)
def test_constraint_counts(name):
    P = problems.get(name)
    n_u, n_x, n_circles, goal = CONSTRAINTS[name]
    finite = lambda *bounds: sum(int(torch.isfinite(b).sum()) for b in bounds if b is not None)  # noqa: E731
    assert finite(P.u_lower, P.u_upper) == n_u
    assert finite(P.x_lower, P.x_upper) == n_x
    sizes = P.constraint_sizes()
    assert sizes["state_ineq"] == n_circles
    assert sizes["terminal_eq"] == (P.nx if goal else 0)
    assert sizes["stage_eq"] == sizes["stage_ineq"] == sizes["terminal_ineq"] == 0
    assert P.has_constraints == (name in ACTIVE)
    assert ("obstacles" in P.params) == (n_circles > 0)


def test_numbers_from_problems_md():
    """A few entries written out, beyond what the reference cost pins down."""
    s = problems.spec("quadrotor2d")
    assert (s.N, s.tf, s.dt) == (200, 6.0, 0.03)
    np.testing.assert_array_equal(s.u_init, [4.905, 4.905])
    np.testing.assert_array_equal(s.x_upper[2], math.pi / 6)
    np.testing.assert_allclose(np.diag(s.Q), np.array([1, 1, 1, 0.1, 0.1, 0.1]) * 0.03, rtol=1e-15)
    s = problems.spec("parallel_park")
    np.testing.assert_array_equal(s.x_lower[:2], [-0.25, -0.001])
    np.testing.assert_array_equal(s.x_upper[:2], [0.25, 1.501])
    r = 0.425
    np.testing.assert_array_equal(problems.spec("car_3obs").circles, [[0.75, 0.75, r], [1.5, 1.5, r], [2.25, 2.25, r]])
    s = problems.spec("car_escape")
    assert s.circles.shape == (170, 3) and np.all(s.circles[:, 2] == 0.5)
    walls = [(x, y) for x in (0, 5, 10) for y in np.linspace(0, 5, 30)] + [(x, 0) for x in np.linspace(0, 10, 50)]
    walls += [(x, 5) for x in np.concatenate([np.linspace(0, 3, 15), np.linspace(5, 8, 15)])]
    np.testing.assert_array_equal(s.circles[:, :2], walls)
    waypoints = [[2.5, 2.5, 0], [4, 5, 0.785], [5, 6.25, 0], [7.5, 6.25, -0.261], [9, 5, -1.57], [7.5, 2.5, 0]]
    np.testing.assert_allclose(s.X_init[::20], waypoints, rtol=0, atol=1e-15)
    np.testing.assert_allclose(s.X_init[10], (s.X_init[0] + s.X_init[20]) / 2, rtol=0, atol=1e-15)
    assert problems.get("car_escape").X_init.shape == (101, 3)
    with pytest.raises(ValueError):
        s.Q[0, 0] = 1.0  # read-only


@pytest.mark.parametrize("twin", ["pendulum", "cartpole"])
def test_unconstrained_twins(twin):
    a, b = problems.spec(twin), problems.spec(f"{twin}_unconstrained")
    for key in ("N", "tf", "x0", "goal", "Q", "R", "Qf", "u_init", "spread"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    assert a.goal_constraint and not b.goal_constraint
    assert np.all(np.isinf(b.u_lower)) and np.all(np.isinf(b.u_upper))


@pytest.mark.parametrize("name", list(SPREAD))
def test_sample_x0(name):
    x0 = problems.sample_x0(name, 7, seed=3)
    nx = problems.spec(name).nx
    assert x0.shape == (7, nx) and x0.dtype == torch.float64
    expected = problems.spec(name).x0 + np.random.default_rng(3).uniform(-1, 1, (7, nx)) * np.array(SPREAD[name])
    np.testing.assert_array_equal(x0.numpy(), expected)
    torch.testing.assert_close(problems.sample_x0(name, 7, seed=3), x0, rtol=0, atol=0)
    assert not torch.equal(problems.sample_x0(name, 7, seed=4), x0)


def test_sample_x0_undefined_for_car_escape():
    with pytest.raises(ValueError, match="spread"):
        problems.sample_x0("car_escape", 4, seed=0)


def test_float32(reference):
    P = problems.get("car_3obs", dtype=torch.float32)
    assert P.dtype == torch.float32
    assert all(v.dtype == torch.float32 for v in P.params.values())
    assert all(t.dtype == torch.float32 for t in (P.u_lower, P.u_upper, P.u_init))
    X, U = trajectory(reference, "car_3obs")
    X, U = X.float(), U.float()
    assert P.dynamics(X[0], U[0], P.params).dtype == torch.float32
    assert float(total_cost(P, X, U)) == pytest.approx(reference["car_3obs"]["ipopt"]["cost"], rel=1e-5)


def test_gradients_reach_cost_and_obstacle_parameters(reference):
    P = problems.get("car_3obs")
    X, U = trajectory(reference, "car_3obs")

    def objective(params):
        stage = vmap(P.stage_cost, in_dims=(0, 0, None))(X[:-1], U, params).sum()
        circles = vmap(P.state_ineq, in_dims=(0, None))(X[1:-1], params).sum()
        return stage + P.terminal_cost(X[-1], params) + circles

    g = grad(objective)(P.params)
    for key in ("goal", "Q", "R", "Qf", "obstacles"):
        assert g[key].shape == P.params[key].shape and bool(g[key].abs().sum() > 0), key
