"""ALTRO's extensions: square-root backward pass, infeasible start, time-penalised problems."""

import pytest
import torch

import torchtraj as tt
from torchtraj.bench.time_penalized import solve_time_penalized
from torchtraj.core.batching import rollout
from torchtraj.core.constraints import Constraints
from torchtraj.riccati import factorize
from torchtraj.riccati.square_root import downdate, factorize_sqrt
from torchtraj.solvers.altro.augmented_lagrangian import AugmentedLagrangian, Duals


def test_downdate_is_a_cholesky_factor_of_the_difference():
    g = torch.Generator().manual_seed(0)
    A = torch.randn(4, 6, 3, generator=g, dtype=torch.float64)
    C = 0.3 * torch.randn(4, 2, 3, generator=g, dtype=torch.float64)
    R = torch.linalg.cholesky(A.mT @ A).mT
    D, ok = downdate(R, C)
    assert bool(ok.all())
    assert torch.allclose(D.mT @ D, A.mT @ A - C.mT @ C, atol=1e-12)
    assert torch.equal(D, torch.triu(D))
    _, bad = downdate(R, 10 * R)  # not positive definite: reported, not returned as garbage
    assert not bool(bad.any())


def test_square_root_factor_equals_standard_on_an_augmented_lagrangian_expansion():
    problem = tt.problems.get("cartpole")
    c = Constraints(problem)
    params = problem.batched_params(1)
    U = problem.u_init.expand(1, problem.N, problem.nu).clone()
    X = rollout(problem.dynamics, problem.x0[None], U, params)
    duals = Duals.initial(c, 1, 1e3, X)  # stiff penalties: where the square-root form matters
    for sq in (False, True):
        lqr, rhs = AugmentedLagrangian(c, duals, square_root=sq).expand(X, U, params)
        if sq:
            assert lqr.root is not None and lqr.rootN is not None
            fs = factorize_sqrt(lqr).solve(rhs)
        else:
            f = factorize(lqr).solve(rhs)
    scale = f.du.abs().max()
    assert torch.allclose(fs.du, f.du, atol=1e-9 * scale, rtol=0)
    assert torch.allclose(fs.dV1, f.dV1, rtol=1e-9)


def test_square_root_altro_matches_standard_in_float64():
    problem = tt.problems.get("double_integrator")
    std = tt.solve(problem, method="altro", options=tt.problems.altro_options("double_integrator"))
    sq = tt.solve(problem, method="altro", options=tt.problems.altro_options("double_integrator", square_root=True))
    assert sq.status[0] == tt.Status.CONVERGED
    assert torch.allclose(sq.U, std.U, atol=1e-8) and abs(float(sq.cost[0] - std.cost[0])) < 1e-10


def test_infeasible_start_recovers_the_feasible_optimum():
    """A straight-line state guess the dynamics cannot follow; the slacks vanish and the optimum is IPOPT's."""
    problem = tt.problems.get("double_integrator")
    guess = torch.linspace(0, 1, problem.N + 1, dtype=torch.float64)
    X0 = torch.stack([guess, torch.full_like(guess, 0.5)], -1)  # v = 0.5 but p ramps at 0.5/s: infeasible
    sol = tt.solve(problem, method="altro", X0=X0, options=tt.problems.altro_options("double_integrator"))
    ref = tt.solve(problem, method="altro", options=tt.problems.altro_options("double_integrator"))
    assert sol.status[0] == tt.Status.CONVERGED and float(sol.max_violation[0]) <= 1e-8
    assert abs(float(sol.cost[0] - ref.cost[0])) / float(ref.cost[0]) < 1e-6
    assert sol.U.shape == ref.U.shape  # slack controls are gone


def test_infeasible_start_takes_warm_duals():
    """``duals`` also start the infeasible start: from its own solution and multipliers it only confirms them."""
    problem = tt.problems.get("double_integrator")
    opts = tt.problems.altro_options("double_integrator")
    guess = torch.linspace(0, 1, problem.N + 1, dtype=torch.float64)
    X0 = torch.stack([guess, torch.full_like(guess, 0.5)], -1)
    cold = tt.solve(problem, method="altro", X0=X0, options=opts)
    warm_duals = {"multipliers": cold.multipliers, "costate": cold.costate}
    warm = tt.solve(problem, method="altro", X0=cold.X, U0=cold.U, options=opts, duals=warm_duals)
    unwarmed = tt.solve(problem, method="altro", X0=cold.X, U0=cold.U, options=opts)
    assert warm.status[0] == unwarmed.status[0] == tt.Status.CONVERGED
    assert int(warm.iterations[0]) <= 2 < int(unwarmed.iterations[0])  # measured: 1 against 22
    assert abs(float(warm.cost[0] - cold.cost[0])) < 1e-9


@pytest.mark.slow
def test_car_escape_from_waypoints_ends_at_goal_without_collision():
    problem = tt.problems.get("car_escape")
    sol = tt.solve(problem, method="altro", X0=problem.X_init, options=tt.problems.altro_options("car_escape"))
    assert sol.status[0] == tt.Status.CONVERGED
    walls = problem.params["obstacles"]
    d2 = (sol.X[0, 1:-1, None, :2] - walls[:, :2]).pow(2).sum(-1) - walls[:, 2] ** 2
    assert float(d2.min()) >= -1e-8  # outside every wall circle
    assert torch.allclose(sol.X[0, -1], problem.params["goal"], atol=1e-8)
    # the contrast: AL-iLQR from the rollout of u_init (not the problem's X_init) stays in the first room (x < 5)
    rolled = tt.solve(problem, method="al-ilqr", options=tt.problems.altro_options("car_escape", iterations_outer=3,
                                                                                   problem_state_guess=False))
    assert float(rolled.X[0, :, 0].max()) < 5.0 or float(rolled.max_violation[0]) > 1e-3


@pytest.mark.slow  # about a minute of ALTRO iterations at the certificate's accuracy; the default run keeps the
# transform's test_time_penalized_initial_state_of_a_batch
def test_time_penalized_pendulum_is_shorter_and_feasible():
    tp, sol, _ = solve_time_penalized("pendulum")
    assert sol.status[0] == tt.Status.CONVERGED
    assert float(sol.max_violation[0]) <= 1e-6  # the paper's tolerance for time-penalised problems
    X, U, dt = tp.split(sol.X, sol.U)
    duration = float(tp.duration(sol.U)[0])
    assert duration < 0.9 * 3.0  # shorter than the fixed 3 s
    assert float(dt.max() - dt.min()) < 1e-6  # equal steps (δ_k = τ_k)
    assert float(U.abs().max()) <= 3.0 + 1e-6
    assert torch.allclose(X[0, -1], tp.original.params["goal"], atol=1e-6)


@pytest.mark.slow
def test_time_penalized_parallel_park_is_shorter_and_feasible():
    tp, sol, _ = solve_time_penalized("parallel_park")
    assert sol.status[0] == tt.Status.CONVERGED and float(sol.max_violation[0]) <= 1e-6
    assert float(tp.duration(sol.U)[0]) < 0.9 * 3.0  # measured: 2.44 s
    X, U, dt = tp.split(sol.X, sol.U)
    assert float(dt.max() - dt.min()) < 1e-6  # equal steps
    assert torch.allclose(X[0, -1], tp.original.params["goal"], atol=1e-6)
    lower, upper = tp.original.x_lower, tp.original.x_upper
    assert bool(((X[0, 1:, :2] >= lower[:2] - 1e-6) & (X[0, 1:, :2] <= upper[:2] + 1e-6)).all())


@pytest.mark.slow
@pytest.mark.parametrize("square_root", [True, False])
def test_float32_cartpole_reaches_the_float64_solution(square_root, reference):
    """float32 ALTRO on the cart-pole: cost within 1e-4 relative of the float64 optimum, violation within 1e-4.
    Measured (2 cores): square-root pass 2.4e-5 relative, violation 2.1e-6; standard pass 1.5e-5, 1.9e-6."""
    from torchtraj.solvers.altro.projection import ProjectionOptions

    problem = tt.problems.get("cartpole", dtype=torch.float32)
    opts = tt.problems.altro_options("cartpole", square_root=square_root, cost_tolerance=1e-6,
                                     cost_tolerance_intermediate=1e-4, constraint_tolerance=1e-4,
                                     projection_options=ProjectionOptions(tolerance=1e-5))
    sol = tt.solve(problem, method="altro", options=opts)
    optimum = reference["cartpole"]["ipopt"]["cost"]
    assert sol.status[0] == tt.Status.CONVERGED
    assert abs(float(sol.cost[0]) - optimum) / optimum < 1e-4
    assert float(sol.max_violation[0]) < 1e-4


def test_time_penalized_initial_state_of_a_batch():
    problem = tt.problems.get("pendulum")
    tp = tt.time_penalized(problem, tt.models.get("pendulum").dynamics)
    x0 = tt.problems.sample_x0("pendulum", 3, seed=0)
    lifted = tp.initial_state(x0)
    assert torch.equal(tp.initial_state(problem.x0), tp.problem.x0)
    assert torch.equal(lifted[:, :2], x0) and torch.allclose(
        lifted[:, 2], torch.full((3,), problem.dt ** 0.5, dtype=torch.float64))
    assert bool((lifted[:, 3] == 0).all())  # the equal-step switch is off at k = 0
