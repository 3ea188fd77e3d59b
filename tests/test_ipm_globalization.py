"""The interior-point method's second-order corrections (Wächter & Biegler 2006 §2.3), against the analytic optimum.

A terminal equality on the unit circle, ``|x_N|² = 1``, and a terminal cost ``2(|x_N|² − 1) − x_{N,1}`` (the
classical Maratos example on the circle), started on the circle at the angle 0.5: the linearised constraint is the
tangent, so the full Newton step leaves the circle, its ``θ`` grows, and the filter rejects it. With the correction
every step is taken whole; without it the line search halves the second step. Either way the solution is the
analytic optimum ``x_N = (1, 0)``, ``u_k = (1/2, 0)``, cost ``−1 + 10⁻³ · 2 · (1/2)² = −0.9995``.

The filter's augmentation (W&B 2006 step A-7): a step that met the switching and Armijo conditions adds no entry,
whichever test accepted it. IPOPT's first iteration on the minimum-time cart-pendulum swing (its log, default
options: ``4.15e-01f``, two trial points) is such a step at ``θ = 3.14``, far above ``θ_min``, so that its filter
stays empty; the IPM takes the same step size there and must leave its filter empty too.
"""

import math

import pytest
import torch
from small_problems import powell_circle

import torchtraj as tt

F64 = torch.float64


def test_second_order_correction_rescues_the_full_step_on_a_curved_constraint():
    problem = powell_circle([0.0, 0.0], N=2)
    xN = torch.tensor([math.cos(0.5), math.sin(0.5)], dtype=F64)
    X0, U0 = torch.stack([torch.zeros(2, dtype=F64), xN / 2, xN]), torch.stack([xN / 2, xN / 2])
    solve = lambda soc: tt.solve(problem, method="ipm", X0=X0, U0=U0,  # noqa: E731
                                 options=tt.IPOptions(second_order_corrections=soc))
    with_soc, without = solve(4), solve(0)
    for sol in (with_soc, without):
        assert sol.status.tolist() == [tt.Status.CONVERGED]
        assert abs(float(sol.cost[0]) + 0.9995) < 1e-9
        torch.testing.assert_close(sol.X[0, -1], torch.tensor([1.0, 0.0], dtype=F64), rtol=0, atol=1e-8)
    assert bool((without.history.step_size[0] < 1).any())  # the filter rejected a full step
    assert bool((with_soc.history.step_size[0] == 1).all())  # the corrected full step was taken instead
    assert int(with_soc.iterations[0]) < int(without.iterations[0])


def test_least_squares_multipliers_take_ipopts_path(reference):
    """pendulum_unconstrained from the problem set's guess (constraints: the dynamics alone, so the estimate is of
    the costates): started at the least-squares costates (W&B §3.6) the IPM reaches IPOPT's optimum in IPOPT's
    iterations; started at zero costates it takes more and ends at another local optimum (the one iLQR finds,
    tests/test_interior_point.py)."""
    problem = tt.problems.get("pendulum_unconstrained")
    ipopt = reference["pendulum_unconstrained"]["ipopt"]
    estimated = tt.solve(problem, method="ipm")
    zero = tt.solve(problem, method="ipm", options=tt.IPOptions(least_squares_multipliers=False))
    assert estimated.status.tolist() == zero.status.tolist() == [tt.Status.CONVERGED]
    assert abs(float(estimated.cost[0]) - ipopt["cost"]) / ipopt["cost"] < 1e-8
    assert int(estimated.iterations[0]) <= ipopt["iterations"] < int(zero.iterations[0])
    assert abs(float(zero.cost[0]) - ipopt["cost"]) / ipopt["cost"] > 0.5


def test_a_step_that_meets_the_switching_and_armijo_conditions_adds_no_filter_entry(monkeypatch):
    """The cart-pendulum swing's first iteration (module docstring): IPOPT's step size 0.415, and no filter entry
    (an entry there blocked the next steps: the filter was reset at the sixth iteration and the solve took 129
    iterations, not 105)."""
    from torchtraj.bench import minimum_time_problems
    from torchtraj.solvers.ipm import solver as ipm_solver

    steps, search = [], ipm_solver.line_search

    def recorded(*args, **kwargs):
        steps.append(search(*args, **kwargs))
        return steps[-1]

    monkeypatch.setattr(ipm_solver, "line_search", recorded)
    tt.solve(minimum_time_problems.get("cartpole_swing").problem, method="ipm", options=tt.IPOptions(iterations=1))
    (step,) = steps
    assert bool(step.found[0]) and float(step.alpha[0]) == pytest.approx(0.415, abs=5e-4)
    assert bool(torch.isinf(step.filter.entries).all())
