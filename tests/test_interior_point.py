"""The interior-point method (``method="ipm"``) against independent references.

* IPOPT / FATROP optima of the problem set (tests/data) and IPOPT solves of sampled
  instances (``torchtraj.bench.reference``, CasADi);
* first-order optimality of the returned point, checked by autograd of the Lagrangian built here from
  the problem's functions and the solution's costates and multipliers;
* per-instance solves against the batch; a NaN instance; float32 against the float64 optimum;
* iLQR on an unconstrained problem; central differences of re-solves and ALTRO for the gradients.
"""

import functools
import warnings

import pytest
import torch
from kkt import kkt_residuals
from same_solutions import assert_same_solutions
from small_problems import oscillator, pendulum10

import torchtraj as tt
from torchtraj.core.batching import map_stage, rollout
from torchtraj.core.constraints import Constraints
from torchtraj.riccati import sweep_for_batch

F64 = torch.float64
FAST = ["double_integrator", "pendulum"]
SLOW = ["cartpole", "parallel_park"]


@functools.lru_cache(maxsize=None)
def solved(name):
    """The problem set's problem ``name`` solved by the IPM from its default guess (cached: several tests
    look at the same solve)."""
    problem = tt.problems.get(name)
    return problem, tt.solve(problem, method="ipm")


# ------------------------------------------------------------------------- IPOPT / FATROP optima
def check_reference(name, reference):
    """Converged, feasible, and the cost of IPOPT's and FATROP's optima. parallel_park: IPOPT's stored run
    ends 3.5e-6 (relative) above FATROP's; the IPM, on IPOPT's path since it scales the objective as IPOPT does
    (W&B 2006 §3.8; before, it landed 1.4e-7 from FATROP's), lands 2.7e-8 from IPOPT's, so it is held to 1e-6 of
    IPOPT's and to 5e-6 of the lower of the two."""
    _, sol = solved(name)
    ipopt, fatrop = reference[name]["ipopt"]["cost"], reference[name]["fatrop"]["cost"]
    assert sol.status.tolist() == [tt.Status.CONVERGED], sol.status
    assert float(sol.max_violation[0]) < 1e-8
    cost = float(sol.cost[0])
    best = min(ipopt, fatrop)
    assert abs(cost - ipopt) / ipopt < 1e-6, (cost, ipopt, fatrop)
    assert abs(cost - best) / best < 5e-6, (cost, ipopt, fatrop)
    assert sol.method == "ipm" and 0 < int(sol.iterations[0]) < 200


@pytest.mark.parametrize("name", FAST)
def test_reaches_the_reference_optimum(name, reference):
    check_reference(name, reference)
    # and the trajectory IPOPT returned, not another one of equal cost
    _, sol = solved(name)
    X = torch.tensor(reference[name]["ipopt"]["X"], dtype=F64)
    U = torch.tensor(reference[name]["ipopt"]["U"], dtype=F64)
    assert float((sol.X[0] - X).abs().max()) < 1e-5 and float((sol.U[0] - U).abs().max()) < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_reaches_the_reference_optimum_slow(name, reference):
    check_reference(name, reference)


# ------------------------------------------------------------------------------------- KKT point
def check_kkt(name):
    problem, sol = solved(name)
    stationarity, dual_min, complementarity = kkt_residuals(problem, sol)
    assert stationarity < 1e-7, stationarity
    assert dual_min >= 0.0, dual_min  # the slack multipliers are kept positive, not just >= -eps
    assert complementarity < 1e-7, complementarity
    # the problem has both active and inactive inequality rows: an active bound carries a multiplier
    c = Constraints(problem)
    g = c.evaluate(sol.X, sol.U, problem.batched_params(1)).ineq
    z = torch.cat([sol.multipliers[k] for k in c.ineq_blocks if c.ineq_blocks[k].stop > c.ineq_blocks[k].start], -1)
    on = c.ineq_knot_mask.bool().unsqueeze(0)
    # (with the final barrier parameter μ ≈ 2.5e-9 an active row sits at g = −μ/z, 5e-6 for the pendulum)
    active, inactive = on & (g > -1e-3), on & (g < -1e-2)
    assert int(active.sum()) >= 1 and int(inactive.sum()) >= 1
    assert float(z[active].min()) > 1e-6 and float(z[inactive].max()) < 1e-6
    return problem, sol


@pytest.mark.parametrize("name", FAST)
def test_solution_is_a_kkt_point(name):
    problem, sol = check_kkt(name)
    assert set(sol.multipliers) >= {"u_upper", "u_lower", "terminal_eq"}
    assert sol.multipliers["u_upper"].shape == (1, problem.N, problem.nu)
    assert sol.costate.shape == (1, problem.N + 1, problem.nx)


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_solution_is_a_kkt_point_slow(name):
    check_kkt(name)


def test_kkt_check_fails_away_from_the_optimum():
    """The check above can fail: the same multipliers at a perturbed control sequence are not stationary."""
    problem, sol = solved("double_integrator")
    moved = tt.Solution(**{**sol.__dict__, "U": sol.U + 1e-2})
    assert kkt_residuals(problem, moved)[0] > 1e-5


# --------------------------------------------------------------------------- batches and failures
def test_batch_equals_instances_solved_alone():
    """Four double integrators of seed 0 in one batch; instance 1 is infeasible (IPOPT: Infeasible_Problem_
    Detected; its velocity bound cannot bring it to the goal in time) and fails alone. Each instance's
    status, iterations, X and U equal its solve alone, and the feasible ones reach IPOPT's optimum."""
    problem = tt.problems.get("double_integrator")
    x0 = tt.problems.sample_x0("double_integrator", 4, seed=0)
    batch = tt.solve(problem, x0, method="ipm")
    assert batch.status.tolist()[0::2] == [tt.Status.CONVERGED] * 2 and batch.status[3] == tt.Status.CONVERGED
    assert batch.status[1] != tt.Status.CONVERGED
    assert len(set(batch.iterations.tolist())) > 1  # instances stop at their own iteration
    for i in range(4):
        alone = tt.solve(problem, x0[i], method="ipm")
        assert alone.status.tolist() == batch.status[i:i + 1].tolist()
        assert alone.iterations.tolist() == batch.iterations[i:i + 1].tolist()
        for a, b in ((alone.X[0], batch.X[i]), (alone.U[0], batch.U[i]), (alone.costate[0], batch.costate[i])):
            assert torch.allclose(a, b, rtol=0, atol=1e-10, equal_nan=True)
    pytest.importorskip("casadi")
    from torchtraj.bench.reference import ReferenceSolver

    ipopt = ReferenceSolver("double_integrator", "ipopt")
    for i in range(4):
        ref = ipopt.solve(x0=x0[i].numpy())
        if i == 1:
            assert not ref.ok and ref.status == "Infeasible_Problem_Detected"
        else:
            assert ref.ok and abs(float(batch.cost[i]) - ref.cost) / ref.cost < 1e-7


@pytest.mark.slow
def test_pendulum_batch_equals_instances_solved_alone(reference):
    problem = tt.problems.get("pendulum")
    x0 = tt.problems.sample_x0("pendulum", 4, seed=0)
    batch = tt.solve(problem, x0, method="ipm")
    assert bool(batch.converged.all())
    ipopt = torch.tensor(reference["pendulum_batch_seed0_ipopt"]["costs"][:4], dtype=F64)
    assert float(((batch.cost - ipopt).abs() / ipopt).max()) < 1e-6
    for i in range(4):
        alone = tt.solve(problem, x0[i], method="ipm")
        assert alone.status.tolist() == batch.status[i:i + 1].tolist()
        assert alone.iterations.tolist() == batch.iterations[i:i + 1].tolist()
        assert torch.allclose(alone.X[0], batch.X[i], rtol=0, atol=1e-10)
        assert torch.allclose(alone.U[0], batch.U[i], rtol=0, atol=1e-10)


def test_nan_instances_fail_alone():
    """A NaN initial state (instance 1) and a NaN goal, a parameter that first shows up inside the
    iteration (instance 2), each end NON_FINITE; instances 0 and 3 equal their solves alone."""
    problem = tt.problems.get("double_integrator")
    x0 = tt.problems.sample_x0("double_integrator", 4, seed=0)
    x0[1, 0] = float("nan")
    goal = problem.params["goal"].expand(4, 2).clone()
    goal[2, 1] = float("nan")
    batch = tt.solve(problem.with_params(goal=goal), x0, method="ipm")
    assert batch.status.tolist() == [tt.Status.CONVERGED, tt.Status.NON_FINITE, tt.Status.NON_FINITE,
                                     tt.Status.CONVERGED]
    for i in (0, 3):
        alone = tt.solve(problem, x0[i], method="ipm")
        assert alone.status[0] == tt.Status.CONVERGED
        assert alone.iterations.tolist() == batch.iterations[i:i + 1].tolist()
        assert torch.allclose(alone.X[0], batch.X[i], rtol=0, atol=1e-10)
        assert torch.allclose(alone.U[0], batch.U[i], rtol=0, atol=1e-10)
        assert torch.isfinite(batch.X[i]).all() and torch.isfinite(batch.cost[i])


# -------------------------------------------------------------------------------------- float32
def test_float32_double_integrator_reaches_the_float64_optimum(reference):
    problem = tt.problems.get("double_integrator", dtype=torch.float32)
    sol = tt.solve(problem, method="ipm")
    ref = reference["double_integrator"]["ipopt"]
    assert sol.X.dtype == torch.float32 and sol.status[0] == tt.Status.CONVERGED
    assert float(sol.max_violation[0]) < 1e-6
    assert abs(float(sol.cost[0]) - ref["cost"]) / ref["cost"] < 1e-4
    # the final barrier parameter tol / 10 = 1e-6 keeps u_0 at 3 − μ/z = 2.9992 off its bound (z = 2e-3)
    assert float((sol.U[0].double() - torch.tensor(ref["U"], dtype=F64)).abs().max()) < 5e-3


def test_float32_pendulum_reaches_the_float64_optimum(reference):
    """float32's default tol = 1e-6 converges: 1.4e-4 above IPOPT's cost, U 0.025 away."""
    problem = tt.problems.get("pendulum", dtype=torch.float32)
    ref = reference["pendulum"]["ipopt"]
    U_ref = torch.tensor(ref["U"], dtype=F64)
    sol = tt.solve(problem, method="ipm")
    assert sol.X.dtype == torch.float32 and sol.status[0] == tt.Status.CONVERGED
    assert float(sol.max_violation[0]) < 1e-5
    assert 0 <= (float(sol.cost[0]) - ref["cost"]) / ref["cost"] < 3e-4
    assert float((sol.U[0].double() - U_ref).abs().max()) < 0.05


@pytest.mark.slow
def test_float32_pendulum_coarse_tolerance(reference):
    """The pendulum's cost (0.0184) and multipliers (< 5e-4) are small, so the absolute stopping test
    ``E_0 ≤ tol`` at tol = 1e-5 stops early: 1.6e-3 above IPOPT's cost, U 0.24 away (float64 stopped at the
    same tol ends at the same point: the tolerance, not float32's round-off); hence float32's default 1e-6."""
    problem = tt.problems.get("pendulum", dtype=torch.float32)
    ref = reference["pendulum"]["ipopt"]
    sol = tt.solve(problem, method="ipm", options=tt.IPOptions(tolerance=1e-5))
    assert sol.status[0] == tt.Status.CONVERGED
    assert float(sol.max_violation[0]) < 1e-5
    assert 0 <= (float(sol.cost[0]) - ref["cost"]) / ref["cost"] < 3e-3


# ------------------------------------------------------------------------ multiple-shooting start
def test_state_guess_is_used_and_reaches_the_same_optimum(reference):
    """A straight line from x0 to the goal with zero controls: dynamically inconsistent (defects of
    0.05). The first iteration sees its violation (so X0 was used, not a rollout), and the solve ends at
    IPOPT's optimum, the point of the default start."""
    problem = tt.problems.get("double_integrator")
    params = problem.batched_params(1)
    N = problem.N
    s = torch.linspace(0, 1, N + 1, dtype=F64).unsqueeze(-1)
    X0 = ((1 - s) * problem.x0 + s * problem.params["goal"]).unsqueeze(0)
    U0 = torch.zeros(1, N, problem.nu, dtype=F64)
    defects = map_stage(problem.dynamics, X0[:, :-1], U0, params) - X0[:, 1:]
    violation = Constraints(problem).evaluate(X0, U0, params).max_violation()
    start = max(float(defects.abs().max()), float(violation[0]))
    assert start > 1e-2
    sol = tt.solve(problem, method="ipm", X0=X0, U0=U0)
    assert float(sol.history.max_violation[0, 0]) == pytest.approx(start, rel=1e-12)
    assert sol.status[0] == tt.Status.CONVERGED and float(sol.max_violation[0]) < 1e-8
    ref = reference["double_integrator"]["ipopt"]
    assert abs(float(sol.cost[0]) - ref["cost"]) / ref["cost"] < 1e-6
    _, default = solved("double_integrator")
    assert torch.allclose(sol.X, default.X, atol=1e-6) and torch.allclose(sol.U, default.U, atol=1e-6)


@pytest.mark.slow
def test_pendulum_state_guess(reference):
    problem = tt.problems.get("pendulum")
    N = problem.N
    s = torch.linspace(0, 1, N + 1, dtype=F64).unsqueeze(-1)
    X0 = (1 - s) * problem.x0 + s * problem.params["goal"]
    sol = tt.solve(problem, method="ipm", X0=X0)
    assert sol.status[0] == tt.Status.CONVERGED and float(sol.max_violation[0]) < 1e-8
    ref = reference["pendulum"]["ipopt"]
    assert abs(float(sol.cost[0]) - ref["cost"]) / ref["cost"] < 1e-6


# ---------------------------------------------------------------------------------- unconstrained
def test_unconstrained_problem_matches_ilqr():
    """pendulum_unconstrained from the problem's guess: iLQR (tight) and the IPM end at the same local
    optimum (0.0137812669, test_ilqr.py; IPOPT finds another one from this guess, and so does the IPM with its
    least-squares initial costates, tests/test_ipm_globalization.py: here they start at zero, and no second-order
    correction is taken: with them the IPM ends at a KKT point of its own (stationarity 1.2e-14) whose defects of
    1.1e-11 the unstable swing amplifies to 7.5e-7 in the rollout the reduced gradient below is taken on, which is
    then 2.9e-3). The cost is flat along
    part of the swing: tight iLQR stops 7.6e-11 above in cost, 1e-3 away in U, with a reduced gradient of
    6e-8. So: the costs agree to 1e-10, the IPM's reduced gradient (autograd through a rollout) vanishes,
    and iLQR started at the IPM's controls stops there at once. That gradient carries the round-off of the IPM's
    last step through the unstable rollout: 4.9e-8 and 1.3e-7 for two orderings of the same Riccati products (the
    vector sweeps before and after they became affine recursions, :mod:`torchtraj.riccati.sweep`), after the same
    iterates; the bound is 3e-7, a thousandth of the guess's."""
    problem = tt.problems.get("pendulum_unconstrained")
    tight = tt.ILQROptions(cost_tolerance=1e-12, gradient_tolerance=1e-8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ilqr = tt.solve(problem, method="ilqr", options=tight)
    ipm = tt.solve(problem, method="ipm", options=tt.IPOptions(tolerance=1e-10, least_squares_multipliers=False,
                                                                   second_order_corrections=0))
    assert ilqr.status[0] == tt.Status.CONVERGED and ipm.status[0] == tt.Status.CONVERGED
    assert ipm.multipliers == {} and float(ipm.max_violation[0]) < 1e-10  # only the dynamics
    assert abs(float(ipm.cost[0]) - float(ilqr.cost[0])) < 1e-10
    assert abs(float(ipm.cost[0]) - 0.0137812669) < 1e-9
    assert float((ipm.U - ilqr.U).abs().max()) < 2e-3
    params = problem.batched_params(1)
    x0 = problem.x0.unsqueeze(0)

    def reduced_gradient(U):
        U = U.detach().clone().requires_grad_(True)
        J = tt.kkt.total_cost(problem, rollout(problem.dynamics, x0, U, params), U, params)
        return float(torch.autograd.grad(J.sum(), U)[0].abs().max())

    assert reduced_gradient(ipm.U) < 3e-7 < 1e-3 * reduced_gradient(problem.u_init.unsqueeze(0))
    again = tt.solve(problem, method="ilqr", U0=ipm.U, options=tight)
    assert again.status[0] == tt.Status.CONVERGED and float((again.U - ipm.U).abs().max()) < 1e-9


# ---------------------------------------------------------------------------------- gradients
def pendulum10_bounded(**changes):
    """tests/test_implicit.py's pendulum (N = 10, O(1) weights) with the torque bounded by ±3."""
    bounds = dict(u_lower=torch.tensor([-3.0], dtype=F64), u_upper=torch.tensor([3.0], dtype=F64))
    return pendulum10(**{**bounds, **changes})


def test_gradients_match_central_differences_with_active_bounds():
    """gradcheck (central differences of whole IPM re-solves) of X, U and cost with respect to x0, the mass
    (dynamics) and the goal, packed in one vector; the torque bound is active on part of the horizon."""
    problem = pendulum10_bounded()

    def unpack(th):
        return th[:2], dict(mass=th[2], goal=th[3:5])

    theta = torch.cat([torch.tensor([0.1, 0.2], dtype=F64), problem.params["mass"].reshape(1),
                       problem.params["goal"]]).requires_grad_(True)

    def layer(th):
        x0, params = unpack(th)
        sol = tt.solve(problem.with_params(**params), x0, method="ipm")
        assert bool(sol.converged.all())
        return sol.X, sol.U, sol.cost

    X, U, _ = layer(theta)
    g = Constraints(problem).evaluate(X.detach(), U.detach(), problem.batched_params(1)).ineq
    assert int((g > -1e-4).sum()) >= 1 and int((g < -1e-2).sum()) >= 1
    assert torch.autograd.gradcheck(layer, (theta,), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_gradients_agree_with_altro():
    """Gradients of a loss of U with respect to x0 and the mass, through the IPM and through ALTRO (tight),
    two instances, the torque bound active: the same KKT point, so the same derivative."""
    problem = pendulum10_bounded()
    x0s = torch.tensor([[0.1, 0.2], [0.3, -0.1]], dtype=F64)
    tight = tt.ALTROOptions(ilqr=tt.ILQROptions(cost_tolerance=1e-10, gradient_tolerance=1e-6),
                            cost_tolerance=1e-10, cost_tolerance_intermediate=1e-6, constraint_tolerance=1e-8)
    out = {}
    for method, options in (("ipm", None), ("altro", tight)):
        x0 = x0s.clone().requires_grad_(True)
        mass = torch.full((2,), 1.0, dtype=F64, requires_grad=True)
        sol = tt.solve(problem.with_params(mass=mass), x0, method=method, options=options)
        assert bool(sol.converged.all())
        loss = (sol.U ** 2).sum() + sol.U[:, :3].sum()
        out[method] = (sol.U.detach(), *torch.autograd.grad(loss, [x0, mass]))
        if method == "altro":
            g = Constraints(problem).evaluate(sol.X.detach(), sol.U.detach(), problem.batched_params(2)).ineq
            assert int((g > -1e-8).sum()) >= 1 and int((g < -1e-2).sum()) >= 1  # bounds active and inactive
    assert torch.allclose(out["ipm"][0], out["altro"][0], atol=1e-5)
    for a, b in zip(out["ipm"][1:], out["altro"][1:]):
        assert float(b.abs().max()) > 1e-2
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-6 * float(b.abs().max())), (a, b)


# ---------------------------------------------------------------------------------- input errors
def test_penalties_and_a_misshapen_state_guess_are_refused():
    """The IPM takes multipliers, costates and a barrier as duals (tests/test_ipm_warm_start.py), no penalties."""
    problem = tt.problems.get("double_integrator")
    with pytest.raises(ValueError, match="method 'ipm' takes"):
        tt.solve(problem, method="ipm", duals={"penalties": {}})
    with pytest.raises(ValueError, match="X0"):
        tt.solve(problem, method="ipm", X0=torch.zeros(problem.N, problem.nx, dtype=F64))


@pytest.mark.slow
def test_obstacles_without_restoration_end_with_a_status():
    """car_3obs from the problem set's guess with the restoration phase off (``IPOptions(restoration=False)``;
    with it, tests/test_ipm_restoration.py): it must still return a per-instance, non-RUNNING status, and a finite
    point if converged."""
    problem = tt.problems.get("car_3obs")
    sol = tt.solve(problem, method="ipm", options=tt.IPOptions(restoration=False))
    assert isinstance(sol, tt.Solution) and sol.status.shape == (1,)
    status = int(sol.status[0])
    assert status in {int(s) for s in tt.Status} and status != tt.Status.RUNNING
    assert 0 < int(sol.iterations[0]) <= tt.IPOptions().iterations
    assert sol.history.cost.shape == (1, len(sol.history))
    if status == tt.Status.CONVERGED:
        assert bool(torch.isfinite(sol.X).all()) and float(sol.max_violation[0]) < 1e-8


@pytest.mark.slow
def test_obstacles_from_a_state_guess_around_them(reference):
    """car_3obs from a state guess that goes around the circles (up the y axis, then across; dynamically
    inconsistent, controls at the problem set's guess): no restoration is needed and the IPM reaches the
    optimum IPOPT and FATROP find, a KKT point."""
    problem = tt.problems.get("car_3obs")
    s = torch.linspace(0, 2, problem.N + 1, dtype=F64)[:, None]
    a, b, c = (torch.tensor(p, dtype=F64) for p in ([0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [3.0, 3.0, 0.0]))
    X0 = torch.where(s <= 1, a + (b - a) * s, b + (c - b) * (s - 1))
    sol = tt.solve(problem, method="ipm", X0=X0)
    assert sol.status.tolist() == [tt.Status.CONVERGED] and float(sol.max_violation[0]) < 1e-8
    ipopt = reference["car_3obs"]["ipopt"]["cost"]
    assert abs(float(sol.cost[0]) - ipopt) / ipopt < 1e-6
    stationarity, dual_min, complementarity = kkt_residuals(problem, sol)
    assert stationarity < 1e-7 and dual_min >= 0 and complementarity < 1e-7


def test_a_linear_quadratic_problem_is_expanded_once(monkeypatch):
    """Declared ``linear_quadratic``, the IPM takes the torch.func expansion once, at each instance's first stage,
    and its derivatives by products after that; its iterates, multipliers and implicit gradients are those of the
    plain IPM, which expands at every stage of every iterate."""
    from torchtraj.solvers.ipm import expansion as interior_point

    calls = []

    def counted(name):
        original = getattr(interior_point, name)

        def call(*args, **kwargs):
            calls.append(name)
            return original(*args, **kwargs)
        return call

    for name in ("problem_kkt_expansion", "quadratic_stage_hessian"):
        monkeypatch.setattr(interior_point, name, counted(name))
    x0s = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2]], dtype=F64)
    out = {}
    for declared in (False, True):
        problem = oscillator(linear_quadratic=declared)
        x0 = x0s.clone().requires_grad_(True)
        k = torch.tensor(2.0, dtype=F64, requires_grad=True)
        goal = torch.tensor([-0.5, 0.0], dtype=F64, requires_grad=True)
        calls.clear()
        # without the crossover, which only the declared problem takes (tests/test_crossover.py)
        sol = tt.solve(problem.with_params(k=k, goal=goal), x0, method="ipm", options=tt.IPOptions(crossover=False))
        assert bool(sol.converged.all()), sol.status
        loss = (sol.U ** 2).sum() + sol.X[:, -5:].sum() + sol.cost.sum()
        out[declared] = (sol, list(calls), torch.autograd.grad(loss, [x0, k, goal]))
    (plain, plain_calls, plain_grads), (lq, lq_calls, lq_grads) = out[False], out[True]
    assert lq_calls == ["quadratic_stage_hessian"]
    # one per iterate, and the first iterate's again with its least-squares multipliers
    assert plain_calls == ["problem_kkt_expansion"] * (int(plain.iterations.max()) + 2)
    # the same path up to round-off: the third start's step at iteration 11 ends at a KKT error of 1e-8 to 1e-7 or of
    # 3e-9 as the Riccati products' rounding falls (both ways, before and after the vector sweeps' reordering), so
    # it converges at iteration 12 or 13
    assert int((lq.iterations - plain.iterations).abs().max()) <= 1
    X, U = lq.X.detach(), lq.U.detach()
    assert bool(((X[:, 1:-1, 0] < -0.2 + 1e-6).sum(-1) >= 1).all())  # the state row holds on an arc
    assert bool(((U.abs() > 0.6 - 1e-6).flatten(1).sum(-1) >= 1).all())  # and so does a bound
    assert torch.allclose(lq.X, plain.X, atol=1e-10) and torch.allclose(lq.U, plain.U, atol=1e-10)
    # one iteration apart the barrier differs: multipliers to 1e-5; so does the third start's last step, from a KKT
    # error that the rounding moves by a factor of 3 (2e-8 to 6e-8): its rows near the arc (inactive by 4e-4), whose
    # multipliers are μ/s ~ 1e-6, end 1e-8 to 1e-6 apart
    same = (lq.iterations == plain.iterations) & torch.tensor([True, True, False])
    for name in plain.multipliers:
        a, b = lq.multipliers[name], plain.multipliers[name]
        assert torch.allclose(a[same], b[same], atol=1e-8), name
        assert torch.allclose(a[~same], b[~same], atol=1e-5), name
    for a, b in zip(lq_grads, plain_grads):
        assert float(b.abs().max()) > 1e-2
        assert torch.allclose(a, b, rtol=1e-8, atol=1e-8 * float(b.abs().max())), (a, b)


@pytest.mark.parametrize("declared", [False, True])
def test_iterating_on_the_running_instances_alone_changes_no_answer(declared, monkeypatch):
    """``compact_below``: once instances have finished, the next iterations run on the others alone (gathered,
    with their own parameters). Every field of the solution and of its history is the same as without, where
    instances stop at different iterations and a parameter differs per instance (the spring constant), one
    instance fails (a NaN goal), and, declared linear-quadratic, the first expansion is gathered too."""
    from torchtraj.solvers.ipm import solver as interior_point

    gathers = []
    original = interior_point.param_rows
    monkeypatch.setattr(interior_point, "param_rows", lambda params, index: gathers.append(index) or original(
        params, index))
    x0 = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2], [0.1, 0.0], [0.9, 0.4], [0.4, -0.2]], dtype=F64)
    k = torch.tensor([2.0, 1.0, 3.0, 2.5, 1.5, 2.0], dtype=F64)
    goal = torch.tensor([-0.5, 0.0], dtype=F64).repeat(6, 1)
    goal[4, 0] = float("nan")
    problem = oscillator(linear_quadratic=declared).with_params(k=k, goal=goal)

    # the crossover gathers the instances it tries too (tests/test_crossover.py)
    whole = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(compact_below=0.0, crossover=False))
    assert not gathers
    gathered = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(compact_below=0.99, crossover=False))
    assert len(gathers) >= 2 and len(set(whole.iterations.tolist())) >= 3
    assert whole.status[4] == tt.Status.NON_FINITE and int(whole.converged.sum()) == 5
    assert_same_solutions(gathered, whole)


def test_corrections_on_the_pending_instances_alone_change_no_answer(monkeypatch):
    """The inertia correction's attempts after the first, and the second-order corrections, work on the rows of the
    instances that need them alone (gathered), not on the whole batch again: every field of the solution and of its
    history is the one of whole-batch attempts and corrections, bit for bit, on pendulum starts where some
    instances need them at some iterations and others do not."""
    from torchtraj.solvers.ipm import solver as interior_point

    problem = tt.problems.get("pendulum")
    x0 = tt.problems.sample_x0("pendulum", 6, 0)
    options = tt.IPOptions(iterations=12, compact_below=0.0)
    regularized, corrected = interior_point.regularized_direction, interior_point.correction_of_rows
    gathered = {"attempts": [], "corrections": []}

    def counted_attempts(attempt, *args, by_rows=False, first=None):
        def counting(delta, rows=None):
            if rows is not None:
                gathered["attempts"].append(rows.numel())
            return attempt(delta) if rows is None else attempt(delta, rows)
        return regularized(counting, *args, by_rows=by_rows, first=first)

    def counted_corrections(*args):
        gathered["corrections"].append(int(args[12].sum()))  # need
        return corrected(*args)

    monkeypatch.setattr(interior_point, "regularized_direction", counted_attempts)
    monkeypatch.setattr(interior_point, "correction_of_rows", counted_corrections)
    by_rows = tt.solve(problem, x0, method="ipm", options=options)
    for counts in gathered.values():  # made, and never for the whole batch
        assert counts and min(counts) > 0 and max(counts) < x0.shape[0], gathered
    monkeypatch.setattr(interior_point, "regularized_direction",
                        lambda *args, by_rows=False, first=None: regularized(*args, first=first))
    monkeypatch.setattr(interior_point, "correction_of_rows", interior_point.second_order_correction)
    whole = tt.solve(problem, x0, method="ipm", options=options)
    assert_same_solutions(by_rows, whole)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("case", ["general", "declared", "bounds", "terminal"])
def test_cuda_graphs_replay_the_eager_solve(case):
    """``IPOptions(cuda_graphs=True)`` on a GPU: every kernel captured, and the same statuses, iterations and
    solutions as the eager solve to rounding (the Cholesky factors by formulas instead of LAPACK-like calls), and
    the same gradients. The second graphed solve, of a new problem object with a new parameter tensor as a training
    step makes, replays the graphs the first captured: none is captured again. On the oscillator with its
    inequality rows (its torch.func expansion captured), declared linear-quadratic (its products; the crossover's
    candidates and refinement hold the state row, which takes the Riccati core's SVD: eager), and with control
    bounds alone (the crossover's start rounds on the whole batch, refinement's Newton step and the adjoint solve
    graphed too), and with its terminal row (the range-space method, whose pseudo-inverses are Jacobi rotations on
    a GPU: LAPACK-like solvers read their status on the host)."""
    from torchtraj.core.graphs import _GRAPHED, graphed
    from torchtraj.differentiation import implicit
    from torchtraj.solvers.ipm import crossover
    from torchtraj.solvers.ipm.newton import direction

    changes = dict(general=dict(terminal_eq=None), declared=dict(linear_quadratic=True, terminal_eq=None),
                   bounds=dict(linear_quadratic=True, state_ineq=None, terminal_eq=None), terminal={})[case]
    problem = oscillator(**changes).to(device="cuda")
    x0s = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2]], dtype=F64, device="cuda")
    out, captured = {}, []
    for graphs in (False, True, True):
        x0 = x0s.clone().requires_grad_(True)
        k = problem.params["k"].clone().requires_grad_(True)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # every kernel captured: none falls back to eager
            sol = tt.solve(problem.with_params(k=k), x0, method="ipm", options=tt.IPOptions(cuda_graphs=graphs))
            assert bool(sol.converged.all()), sol.status
            grads = torch.autograd.grad((sol.U ** 2).sum() + sol.X[:, -5:].sum(), [x0, k])
        out.setdefault(graphs, []).append((sol, grads))
        captured.append(sum(w.captures for w in _GRAPHED.values()))
    assert captured[2] == captured[1] > captured[0]
    assert len(graphed(direction).graphs) >= 1
    if case == "bounds":
        assert len(graphed(crossover.candidate).graphs) >= 1 and len(graphed(implicit._adjoint).graphs) >= 1
        assert len(graphed(implicit._newton_step).graphs) >= 1
    (eager, g_eager), = out[False]
    for sol, grads in out[True]:
        assert torch.equal(sol.iterations, eager.iterations)
        assert torch.allclose(sol.X, eager.X, atol=1e-10) and torch.allclose(sol.U, eager.U, atol=1e-10)
        for a, b in zip(grads, g_eager):
            assert torch.allclose(a, b, atol=1e-10)


def test_graph_keys_follow_the_problems_functions_and_the_options_values():
    """A CUDA graph's key (:mod:`torchtraj.core.graphs`) reads a problem as its functions and the shapes of its tensors,
    its constraints as their problem, and options by value: the solve of a new problem object with new parameter
    tensors replays the last one's graphs, and reads the new tensors. New functions or other settings are new
    graphs. (The keys are made on any device; only their replay needs a GPU.)"""
    from torchtraj.core.graphs import _flatten, _rebuild

    def key_of(problem, options):
        tensors, key = [], []
        template = _flatten((problem, Constraints(problem), options), tensors, key)
        return tuple(key), template, tensors

    problem = oscillator(linear_quadratic=True)
    k2, k3 = torch.tensor(2.0, dtype=F64), torch.tensor(3.0, dtype=F64)
    key, _, _ = key_of(problem.with_params(k=k2), tt.IPOptions(cuda_graphs=True))
    same, template, tensors = key_of(problem.with_params(k=k3), tt.IPOptions(cuda_graphs=True))
    assert same == key
    assert key_of(problem.with_params(k=k2), tt.IPOptions(cuda_graphs=True, tolerance=1e-6))[0] != key
    other_cost = problem.replace(stage_cost=lambda x, u, p: (u * u).sum())
    assert key_of(other_cost.with_params(k=k2), tt.IPOptions(cuda_graphs=True))[0] != key
    # made again around copies of the tensors (a graph's static inputs), the constraints read those copies
    copies = [t.clone() for t in tensors]
    rebuilt, cons, _ = _rebuild(template, copies)
    assert any(cons.problem.params["k"] is c for c in copies) and float(cons.problem.params["k"]) == 3.0
    X, U = torch.randn(2, 16, 2, dtype=F64), torch.randn(2, 15, 1, dtype=F64)
    original = Constraints(problem.with_params(k=k3))
    params = {n: v.expand(2, *v.shape) for n, v in problem.with_params(k=k3).params.items()}
    assert torch.equal(cons.max_violation(X, U, params), original.max_violation(X, U, params))


def test_mehrotra_reaches_the_monotone_optimum_in_fewer_iterations():
    """``barrier_strategy="mehrotra"`` on a convex problem (the oscillator: linear dynamics, a state row on an arc,
    active bounds, a terminal equality): the KKT point of the monotone IPM, with costates and multipliers that
    satisfy the KKT conditions, the same implicit gradients, in fewer iterations over the batch."""
    x0s = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2], [0.1, 0.0]], dtype=F64)
    problem = oscillator(linear_quadratic=True)
    out = {}
    for strategy in ("monotone", "mehrotra"):
        x0 = x0s.clone().requires_grad_(True)
        k = torch.tensor(2.0, dtype=F64, requires_grad=True)
        sol = tt.solve(problem.with_params(k=k), x0, method="ipm", options=tt.IPOptions(barrier_strategy=strategy))
        assert bool(sol.converged.all()), sol.status
        out[strategy] = (sol, torch.autograd.grad((sol.U ** 2).sum() + sol.X[:, -5:].sum(), [x0, k]))
    (mono, mono_grads), (meh, meh_grads) = out["monotone"], out["mehrotra"]
    assert int(meh.iterations.sum()) < int(mono.iterations.sum()), (meh.iterations, mono.iterations)
    assert torch.allclose(meh.X, mono.X, atol=1e-6) and torch.allclose(meh.U, mono.U, atol=1e-6)
    assert torch.allclose(meh.cost, mono.cost, rtol=1e-8)
    # (a differentiable solve refines X and U: the solver's own point is that of a plain solve)
    plain = tt.solve(problem, x0s, method="ipm", options=tt.IPOptions(barrier_strategy="mehrotra"))
    stationarity, dual_min, complementarity = kkt_residuals(problem, plain)
    assert stationarity < 1e-7 and dual_min >= 0.0 and complementarity < 1e-7, (stationarity, complementarity)
    for a, b in zip(meh_grads, mono_grads):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-6 * float(b.abs().max())), (a, b)


def test_barrier_strategy_is_checked():
    with pytest.raises(ValueError, match="monotone"):
        tt.IPOptions(barrier_strategy="adaptive")
    with pytest.raises(ValueError, match="eager"):
        tt.IPOptions(barrier_strategy="mehrotra", compile=True)


def test_mehrotra_ends_an_infeasible_instance_with_a_status():
    """Without a line search, a step that the boundary cuts to nothing counts as a failed one: the instance that
    cannot reach its terminal equality within the bounds retries with larger ``δ_w`` until it gives up (Mehrotra's
    steps have no filter for a restoration phase to return to), and the other instance gets its own answer."""
    options = tt.IPOptions(barrier_strategy="mehrotra")
    problem = oscillator(linear_quadratic=True)
    both = tt.solve(problem, torch.tensor([[0.5, 0.0], [0.9, 0.4]], dtype=F64), method="ipm", options=options)
    alone = tt.solve(problem, torch.tensor([[0.5, 0.0]], dtype=F64), method="ipm", options=options)
    assert both.status.tolist() == [tt.Status.CONVERGED, tt.Status.MAX_REGULARIZATION]
    assert torch.allclose(both.U[:1], alone.U, rtol=0, atol=1e-12) and both.iterations[0] == alone.iterations[0]


def test_the_automatic_sweep_is_decided_once_for_the_whole_batch(monkeypatch):
    """``sweep="auto"`` decides for the batch as given (:func:`~torchtraj.riccati.sweep_for_batch`), so that the
    factorisations of the running instances alone, once the batch compacts, take the same sweep: a batch too large
    for the parallel sweep never takes it, though its running instances fall below the bound, and is solved as with
    ``"sequential"``; a batch below the bound takes it throughout."""
    import torchtraj.riccati.factorization as factorization

    parallel_rows = []
    factorize_parallel = factorization.factorize_parallel

    def counted(lqr, *args):
        parallel_rows.append(lqr.B.shape[0])
        return factorize_parallel(lqr, *args)

    monkeypatch.setattr(factorization, "factorize_parallel", counted)
    problem = tt.problems.get("pendulum").replace(horizon=12, u_init=torch.zeros(1, dtype=torch.float64),
                                                 terminal_eq=None)
    B = 160
    assert sweep_for_batch(B, 12, 2, 1, "cpu") == "sequential" and sweep_for_batch(100, 12, 2, 1, "cpu") == "parallel"
    x0 = tt.problems.sample_x0("pendulum", B, seed=0)
    auto = tt.solve(problem, x0, "ipm", options=tt.IPOptions(sweep="auto"))
    assert parallel_rows == []
    sequential = tt.solve(problem, x0, "ipm", options=tt.IPOptions(sweep="sequential"))
    assert (sequential.status == tt.Status.CONVERGED).all() and len(set(sequential.iterations.tolist())) > 3
    assert torch.equal(auto.U, sequential.U) and torch.equal(auto.iterations, sequential.iterations)
    small = tt.solve(problem, x0[:100], "ipm", options=tt.IPOptions(sweep="auto"))
    assert parallel_rows[0] == 100 and len(parallel_rows) >= int(small.iterations.max())


def test_the_parallel_in_time_sweep_takes_the_same_steps():
    """``IPOptions.sweep = "parallel"``: the Newton steps by the associative-scan Riccati sweep, on a problem without
    equality rows (bounds as barriers), give the sequential sweep's iterates to round-off; a goal equality takes the
    range-space method on either sweep (the same steps to round-off), while its back-propagation is sequential and
    "parallel" refuses it by name."""
    problem = tt.problems.get("pendulum").replace(horizon=12, u_init=torch.zeros(1, dtype=torch.float64),
                                                 terminal_eq=None)
    x0 = tt.problems.sample_x0("pendulum", 2, seed=0)
    sequential = tt.solve(problem, x0, "ipm")
    parallel = tt.solve(problem, x0, "ipm", options=tt.IPOptions(sweep="parallel"))
    assert (sequential.status == tt.Status.CONVERGED).all()
    assert torch.equal(parallel.status, sequential.status) and torch.equal(parallel.iterations, sequential.iterations)
    torch.testing.assert_close(parallel.U, sequential.U, rtol=0, atol=1e-9)
    torch.testing.assert_close(parallel.costate, sequential.costate, rtol=0, atol=1e-8)
    goal = tt.problems.get("double_integrator")  # its goal is a terminal equality
    x0 = torch.stack([goal.x0, 0.5 * goal.x0])  # feasible starts (some of sample_x0's are not)
    sequential = tt.solve(goal, x0, "ipm")
    parallel = tt.solve(goal, x0, "ipm", options=tt.IPOptions(sweep="parallel"))
    assert (sequential.status == tt.Status.CONVERGED).all()
    assert torch.equal(parallel.status, sequential.status) and torch.equal(parallel.iterations, sequential.iterations)
    torch.testing.assert_close(parallel.U, sequential.U, rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="parallel"):
        tt.solve(goal, x0, "ipm", options=tt.IPOptions(sweep="parallel", terminal_rows="back-propagation"))
    auto = tt.solve(goal, x0, "ipm", options=tt.IPOptions(sweep="auto"))
    assert torch.equal(auto.U, parallel.U)  # a batch this small takes the parallel sweep
    with pytest.raises(ValueError, match="sweep"):
        tt.IPOptions(sweep="scan")
