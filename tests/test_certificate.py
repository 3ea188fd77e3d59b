"""The KKT certificate (torchtraj.kkt.certificate): CONVERGED only at a KKT point, for every method.

Its residuals are checked against independent computations (the gradient of the rolled-out cost by autograd, a
multiplier flipped by hand), and ``tt.solve`` is checked to report a point that a method's own stopping test
accepted short of the optimum as ``STALLED``.
"""

import pytest
import torch

import torchtraj as tt
from torchtraj import problems, solvers
from torchtraj.core.batching import rollout
from torchtraj.core.constraints import Constraints
from torchtraj.core.recorded import TRACE_AT
from torchtraj.core.scripted import Scripted
from torchtraj.kkt import certificate

F64 = torch.float64


def short_pendulum(dtype=F64) -> tt.Problem:
    """The benchmark pendulum over N = 10 without its goal: nonlinear, its torque bound active at the start."""
    return problems.get("pendulum", dtype=dtype).replace(horizon=10, u_init=torch.zeros(1, dtype=dtype),
                                                          terminal_eq=None)


def test_stationarity_is_the_gradient_of_the_rolled_out_cost():
    """Unconstrained and without defects, the reduced gradient is ∇_U J(rollout(U)): autograd through a rollout."""
    problem = problems.get("pendulum_unconstrained").replace(horizon=12, u_init=torch.zeros(1, dtype=F64))
    x0 = problems.sample_x0("pendulum_unconstrained", 3, seed=1)
    U = 0.3 * torch.randn(3, 12, 1, dtype=F64, generator=torch.Generator().manual_seed(0))
    params = problem.batched_params(3)
    X = rollout(problem.dynamics, x0, U, params)
    res = certificate.residuals(problem, X, U, {}, params, x0, Constraints.of(problem))
    Ug = U.clone().requires_grad_(True)
    cost = tt.kkt.total_cost(problem, rollout(problem.dynamics, x0, Ug, params), Ug, params).sum()
    (gradient,) = torch.autograd.grad(cost, Ug)
    # the multipliers (costates) are small here, so IPOPT's scale s_d is 1
    torch.testing.assert_close(res.stationarity, gradient.abs().flatten(1).amax(1), rtol=1e-10, atol=1e-14)
    assert (res.feasibility < 1e-14).all() and (res.complementarity == 0).all()


def test_a_kkt_point_passes_and_a_wrong_signed_multiplier_fails():
    problem = short_pendulum()
    x0 = problems.sample_x0("pendulum", 2, seed=0)
    sol = tt.solve(problem, x0, method="ipm")
    assert (sol.status == tt.Status.CONVERGED).all()
    assert max(float(v.max()) for v in sol.kkt.values()) < 1e-7
    params = problem.batched_params(2)
    c = Constraints.of(problem)
    active = sol.multipliers["u_upper"].abs() > 1e-3
    assert active.any()  # the torque bound holds, so a multiplier is nonzero
    upper = sol.multipliers["u_upper"]
    flipped = {**sol.multipliers, "u_upper": torch.where(active, -upper, upper)}
    status, res = certificate.certify(problem, sol.status, sol.X, sol.U, flipped, params, x0, c)
    assert (res.dual_sign > 1e-3).all() and (res.stationarity > 1e-3).all()
    assert (status == tt.Status.STALLED).all()


def test_complementarity_and_feasibility_are_measured():
    problem = short_pendulum()
    x0 = problems.sample_x0("pendulum", 1, seed=0)
    sol = tt.solve(problem, x0, method="ipm")
    params, c = problem.batched_params(1), Constraints.of(problem)
    # a multiplier on a bound row that is far from active: z g is its value times the slack
    inactive = sol.multipliers["u_lower"].abs() < 1e-9
    z = torch.where(inactive, torch.full_like(sol.multipliers["u_lower"], 0.5), sol.multipliers["u_lower"])
    res = certificate.residuals(problem, sol.X, sol.U, {**sol.multipliers, "u_lower": z}, params, x0, c)
    slack = (sol.U - problem.u_lower).squeeze(-1)[inactive.squeeze(-1)]
    assert float(res.complementarity) == pytest.approx(float((0.5 * slack).max()), rel=1e-9)
    # a state moved off its dynamics: the defect is the violation
    X = sol.X.clone()
    X[:, 5, 0] += 0.25
    res = certificate.residuals(problem, X, sol.U, sol.multipliers, params, x0, c)
    assert float(res.feasibility) >= 0.25 - 1e-12


@pytest.mark.slow  # two full ALTRO solves of the pendulum; iLQR's test below checks the same in the default run
def test_altro_with_its_paper_tolerances_stops_short_and_says_so():
    """Altro.jl's stopping tolerances end the pendulum well above its optimum; ALTRO's own tests accept that
    point, the certificate does not. The defaults reach the optimum, which it accepts."""
    problem = problems.get("pendulum")
    fast = tt.solve(problem, method="altro", options=tt.ALTROOptions.fast())
    assert fast.status.item() == tt.Status.STALLED
    assert float(fast.kkt["stationarity"]) > 1e-6
    default = tt.solve(problem, method="altro")
    assert default.status.item() == tt.Status.CONVERGED
    assert float(fast.cost) > 1.05 * float(default.cost)


def test_ilqr_with_its_paper_tolerances_stops_short_and_says_so():
    problem = problems.get("pendulum_unconstrained")
    fast = tt.solve(problem, method="ilqr", options=tt.ILQROptions.fast())
    default = tt.solve(problem, method="ilqr")
    assert fast.status.item() == tt.Status.STALLED and default.status.item() == tt.Status.CONVERGED
    assert float(default.kkt["stationarity"]) < 1e-6 < float(fast.kkt["stationarity"])


def test_the_tolerances_follow_the_dtype():
    single, double = certificate.Tolerances.for_dtype(torch.float32), certificate.Tolerances.for_dtype(F64)
    assert single.stationarity > double.stationarity and double.stationarity == 1e-6


def test_the_history_records_the_stationarity_of_every_iterate():
    """iLQR's first history row is at the guess: its stationarity is autograd's ∇_U J(rollout(U0)); every method
    records one per iteration, and it falls to the certificate's tolerance where the solve converged."""
    problem = problems.get("pendulum_unconstrained").replace(horizon=12, u_init=torch.full((1,), 0.3, dtype=F64))
    x0 = problems.sample_x0("pendulum_unconstrained", 2, seed=1)
    sol = tt.solve(problem, x0, method="ilqr")
    params = problem.batched_params(2)
    Ug = problem.u_init.expand(2, 12, 1).clone().requires_grad_(True)
    cost = tt.kkt.total_cost(problem, rollout(problem.dynamics, x0, Ug, params), Ug, params).sum()
    (gradient,) = torch.autograd.grad(cost, Ug)
    torch.testing.assert_close(sol.history.extra["stationarity"][:, 0], gradient.abs().flatten(1).amax(1),
                               rtol=1e-10, atol=1e-14)
    for method in ("altro", "al-ilqr", "ipm", "eilqr", "hm-ilqr"):
        sol = tt.solve(problems.get("double_integrator"), method=method)
        history = sol.history.extra["stationarity"]
        assert history.shape == sol.history.cost.shape and sol.status[0] == tt.Status.CONVERGED, method
        assert float(history[0, 0]) > 1e-3 and float(history[0, -1]) < 1e-4, (method, history[0, [0, -1]])


@pytest.mark.parametrize("name, B, method", [("pendulum", 1, "ipm"), ("car_3obs", 2, "ipm"), ("car_3obs", 2, "eilqr")])
def test_recorded_residuals_are_the_eager_ones_to_the_last_bit(name, B, method):
    """A controller certifies every step: the residuals replay from a recorded graph (record=True, traced at the
    eighth call), with every bit of the eager computation. eILQR's control steps certify its declared problem (the
    inequalities as soft barriers, whose costs read the original rows' tensors): recorded as well."""
    solver = solvers.get(method)
    options = solver.step_options(None, 15)
    problem = problems.get(name)
    x0 = problems.sample_x0(name, B, seed=0) if B > 1 else problem.x0.expand(1, -1)
    sol = tt.solve(problem, x0=x0, method=method, options=options)
    problem = solver.kkt_problem(problem, options) or problem
    c, params = Constraints.of(problem), problem.batched_params(B)
    eager = certificate.residuals(problem, sol.X, sol.U, sol.multipliers, params, x0, c, record=False)
    traces = certificate._RECORDED_RESIDUALS.traces
    for _ in range(TRACE_AT + 1):
        recorded = certificate.residuals(problem, sol.X, sol.U, sol.multipliers, params, x0, c, record=True)
    assert certificate._RECORDED_RESIDUALS.traces == traces + 1
    replay = next(reversed(certificate._RECORDED_RESIDUALS.records.values()))[0]
    assert isinstance(replay, (Scripted, torch.fx.GraphModule))  # traced, not left eager
    for key, value in eager.as_dict().items():
        assert torch.equal(recorded.as_dict()[key], value), key


@pytest.mark.parametrize("name", ["car_3obs", "parallel_park", "quadrotor2d"])
def test_the_feasibility_is_the_largest_violation_to_the_last_bit(name):
    """The residuals take the violation from the dynamics' and the rows' values they evaluate for the derivatives:
    the same numbers as :func:`~torchtraj.kkt.merit.largest_violation` evaluating them again, at points off the
    constraints, with and without an initial defect."""
    problem = problems.get(name)
    c, params = Constraints.of(problem), problem.batched_params(3)
    g = torch.Generator().manual_seed(3)
    X = problem.x0 + 0.5 * torch.randn(3, problem.N + 1, problem.nx, dtype=F64, generator=g)
    U = torch.randn(3, problem.N, problem.nu, dtype=F64, generator=g)
    multipliers = {k: torch.rand(3, *v.shape[1:], dtype=F64, generator=g)
                   for k, v in tt.solve(problem, method="ipm", options={"iterations": 1}).multipliers.items()}
    for x0 in (None, problem.x0 + torch.randn(3, problem.nx, dtype=F64, generator=g)):
        res = certificate.residuals(problem, X, U, multipliers, params, x0, c)
        violation = tt.kkt.largest_violation(problem, X, U, params, x0=x0, constraints=c)
        assert (violation > 0).all() and torch.equal(res.feasibility, violation)


def test_a_compiled_solves_residuals_are_one_kernel_with_the_eager_values(dynamo_capture):
    """A compiled solve certifies its answer in one kernel call (``compile=True``): Dynamo's capture of the residuals
    is one graph with no break, and gives every bit of the eager computation (the capture runs the same operators;
    inductor's kernels round their own way)."""
    from torchtraj.core import compiled

    problem, x0 = problems.get("car_3obs"), problems.sample_x0("car_3obs", 2, seed=0)
    sol = tt.solve(problem, x0=x0, method="ipm")
    c, params = Constraints.of(problem), problem.batched_params(2)
    eager = certificate.residuals(problem, sol.X, sol.U, sol.multipliers, params, x0, c)
    kernel = certificate.residuals(problem, sol.X, sol.U, sol.multipliers, params, x0, c, compile=True)
    assert set(compiled._KERNELS) == {certificate._residuals}
    assert not dict(dynamo_capture["graph_break"]) and dynamo_capture["stats"]["unique_graphs"] == 1
    for key, value in eager.as_dict().items():
        assert torch.equal(kernel.as_dict()[key], value), key
