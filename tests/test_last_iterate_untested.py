"""The last iterate untested (``test_last_iterate=False``, the IPM's and eILQR's options), as their control steps run.

Where the iterations run out, the tested solve expands its last iterate to test it; the untested one evaluates the
functions' values there alone. Everything but the status must be the tested solve's: the same iterates, gains and
multipliers to the last bit, the same cost and violation; the status says ``MAX_ITERATIONS`` where the test would
have said ``CONVERGED`` at the cap, and keeps every status told before it.
"""

import dataclasses

import pytest
import torch

import torchtraj as tt
import torchtraj.solvers.eilqr.solver as eilqr_solver
import torchtraj.solvers.eilqr.verdicts as eilqr_verdicts
import torchtraj.solvers.ipm.solver as ipm_solver
from torchtraj import envs, problems

STATES = torch.tensor([[0.3, 2.0], [3.0, 0.2], [0.05, 0.0]], dtype=torch.float64)
MODULES = {"ipm": ipm_solver, "eilqr": eilqr_verdicts}  # where each method calls its expansion


def counting_expansions(monkeypatch, method) -> list:
    """A list that grows by one at every expansion of the method's iterations."""
    module = MODULES[method]
    calls, expand = [], module.expand
    monkeypatch.setattr(module, "expand", lambda *a: calls.append(1) or expand(*a))
    return calls


def solve(problem, x0, method, cap, tested):
    solver = tt.solvers.get(method)
    options = dataclasses.replace(solver.default_options(), iterations=cap, test_last_iterate=tested)
    return tt.solve(problem, x0, method=method, options=options)


def assert_same_point(a: tt.Solution, b: tt.Solution) -> None:
    for name in ("X", "U", "K", "costate", "iterations"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.multipliers.keys() == b.multipliers.keys()
    assert all(torch.equal(a.multipliers[k], b.multipliers[k]) for k in a.multipliers)
    torch.testing.assert_close(a.cost, b.cost, rtol=1e-14, atol=0)
    torch.testing.assert_close(a.max_violation, b.max_violation, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("method", ["ipm", "eilqr"])
@pytest.mark.parametrize("cap", [1, 3])
def test_a_capped_solve_untested_ends_at_the_tested_ones_point_with_one_expansion_fewer(monkeypatch, method, cap):
    problem = problems.get("car_3obs")  # stage and terminal rows, the obstacles nonconvex
    x0 = problem.x0 + torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.1, 0.2]], dtype=torch.float64)
    calls = counting_expansions(monkeypatch, method)
    tested = solve(problem, x0, method, cap, True)
    expansions = len(calls)
    untested = solve(problem, x0, method, cap, False)
    assert len(calls) - expansions == expansions - 1
    assert_same_point(tested, untested)
    assert (tested.status == tt.Status.MAX_ITERATIONS).all()
    assert torch.equal(untested.status, tested.status)
    assert untested.kkt is not None  # the certificate's residuals are reported all the same


@pytest.mark.parametrize("method", ["ipm", "eilqr"])
def test_an_untested_instance_reports_max_iterations_where_the_test_would_have_said_converged(method):
    problem = problems.get("pendulum")
    x0 = torch.tensor([[0.0, 0.0], [0.5, 0.0]], dtype=torch.float64)
    full = tt.solve(problem, x0, method=method)
    assert (full.status == tt.Status.CONVERGED).all() and full.iterations[0] != full.iterations[1]
    cap = int(full.iterations.max())  # the slower instance converges at the cap, the other one before it
    slower = int(full.iterations.argmax())
    tested, untested = solve(problem, x0, method, cap, True), solve(problem, x0, method, cap, False)
    assert (tested.status == tt.Status.CONVERGED).all()
    assert_same_point(tested, untested)
    expected = tested.status.clone()
    expected[slower] = int(tt.Status.MAX_ITERATIONS)
    assert torch.equal(untested.status, expected)


def test_an_ipms_untested_last_iterate_that_is_not_finite_is_told_for_that_instance_alone(monkeypatch):
    values = ipm_solver.last_values

    def broken_first(*args):  # the first instance's cost is NaN at the last iterate
        J, violation, finite = values(*args)
        J = J.clone()
        J[0] = float("nan")
        return J, violation, finite & torch.isfinite(J)

    monkeypatch.setattr(ipm_solver, "last_values", broken_first)
    sol = solve(problems.get("pendulum"), STATES, "ipm", 2, False)
    assert sol.status.tolist() == [int(tt.Status.NON_FINITE)] + [int(tt.Status.MAX_ITERATIONS)] * 2


def test_an_eilqr_untested_last_iterate_that_is_not_finite_is_told_for_that_instance_alone(monkeypatch):
    """eILQR tells an untested last iterate from the cost and violation its solution evaluates there."""
    solution_of = eilqr_solver._solution

    def broken_first(*args):  # the first instance's cost is NaN at the last iterate
        sol = solution_of(*args)
        cost = sol.cost.clone()
        cost[0] = float("nan")
        return dataclasses.replace(sol, cost=cost)

    monkeypatch.setattr(eilqr_solver, "_solution", broken_first)
    sol = solve(problems.get("pendulum"), STATES, "eilqr", 2, False)
    assert sol.status.tolist() == [int(tt.Status.NON_FINITE)] + [int(tt.Status.MAX_ITERATIONS)] * 2


@pytest.mark.parametrize("method", ["ipm", "eilqr"])
def test_the_control_steps_leave_their_last_iterate_untested_and_apply_the_same_controls(monkeypatch, method):
    env = envs.PendulumEnv()
    fixed = tt.solvers.get(method).step_defaults()
    if method == "ipm":  # its adaptive budget off, so that both controllers spend the same budget
        fixed = dataclasses.replace(fixed, stop_feasible_after=0)
    untested = tt.MPC(env.problem(), method, 2, options=fixed)
    assert not untested.options.test_last_iterate
    tested = tt.MPC(env.problem(), method, 2, options=dataclasses.replace(untested.options, test_last_iterate=True))
    calls = counting_expansions(monkeypatch, method)
    x = STATES
    for _ in range(4):
        before = len(calls)
        u = untested(x)
        between = len(calls)
        assert torch.equal(u, tested(x))
        assert len(calls) - between == between - before + 1  # the tested step's one expansion more
        assert (untested.status == tt.Status.MAX_ITERATIONS).all()
        x = x + 0.05 * torch.cat([x[:, 1:], u], -1)
    assert torch.equal(untested.X, tested.X) and torch.equal(untested.U, tested.U)
