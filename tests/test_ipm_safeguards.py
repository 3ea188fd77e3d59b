"""The interior-point method's safeguards from IPOPT (Wächter & Biegler 2006): the watchdog and the filter reset
heuristic (§3.2), very small search directions (§3.9), and dependent equality rows (§3.1's ``δ_c``).

**Watchdog.** Powell's Maratos example on the unit circle as a one-stage problem: ``x_1 = x_0 + u`` with
``|x_1|² = 1``, cost ``10⁻³|u|² + 2(|x_1|² − 1) − x_{1,1}``, from ``x_0`` on the circle at the angle 3 (nearly
opposite the optimum) and without second-order corrections, so that the filter keeps cutting the Newton steps.
Triggered after one shortened step, the watchdog takes ``watchdog_trials`` = 3 full steps without a line search;
none of them is acceptable to the stored point's tests here, so it returns to the stored point, whose next step is
the one the line search takes there without the watchdog (the same direction: the restored ``δ_w``). Both runs end
at the optimum on the circle, from a scalar minimisation over the angle (scipy).

**Filter reset.** :func:`~torchtraj.solvers.ipm.watchdog.count_steps` on a batch of two: the instance whose last
rejected trial point the filter alone refused in ``filter_reset_trigger`` successive iterations has its filter
emptied, the other keeps its own, and no instance is reset more than ``filter_resets`` times.

**Very small search directions.** A tolerance below round-off (1e-20 in float64) cannot be met: the Newton steps
fall to round-off while ``E_μ > κ_ε μ``, so the monotone rule alone never lowers ``μ`` and the solve ran to its
iteration limit (60 here). With the rule, ``μ`` is forced down to its floor ``tol/10`` and the instance stops
``STALLED`` within a few dozen iterations, at the same solution as a regular solve (a dense check: the KKT
residuals by autograd, ``tests/kkt.py``).

**Dependent equality rows** (the case of IPOPT's ``δ_c``): a terminal row stated twice, and two stage rows whose
Jacobians coincide at the solution and whose linearisations disagree elsewhere (``u = 0.5`` and ``u² = 0.25``).
IPOPT, on a duplicated row, perturbs the constraint block; the Riccati core's rank-revealing elimination drops the
dependent row instead. Both converge, with the cost of the problem stated once, and pass the KKT check. A row
whose gradient vanishes where it holds (``(x_{N,0} − 1)² = 0``, slow) is no case for ``δ_c``: IPOPT never perturbs
the constraint block there (the Jacobian is small, not singular) and ends ``Error_In_Step_Computation`` at a
violation of 1.1e-16; the IPM takes the same iterates and ends there too, ``MAX_REGULARIZATION``.

**Host synchronisations.** The loop asks the host twice per iteration (the running count, and one read of the
restoration gate, the tiny steps and the watchdog's state), counted on Powell's example.
"""

import json
import math
import pathlib

import pytest
import torch
from kkt import kkt_residuals
from small_problems import powell_circle

import torchtraj as tt
from torchtraj import problems
from torchtraj.globalization.filter import Filter
from torchtraj.solvers.ipm.line_search import Step
from torchtraj.solvers.ipm.watchdog import Watchdog, count_steps

F64 = torch.float64
ANGLE = 3.0


def test_the_watchdog_takes_full_steps_and_returns_to_the_stored_point():
    scipy = pytest.importorskip("scipy.optimize")
    best = scipy.minimize_scalar(lambda a: 1e-3 * (2 - 2 * math.cos(a - ANGLE)) - math.cos(a), bounds=(-1, 1),
                                 method="bounded", options={"xatol": 1e-12})
    problem = powell_circle([math.cos(ANGLE), math.sin(ANGLE)])
    solve = lambda trigger: tt.solve(problem, method="ipm", options=tt.IPOptions(  # noqa: E731
        second_order_corrections=0, watchdog_trigger=trigger))
    watched, plain = solve(1), solve(0)
    for sol in (watched, plain):
        assert sol.status.tolist() == [tt.Status.CONVERGED]
        assert abs(float(sol.cost[0]) - best.fun) < 1e-9
        torch.testing.assert_close(sol.X[0, -1], torch.tensor([math.cos(best.x), math.sin(best.x)], dtype=F64),
                                   rtol=0, atol=1e-6)
    a, b = watched.history.step_size[0].tolist(), plain.history.step_size[0].tolist()
    # the first time the line search cuts two steps in a row (iterations 8 and 9), the watchdog starts instead
    k = next(i for i in range(1, len(b)) if b[i - 1] < 1 and b[i] < 1)
    assert a[:k] == b[:k]
    assert a[k:k + 3] == [1.0, 1.0, 1.0]  # three full steps without a line search
    assert a[k + 3] == 0.0  # none acceptable: back to the stored point
    assert a[k + 4] == b[k]  # whose step is the line search's there


def test_the_filter_is_reset_after_successive_steps_it_blocked():
    opts = tt.IPOptions()
    it_like = torch.zeros(2, 1, dtype=F64)
    filt = Filter.empty(2, 4, it_like).add(torch.tensor([True, True]), torch.tensor([1.0, 1.0], dtype=F64),
                                           torch.tensor([2.0, 2.0], dtype=F64))
    wd = Watchdog(shortened=torch.zeros(2, dtype=torch.long), trials=torch.zeros(2, dtype=torch.long), it=None,
                  phi=it_like[:, 0], slope=it_like[:, 0], theta=it_like[:, 0], alpha=it_like[:, 0],
                  last=it_like[:, 0], blocked=torch.zeros(2, dtype=torch.long),
                  resets=torch.zeros(2, dtype=torch.long))
    taken, watching = torch.tensor([True, True]), torch.tensor([False, False])
    step = Step(it=None, alpha=it_like[:, 0] + 1, found=taken, filter=filt,
                shortened=torch.tensor([True, True]), blocked=torch.tensor([True, False]))
    resets = []
    for _ in range(opts.filter_reset_trigger * (opts.filter_resets + 2)):
        wd, after = count_steps(wd, taken, step, watching, filt, opts)
        resets.append(torch.isinf(after.entries).all(-1).all(-1).tolist())
    assert resets[opts.filter_reset_trigger - 2] == [False, False]
    assert resets[opts.filter_reset_trigger - 1] == [True, False]  # the fifth successive blocked step
    assert sum(r[0] for r in resets) == opts.filter_resets and not any(r[1] for r in resets)
    assert wd.resets.tolist() == [opts.filter_resets, 0]
    off = tt.IPOptions(filter_resets=0)
    assert not bool(torch.isinf(count_steps(wd, taken, step, watching, filt, off)[1].entries).all())


def test_the_filter_reset_keeps_the_entry_of_the_point_the_step_leaves():
    """IPOPT empties the filter when it accepts the trial point, then augments it with the point the step leaves
    (an h-type step): the entries held before the line search go, the one it added stays."""
    opts = tt.IPOptions()
    like = torch.zeros(2, 1, dtype=F64)
    before = Filter.empty(2, 4, like).add(torch.tensor([True, True]), torch.tensor([1.0, 1.0], dtype=F64),
                                          torch.tensor([2.0, 2.0], dtype=F64))
    added = before.add(torch.tensor([True, False]), torch.tensor([0.5, 0.5], dtype=F64),
                       torch.tensor([1.5, 1.5], dtype=F64))  # instance 0's step was h-type, instance 1's f-type
    wd = Watchdog(shortened=torch.zeros(2, dtype=torch.long), trials=torch.zeros(2, dtype=torch.long), it=None,
                  phi=like[:, 0], slope=like[:, 0], theta=like[:, 0], alpha=like[:, 0], last=like[:, 0],
                  blocked=torch.full((2,), opts.filter_reset_trigger - 1, dtype=torch.long),
                  resets=torch.zeros(2, dtype=torch.long))
    taken, watching = torch.tensor([True, True]), torch.tensor([False, False])
    step = Step(it=None, alpha=like[:, 0] + 1, found=taken, filter=added, shortened=torch.tensor([True, True]),
                blocked=torch.tensor([True, True]))
    wd, after = count_steps(wd, taken, step, watching, before, opts)
    assert wd.resets.tolist() == [1, 1]
    finite = torch.isfinite(after.entries).all(-1)
    assert finite.sum(-1).tolist() == [1, 0]
    assert after.entries[0][finite[0]].tolist() == [[0.5, 1.5]]
    # the kept entry is the newest of the ring: it is overwritten last
    assert after.slot.tolist() == added.slot.tolist()


def test_the_solver_asks_for_a_reset_only_where_a_count_can_reach_its_trigger(monkeypatch):
    """The iteration reads, with its other host reads, whether a count of blocked steps is one short of the
    trigger; only then does ``count_steps`` compute a reset. On car_3obs the filter blocks the steps of iterations
    28 to 32 and is reset at the 32nd: the reset is asked for there alone, and the iterates are the same as when
    every step may reset."""
    from torchtraj.solvers.ipm import conclusion

    problem = problems.get("car_3obs")
    options = tt.IPOptions(iterations=32)
    calls, before, resets, count = [], [], [], conclusion.count_steps

    def always(*args):
        calls.append(args[-1])
        before.append(int(args[0].blocked.max()))
        wd, filt = count(*args[:-1], True)
        resets.append(int(wd.resets.sum()))
        return wd, filt

    monkeypatch.setattr(conclusion, "count_steps", always)
    every = tt.solve(problem, method="ipm", options=options)
    monkeypatch.setattr(conclusion, "count_steps", count)
    gated = tt.solve(problem, method="ipm", options=options)
    assert resets[-1] == 1 and resets[-2] == 0
    assert calls == [b >= options.filter_reset_trigger - 1 for b in before] and sum(calls) == 1
    assert torch.equal(every.X, gated.X) and torch.equal(every.U, gated.U)
    assert torch.equal(every.history.step_size, gated.history.step_size)


def double_integrator(**rows) -> tt.Problem:
    goal = torch.tensor([1.0, 0.0], dtype=F64)
    return tt.Problem(
        dynamics=tt.rk4(lambda x, u, p: torch.stack([x[1], u[0]]), 0.1),
        stage_cost=lambda x, u, p: 0.1 * (u ** 2).sum() + ((x - goal) ** 2).sum(),
        terminal_cost=lambda x, p: 10.0 * ((x - goal) ** 2).sum(),
        u_lower=torch.tensor([-1.0], dtype=F64), u_upper=torch.tensor([1.0], dtype=F64),
        x0=torch.tensor([0.3, 0.1], dtype=F64), horizon=20, nu=1, **rows)


def _kkt_ok(problem, sol):
    stationarity, dual_min, complementarity = kkt_residuals(problem, sol)
    return stationarity < 1e-6 and dual_min >= 0 and complementarity < 1e-6


def test_very_small_search_directions_lower_mu_and_stop():
    problem = double_integrator(state_ineq=lambda x, p: x[1:] - 0.5)
    solve = lambda y: tt.solve(problem, method="ipm", options=tt.IPOptions(  # noqa: E731
        tolerance=1e-20, iterations=60, tiny_step_dual=y))
    ruled, plain, regular = solve(1e-2), solve(0.0), tt.solve(problem, method="ipm")
    assert plain.status.tolist() == [tt.Status.MAX_ITERATIONS]
    assert float(plain.history.extra["barrier"][0, -1]) > 1e-21  # μ stuck above its floor
    assert ruled.status.tolist() == [tt.Status.STALLED] and int(ruled.iterations[0]) < 30
    assert float(ruled.history.extra["barrier"][0, -1]) == pytest.approx(1e-21)
    assert regular.status.tolist() == [tt.Status.CONVERGED] and _kkt_ok(problem, ruled)
    assert abs(float(ruled.cost[0]) - float(regular.cost[0])) < 1e-8 * float(regular.cost[0])  # regular: tol 1e-8


def test_dependent_equality_rows_are_dropped_not_singular():
    once = tt.solve(double_integrator(terminal_eq=lambda x, p: torch.stack([x[0] - 1, x[1]])), method="ipm")
    twice_problem = double_integrator(terminal_eq=lambda x, p: torch.stack([x[0] - 1, x[0] - 1, x[1]]))
    twice = tt.solve(twice_problem, method="ipm")
    assert once.status.tolist() == twice.status.tolist() == [tt.Status.CONVERGED]
    assert abs(float(twice.cost[0]) - float(once.cost[0])) < 1e-9 and _kkt_ok(twice_problem, twice)
    pinned = double_integrator(stage_eq=lambda x, u, p: torch.stack([u[0] - 0.5, u[0] ** 2 - 0.25]))
    sol = tt.solve(pinned, method="ipm")
    assert sol.status.tolist() == [tt.Status.CONVERGED] and _kkt_ok(pinned, sol)
    torch.testing.assert_close(sol.U[0], torch.full_like(sol.U[0], 0.5), rtol=0, atol=1e-8)


def test_one_host_synchronisation_per_iteration_in_the_loop(monkeypatch):
    """The loop of :func:`~torchtraj.solvers.ipm.solver.run` asks the host twice per iteration: how many instances
    still run, and, at once, whether any enters a restoration phase, took a tiny step, or has a watchdog running
    or about to start (before: a test of its own for each). Counted on Powell's example with the watchdog active
    (trigger 1); the line search's and the inertia correction's own tests are elsewhere and not counted here."""
    import sys

    import torchtraj.solvers.ipm.solver as loop

    calls = []

    def counting(name):
        original = getattr(torch.Tensor, name)

        def wrapper(self, *args, **kwargs):
            if sys._getframe(1).f_code.co_filename == loop.__file__:
                calls.append(name)
            return original(self, *args, **kwargs)
        return wrapper

    for name in ("__bool__", "__int__", "__float__", "item", "tolist"):
        monkeypatch.setattr(torch.Tensor, name, counting(name))
    problem = powell_circle([math.cos(ANGLE), math.sin(ANGLE)])
    sol = tt.solve(problem, method="ipm", options=tt.IPOptions(second_order_corrections=0, watchdog_trigger=1))
    monkeypatch.undo()
    steps = int(sol.iterations[0])
    assert sol.status.tolist() == [tt.Status.CONVERGED]
    assert len(calls) == 2 * steps + 1, (len(calls), steps)  # the last pass only counts the running instances


@pytest.mark.slow
def test_a_row_whose_gradient_vanishes_where_it_holds_ends_as_ipopt_does():
    """The terminal row ``(x_{N,0} − 1)² = 0`` (its gradient vanishes where it holds: no multiplier exists there).
    IPOPT (tests/data/ipm_degenerate_row.json, the bounds as two-sided rows as in the problem set's references) takes
    full steps that halve the distance to 1, so the violation falls by 4 per iteration to 1.1e-16, and stays there;
    its ``δ_c`` (W&B §3.1) never acts, the Jacobian row ``2(x − 1)`` being small but never singular. It ends after 37
    iterations by its acceptable-level test (``Solved_To_Acceptable_Level``), which the IPM does not have. The IPM
    takes the same violations and ends at IPOPT's point with ``MAX_REGULARIZATION``, where no step is acceptable.
    (With the bounds as variable bounds, IPOPT ended ``Error_In_Step_Computation`` after 26 iterations at 6.675517.)"""
    ipopt = json.loads((pathlib.Path(__file__).parent / "data" / "ipm_degenerate_row.json").read_text())
    sol = tt.solve(double_integrator(terminal_eq=lambda x, p: ((x[0] - 1) ** 2).reshape(1)), method="ipm")
    assert ipopt["status"] == "Solved_To_Acceptable_Level"
    assert sol.status.tolist() == [tt.Status.MAX_REGULARIZATION]
    torch.testing.assert_close(sol.history.max_violation[0, :len(ipopt["violation"])],
                               torch.tensor(ipopt["violation"], dtype=F64), rtol=1e-9, atol=0)
    assert abs(float(sol.cost[0]) - ipopt["objective"][-1]) < 1e-8 * ipopt["objective"][-1]
