"""ALTRO against IPOPT optima, first-order optimality checked by autograd, and batch isolation."""

import pytest
import torch
from kkt import kkt_residuals
from same_solutions import assert_same_solutions

import torchtraj as tt

FAST = ["double_integrator", "pendulum"]
SLOW = ["parallel_park", "cartpole", "car_3obs", "quadrotor2d", "car_escape"]
#: Problems where ALTRO, from the problem set's guess, finds another local optimum than IPOPT; each is checked to
#: be a KKT point and confirmed by IPOPT warm-started there. car_3obs: ALTRO (9.43375) passes the three circles
#: below the diagonal, IPOPT (12.04034) above it. car_escape (0.3316056 against 0.3316544): the same route, but
#: with the walls constrained at the knots only, other knots touch a wall circle (ALTRO: knots 31-32 on the
#: corner (5, 5), 63-65 on (8, 5); IPOPT: 29-30 and 62-65).
OTHER_OPTIMUM = {"car_3obs", "quadrotor2d", "car_escape"}


def solve_problem(name):
    problem = tt.problems.get(name)
    X0 = problem.X_init if name == "car_escape" else None
    options = tt.problems.altro_options(name)
    return problem, tt.solve(problem, method="altro", X0=X0, options=options)


def check_problem(name, reference):
    problem, sol = solve_problem(name)
    ipopt = reference[name]["ipopt"]["cost"]
    assert sol.status[0] == tt.Status.CONVERGED
    assert sol.max_violation[0] <= 1e-8
    stationarity, dual_min, complementarity = kkt_residuals(problem, sol)
    assert stationarity < 1e-5, stationarity
    assert dual_min > -1e-8 and complementarity < 1e-8
    cost = float(sol.cost[0])
    if name not in OTHER_OPTIMUM:
        assert abs(cost - ipopt) / ipopt < 1e-4
        return
    # another local optimum: it must be a KKT point (checked above) that IPOPT, started there, keeps. A warm
    # start proper (small initial barrier parameter, no push off the active bounds): with IPOPT's cold-start
    # defaults it leaves car_3obs' and car_escape's optimum for the neighbouring one, 1.9e-4 / 1.5e-4 higher.
    from torchtraj.bench.reference import ReferenceSolver

    warm = ReferenceSolver(name, "ipopt").solve(U0=sol.U[0].numpy(), X0=sol.X[0].numpy(), warm_start=True)
    assert warm.ok and abs(warm.cost - cost) / cost < 1e-6, (warm.cost, cost)
    assert abs(warm.X - sol.X[0].numpy()).max() < 1e-2  # stayed, not a different optimum of equal cost
    assert abs(cost - ipopt) / ipopt > 1e-4  # the note in OTHER_OPTIMUM is still true


@pytest.mark.parametrize("name", FAST)
def test_problem_set_fast(name, reference):
    check_problem(name, reference)


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_problem_set_slow(name, reference):
    check_problem(name, reference)


@pytest.mark.slow  # 64 ALTRO solves to the certificate's accuracy; the contract test checks batches on short problems
def test_pendulum_batch_of_64(reference):
    """``sample_x0("pendulum", 64, seed=0)`` in one batch: all converge, each cost within 1e-4 of IPOPT's."""
    problem = tt.problems.get("pendulum")
    x0 = tt.problems.sample_x0("pendulum", 64, seed=0)
    sol = tt.solve(problem, x0, method="altro", options=tt.problems.altro_options("pendulum"))
    ipopt = torch.tensor(reference["pendulum_batch_seed0_ipopt"]["costs"], dtype=torch.float64)
    assert bool(sol.converged.all())
    assert float(sol.max_violation.max()) <= 1e-8
    rel = (sol.cost - ipopt).abs() / ipopt
    assert float(rel.max()) < 1e-4, rel.max()


def test_nan_instance_is_isolated():
    """One x0 with a NaN fails alone; the other instances equal their single solves to the last bit."""
    problem = tt.problems.get("double_integrator")
    opts = tt.problems.altro_options("double_integrator")
    x0 = torch.tensor([[0.0, 0.0], [float("nan"), 0.0], [0.1, -0.1]], dtype=torch.float64)
    batch = tt.solve(problem, x0, method="altro", options=opts)
    assert batch.status.tolist()[1] == tt.Status.NON_FINITE
    for i in (0, 2):
        alone = tt.solve(problem, x0[i], method="altro", options=opts)
        assert alone.status[0] == tt.Status.CONVERGED
        assert torch.equal(batch.X[i], alone.X[0]) and torch.equal(batch.U[i], alone.U[0])
        assert torch.equal(batch.cost[i], alone.cost[0])


@pytest.mark.slow  # a full solve of the pendulum besides the capped one; the contract test covers the blocks
def test_status_max_iterations_and_multiplier_blocks():
    problem = tt.problems.get("pendulum")
    sol = tt.solve(problem, method="altro", options=tt.problems.altro_options("pendulum", iterations_outer=1,
                                                                               iterations_inner=5))
    assert sol.status[0] == tt.Status.MAX_ITERATIONS
    full = tt.solve(problem, method="altro", options=tt.problems.altro_options("pendulum"))
    assert set(full.multipliers) == {"u_upper", "u_lower", "terminal_eq"} == set(full.penalties)
    assert full.multipliers["u_upper"].shape == (1, 50, 1) and full.multipliers["terminal_eq"].shape == (1, 2)
    # the torque bound is active on part of the swing-up: positive multipliers exactly there
    U = full.U[0, :, 0]
    active = (U - 3.0).abs() < 1e-7
    assert bool(active.any()) and bool((full.multipliers["u_upper"][0, active, 0] > 0).all())
    assert bool((full.multipliers["u_upper"][0, ~active, 0] == 0).all())
    assert float(full.penalties["u_upper"].max()) > 1.0  # the schedule raised them


@pytest.mark.slow  # a minute of the default run; the same path is tested on shorter problems
def test_al_ilqr_stops_at_the_coarse_tolerance():
    """The AL stage alone ends below ``constraint_tolerance``; the projection then reaches 1e-8. The AL stage's point
    is no KKT point at the certificate's feasibility (1e-8), so AL-iLQR says ``STALLED`` (issue 23's contract;
    measured: violation 9.7e-6 after 217 iterations)."""
    problem = tt.problems.get("pendulum")
    opts = tt.problems.altro_options("pendulum", constraint_tolerance=1e-4)
    coarse = tt.solve(problem, method="al-ilqr", options=opts)
    fine = tt.solve(problem, method="altro", options=opts)
    assert coarse.status[0] == tt.Status.STALLED and fine.status[0] == tt.Status.CONVERGED
    assert 1e-8 < float(coarse.max_violation[0]) < 1e-4  # what projection is for
    assert float(fine.max_violation[0]) <= 1e-8
    assert torch.allclose(coarse.U, fine.U, atol=1e-2)  # a projection, not a different solution


@pytest.mark.slow  # two full pendulum solves; MPC's warm starts are tested by tests/test_mpc.py
def test_warm_started_duals_resolve_in_few_iterations():
    problem = tt.problems.get("pendulum")
    opts = tt.problems.altro_options("pendulum")
    cold = tt.solve(problem, method="altro", options=opts)
    warm = tt.solve(problem, method="altro", options=opts, U0=cold.U,
                    duals={"multipliers": cold.multipliers, "penalties": cold.penalties})
    assert warm.status[0] == tt.Status.CONVERGED
    assert int(warm.iterations[0]) < int(cold.iterations[0]) // 5
    assert abs(float(warm.cost[0] - cold.cost[0])) < 1e-6


@pytest.mark.parametrize("method", ["altro", "ilqr"])
def test_iterating_on_the_running_instances_alone_changes_no_answer(method, monkeypatch):
    """``ILQROptions.compact_below``: once instances have finished, the iLQR iterations run on the others alone
    (gathered, with their own parameters and multipliers). Every field of the solution and of its history is the
    same as without, bit for bit, where instances stop at different iterations, a parameter differs per instance
    and one instance fails (a NaN start)."""
    from small_problems import oscillator, pendulum10

    from torchtraj.iterations import ilqr as ilqr_module

    gathered = []
    original = ilqr_module._on_rows
    monkeypatch.setattr(ilqr_module, "_on_rows", lambda iteration, rows, *args: gathered.append(rows.numel())
                        or original(iteration, rows, *args))
    x0 = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2], [float("nan"), 0.0], [0.9, 0.4], [0.4, -0.2]],
                      dtype=torch.float64)
    if method == "altro":
        k = torch.tensor([2.0, 1.0, 3.0, 2.5, 1.5, 2.0], dtype=torch.float64)
        problem = oscillator().with_params(k=k, goal=torch.tensor([-0.5, 0.0], dtype=torch.float64).repeat(6, 1))

        def options(compact_below):
            return tt.ALTROOptions(ilqr=tt.ILQROptions(compact_below=compact_below))
    else:
        problem = pendulum10(N=20)

        def options(compact_below):
            return tt.ILQROptions(compact_below=compact_below)
    whole = tt.solve(problem, x0, method=method, options=options(0.0))
    assert not gathered
    compacted = tt.solve(problem, x0, method=method, options=options(0.99))
    assert gathered and min(gathered) >= 1 and max(gathered) < x0.shape[0]
    assert whole.status[3] == tt.Status.NON_FINITE and len(set(whole.iterations.tolist())) >= 3

    assert_same_solutions(compacted, whole)


@pytest.mark.parametrize("method", ["altro", "ilqr"])
def test_later_line_search_rounds_on_the_instances_still_looking_change_no_answer(method, monkeypatch):
    """A line-search round after the first simulates only the instances that found no step yet (``backtrack``'s
    ``by_rows``): the solution and its history are those of rounds over the whole batch, bit for bit, with one step
    size a round so that instances part ways at every round."""
    from small_problems import oscillator, pendulum10

    from torchtraj.globalization import line_search
    from torchtraj.iterations import ilqr as ilqr_module

    x0 = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2], [0.1, 0.0], [0.9, 0.4], [0.4, -0.2]],
                      dtype=torch.float64)
    inner = tt.ILQROptions(line_search_parallel=1, compact_below=0.0)
    if method == "altro":
        problem, options = oscillator(), tt.ALTROOptions(ilqr=inner)
    else:  # swinging up from far: shortened steps
        problem, options = pendulum10(N=20), inner
        x0 = x0 * torch.tensor([6.0, 4.0], dtype=torch.float64)
    looked = []
    original = line_search._round_of_rows
    monkeypatch.setattr(line_search, "_round_of_rows", lambda evaluate, alphas, looking, *args: looked.append(
        looking.numel()) or original(evaluate, alphas, looking, *args))
    by_rows = tt.solve(problem, x0, method=method, options=options)
    assert looked and max(looked) < x0.shape[0]
    backtrack = ilqr_module.backtrack
    monkeypatch.setattr(ilqr_module, "backtrack", lambda *args, by_rows=False: backtrack(*args))
    whole = tt.solve(problem, x0, method=method, options=options)
    assert_same_solutions(by_rows, whole)
