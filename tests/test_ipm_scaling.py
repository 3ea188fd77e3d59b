"""The interior-point method's scaling of the objective (Wächter & Biegler 2006 §3.8), against IPOPT.

cartpole_unconstrained from start 59 of ``sample_x0(name, 64, seed=0)``: IPOPT (its defaults, gradient-based
scaling) converges in 16 iterations; the IPM without the scaling took another path from its first step and ended
``MAX_ITERATIONS`` (a fixed point of the full step and its second-order correction, ``torchtraj/solvers/ipm/
scaling.py``). IPOPT's scaling factor, objective at each iterate and optimum are in
``tests/data/ipm_objective_scaling.json`` (``tests/data/make_ipm_objective_scaling.py``).
"""

import json
from pathlib import Path

import pytest
import torch

import torchtraj as tt
from torchtraj.core.batch import Batch
from torchtraj.core.batching import rollout
from torchtraj.core.scripted import Scripted
from torchtraj.solvers.ipm.scaling import objective_scale

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def ipopt() -> dict:
    return json.loads((DATA / "ipm_objective_scaling.json").read_text())


def _start(ipopt):
    x0 = tt.problems.sample_x0("cartpole_unconstrained", 64, seed=0)[ipopt["start"]:ipopt["start"] + 1]
    return tt.problems.get("cartpole_unconstrained"), x0


def test_objective_scale_is_ipopts(ipopt):
    problem, x0 = _start(ipopt)
    batch = Batch.build(problem, x0)
    X = rollout(problem.dynamics, batch.x0, batch.U0, batch.params)
    scale = objective_scale(problem, X, batch.U0, batch.params, tt.IPOptions())
    assert abs(float(scale[0]) - ipopt["objective_scale"]) < 1e-12 * ipopt["objective_scale"]


def test_a_recorded_scale_is_the_eager_one_to_the_last_bit(ipopt):
    """A controller scales every step: with ``record=True`` the gradient's norm replays from its record (traced at
    the eighth call) with every bit of the eager one."""
    from torchtraj.core.recorded import TRACE_AT
    from torchtraj.solvers.ipm import scaling

    problem, x0 = _start(ipopt)
    batch = Batch.build(problem, x0)
    X = rollout(problem.dynamics, batch.x0, batch.U0, batch.params)
    eager = objective_scale(problem, X, batch.U0, batch.params, tt.IPOptions(record=False))
    traces = scaling._RECORDED_LARGEST_GRADIENT.traces
    for _ in range(TRACE_AT):
        recorded = objective_scale(problem, X, batch.U0, batch.params, tt.IPOptions(record=True))
    assert scaling._RECORDED_LARGEST_GRADIENT.traces == traces + 1 and torch.equal(recorded, eager)
    replay = next(reversed(scaling._RECORDED_LARGEST_GRADIENT.records.values()))[0]
    assert isinstance(replay, (Scripted, torch.fx.GraphModule))  # traced, not left eager
    assert float(eager[0]) < 1.0  # the scale acts here


def test_cartpole_start_59_takes_ipopts_path_to_its_optimum(ipopt):
    """Before the scaling: ``MAX_ITERATIONS`` here (100 iterations; 1000 by default)."""
    problem, x0 = _start(ipopt)
    sol = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(iterations=100))
    assert sol.status.tolist() == [tt.Status.CONVERGED]
    assert int(sol.iterations[0]) == ipopt["iterations"]
    assert abs(float(sol.cost[0]) - ipopt["cost"]) < 1e-9 * ipopt["cost"]
    U = torch.tensor(ipopt["U"], dtype=torch.float64).reshape(sol.U.shape[1:])
    torch.testing.assert_close(sol.U[0], U, rtol=0, atol=1e-6)
    # IPOPT's iterates: its objective at each of them (the history's cost is the problem's, unscaled)
    path = torch.tensor(ipopt["objective"][:ipopt["iterations"]], dtype=torch.float64)
    torch.testing.assert_close(sol.history.cost[0], path, rtol=1e-9, atol=0)
    # without the scaling the first step already goes elsewhere (J = 261 against IPOPT's 23.7)
    unscaled = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(iterations=2, scaling="none"))
    assert float(unscaled.history.cost[0, 1]) > 5 * ipopt["objective"][1]


def test_multipliers_are_the_problems(reference):
    """The double integrator with its costs times 1000 (``‖∇J(w_0)‖_∞ = 1000``, ``s_f = 0.1``): IPOPT's optimum
    times 1000, and the multipliers 1000 times those of the problem as given (``s_f = 1``), not the scaled ones."""
    problem = tt.problems.get("double_integrator")
    p = problem.params
    heavy = problem.with_params(Q=1000 * p["Q"], R=1000 * p["R"], Qf=1000 * p["Qf"])
    given, scaled = tt.solve(problem, method="ipm"), tt.solve(heavy, method="ipm")
    assert given.status.tolist() == scaled.status.tolist() == [tt.Status.CONVERGED]
    cost = reference["double_integrator"]["ipopt"]["cost"]
    assert abs(float(scaled.cost[0]) - 1000 * cost) < 1e-7 * 1000 * cost  # a tolerance on the scaled error
    # to the five digits that the stop at a scaled error of 1e-8 leaves (unscaled, they would be 0.1 times these)
    torch.testing.assert_close(scaled.costate, 1000 * given.costate, rtol=1e-4, atol=1e-3)
    for name, value in given.multipliers.items():
        torch.testing.assert_close(scaled.multipliers[name], 1000 * value, rtol=1e-4, atol=1e-3)
    assert float(scaled.kkt["stationarity"][0]) < 1e-6


def test_two_sided_bounds_take_ipopts_least_squares_multipliers(monkeypatch):
    """A variable bounded on both sides is one row of IPOPT's NLP (the problem set's references pose every bound so)
    and two rows here: each enters the least-squares multiplier estimate with its share ½
    (solvers/ipm/initialization.py), so that the first step is IPOPT's. quadrotor2d bounds both controls and the
    pitch; with the two rows' own estimate its first controls were 0.013 off IPOPT's, 30 % of the step."""
    pytest.importorskip("casadi")
    from torchtraj.bench import reference
    from torchtraj.core.constraints import Constraints

    problem = tt.problems.get("quadrotor2d")
    cons = Constraints.of(problem)
    share = {name: cons.ineq_share[cons.ineq_blocks[name]].tolist() for name in ("state_ineq", "u_upper", "x_lower")}
    assert share == {"state_ineq": [1.0], "u_upper": [0.5, 0.5], "x_lower": [0.5]}
    options = reference.WarmStartable._ipopt_options
    monkeypatch.setattr(reference.WarmStartable, "_ipopt_options",
                        lambda self, **changes: options(self, max_iter=1, **changes))
    first = reference.ReferenceSolver("quadrotor2d", "ipopt").solve()
    assert first.iterations == 1
    sol = tt.solve(problem, method="ipm", options=tt.IPOptions(iterations=1))
    torch.testing.assert_close(sol.U[0], torch.tensor(first.U, dtype=torch.float64), rtol=0, atol=1e-6)
    torch.testing.assert_close(sol.X[0], torch.tensor(first.X, dtype=torch.float64), rtol=0, atol=1e-6)
