"""A control step's adaptive budget (``IPOptions.stop_feasible_after``, on in ``IPM.step_defaults``).

An instance whose iterate is feasible to ``stop_feasible_violation`` after that many iterations stops there; the
others go on to the cap. Each instance ends where a solve capped at its own iteration count ends, to the last bit,
so an instance that stops early changes nothing of another's answer.
"""

import dataclasses

import pytest
import torch

import torchtraj as tt
from torchtraj import problems

IPM = tt.solvers.get("ipm")
CAP = 6


def _stacked(warm: torch.Tensor) -> torch.Tensor:
    return torch.cat([warm, torch.zeros_like(warm)])


@pytest.fixture(scope="module")
def car_step():
    """car_3obs as a controller's step sees it: instance 0 warm-started from the optimum at a moved state, instance
    1 cold from a constant state guess (its defects large): ``(problem, x0, solve keyword arguments)``."""
    problem = problems.get("car_3obs")
    optimum = tt.solve(problem, None, method="ipm")
    assert bool((optimum.status == tt.Status.CONVERGED).all())
    x0 = torch.stack([problem.x0 + 0.02, problem.x0])
    X0 = torch.stack([optimum.X[0], problem.x0.expand(problem.N + 1, -1)])
    X0[:, 0] = x0
    carried = IPM.carried_duals(None, optimum, IPM.step_defaults())
    duals = {"multipliers": {k: _stacked(v) for k, v in carried["multipliers"].items()},
             "costate": _stacked(carried["costate"]), "barrier": _stacked(carried["barrier"])}  # a zero: cold
    kwargs = {"U0": torch.stack([optimum.U[0], problem.u_init]), "X0": X0, "duals": duals}
    return problem, x0, kwargs


def _solve(car_step, **changes) -> tt.Solution:
    problem, x0, kwargs = car_step
    options = dataclasses.replace(IPM.step_defaults(), **{"iterations": CAP, "record": None, **changes})
    return tt.solve(problem, x0, method="ipm", options=options, **kwargs)


def _assert_instance_equal(a: tt.Solution, b: tt.Solution, i: int) -> None:
    for name in ("X", "U", "K", "costate"):
        assert torch.equal(getattr(a, name)[i], getattr(b, name)[i]), name
    assert all(torch.equal(a.multipliers[k][i], b.multipliers[k][i]) for k in a.multipliers)
    assert a.cost[i] == b.cost[i] and a.max_violation[i] == b.max_violation[i]


def test_a_feasible_instance_stops_and_the_others_go_on_each_as_a_solve_capped_where_it_ended(car_step):
    threshold = IPM.step_defaults().stop_feasible_violation
    adaptive = _solve(car_step)
    stopped, went_on = adaptive.iterations.tolist()
    assert 1 < stopped < CAP and went_on == CAP  # the warm instance needed more than one iteration, not all
    assert (adaptive.status == tt.Status.MAX_ITERATIONS).all()
    assert adaptive.max_violation[0] <= threshold < adaptive.max_violation[1]
    before = _solve(car_step, stop_feasible_after=0, iterations=stopped - 1)
    assert before.max_violation[0] > threshold  # it stopped at its first feasible iterate, not later
    _assert_instance_equal(adaptive, _solve(car_step, stop_feasible_after=0, iterations=stopped), 0)
    _assert_instance_equal(adaptive, _solve(car_step, stop_feasible_after=0), 1)


def test_a_looser_violation_stops_sooner(car_step):
    adaptive = _solve(car_step, stop_feasible_violation=1.0)
    assert adaptive.iterations.tolist() == [1, CAP]


def test_the_adaptive_budget_is_refused_where_the_last_iterate_is_tested_and_for_bad_values():
    with pytest.raises(ValueError, match="test_last_iterate=False"):
        tt.IPOptions(stop_feasible_after=1)
    with pytest.raises(ValueError, match="stop_feasible_after must be >= 0"):
        tt.IPOptions(stop_feasible_after=-1, test_last_iterate=False)
    with pytest.raises(ValueError, match="stop_feasible_violation > 0"):
        tt.IPOptions(stop_feasible_after=1, test_last_iterate=False, stop_feasible_violation=0.0)
