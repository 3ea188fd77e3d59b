"""iLQR against IPOPT optima and against first-order optimality computed independently by autograd."""

import dataclasses

import pytest
import torch

import torchtraj as tt
from torchtraj.core.batching import rollout
from torchtraj.kkt import total_cost

TIGHT = tt.ILQROptions(cost_tolerance=1e-10, gradient_tolerance=1e-6)


def reduced_gradient(problem, x0, U):
    """dJ/dU of the single-shooting objective by plain autograd through a rollout (no Riccati)."""
    U = U.detach().clone().requires_grad_(True)
    params = problem.batched_params(U.shape[0])
    J = total_cost(problem, rollout(problem.dynamics, x0, U, params), U, params)
    (grad,) = torch.autograd.grad(J.sum(), U)
    return grad


def test_pendulum_unconstrained_from_ipopt_optimum_stays_there(reference):
    prob = tt.problems.get("pendulum_unconstrained")
    ipopt = reference["pendulum_unconstrained"]["ipopt"]
    # start a little away from IPOPT's optimum: iLQR must come back to it
    U0 = torch.tensor(ipopt["U"], dtype=torch.float64) * 1.02
    sol = tt.solve(prob, U0=U0, options=TIGHT)
    assert sol.status[0] == tt.Status.CONVERGED
    assert abs(sol.cost[0].item() - ipopt["cost"]) / ipopt["cost"] < 1e-6


def test_pendulum_unconstrained_from_problem_guess_reaches_a_better_local_optimum(reference):
    """From the problem set's guess (u = 0.1) iLQR finds a local optimum of cost 0.0137813, below IPOPT's
    0.0435288 from the same guess: a different local minimum of this non-convex problem. We check it is
    one: converged, lower cost, and the gradient of the cost with respect to every control vanishes."""
    prob = tt.problems.get("pendulum_unconstrained")
    sol = tt.solve(prob, options=TIGHT)
    assert sol.status[0] == tt.Status.CONVERGED
    assert sol.cost[0] < reference["pendulum_unconstrained"]["ipopt"]["cost"]
    assert abs(sol.cost[0].item() - 0.0137812669) < 1e-9  # the optimum IPOPT confirms when warm-started there
    grad = reduced_gradient(prob, prob.x0.unsqueeze(0), sol.U)
    initial = reduced_gradient(prob, prob.x0.unsqueeze(0), prob.u_init.unsqueeze(0))
    assert grad.abs().max() < 1e-6 * initial.abs().max()
    assert sol.history.cost.shape == (1, int(sol.iterations[0]))
    assert bool((sol.history.cost[0, 1:] <= sol.history.cost[0, :-1] + 1e-15).all())  # monotone decrease


@pytest.mark.slow  # a minute of the default run; the same path is tested on shorter problems
def test_cartpole_unconstrained_from_perturbed_optimum(reference):
    prob = tt.problems.get("cartpole_unconstrained")
    ipopt = reference["cartpole_unconstrained"]["ipopt"]
    U0 = torch.tensor(ipopt["U"], dtype=torch.float64) + 0.05
    # iLQR's linear convergence on the cart-pole: 311 iterations (measured), past the default cap of 300
    sol = tt.solve(prob, U0=U0, options=dataclasses.replace(TIGHT, iterations=1000))
    assert sol.status[0] == tt.Status.CONVERGED
    assert abs(sol.cost[0].item() - ipopt["cost"]) / ipopt["cost"] < 1e-6


@pytest.mark.slow
def test_cartpole_unconstrained_from_problem_guess_matches_ipopt(reference):
    """About 740 iterations (100 s on two cores): iLQR's linear convergence on the cart-pole."""
    prob = tt.problems.get("cartpole_unconstrained")
    sol = tt.solve(prob, options=tt.ILQROptions(cost_tolerance=1e-10, gradient_tolerance=1e-6, iterations=1500))
    ipopt = reference["cartpole_unconstrained"]["ipopt"]["cost"]
    assert sol.status[0] == tt.Status.CONVERGED
    assert abs(sol.cost[0].item() - ipopt) / ipopt < 1e-6


@pytest.mark.slow  # the contract test checks a batch against its instances on short problems
def test_batch_of_64_pendulums_all_converge_to_stationary_points():
    prob = tt.problems.get("pendulum_unconstrained")
    x0 = tt.problems.sample_x0("pendulum_unconstrained", 64, seed=0)
    sol = tt.solve(prob, x0, options=TIGHT)
    assert sol.X.shape == (64, prob.N + 1, 2) and sol.U.shape == (64, prob.N, 1) and sol.K.shape == (64, prob.N, 1, 2)
    assert bool((sol.status == tt.Status.CONVERGED).all())
    grad = reduced_gradient(prob, x0, sol.U)
    initial = reduced_gradient(prob, x0, prob.u_init.expand(64, prob.N, 1))
    assert grad.abs().max() < 1e-6 * initial.abs().max()
    # an instance solved alone reaches the same optimum
    alone = tt.solve(prob, x0[5], options=TIGHT)
    assert abs(alone.cost[0] - sol.cost[5]) < 1e-10


def test_nan_instance_fails_alone_and_leaves_the_others_bit_for_bit():
    prob = tt.problems.get("pendulum_unconstrained")
    x0 = tt.problems.sample_x0("pendulum_unconstrained", 4, seed=1)
    opts = tt.ILQROptions(cost_tolerance=1e-8, gradient_tolerance=1e-5)
    clean = tt.solve(prob, x0, options=opts)
    broken = x0.clone()
    broken[2, 0] = float("nan")
    sol = tt.solve(prob, broken, options=opts)
    assert sol.status[2] == tt.Status.NON_FINITE
    assert tt.Status.describe(sol.status)[2] == "non_finite"
    others = [0, 1, 3]
    assert torch.equal(sol.X[others], clean.X[others])
    assert torch.equal(sol.U[others], clean.U[others])
    assert torch.equal(sol.cost[others], clean.cost[others])
    assert torch.equal(sol.status[others], clean.status[others])


def test_float32_reaches_the_float64_optimum():
    prob64 = tt.problems.get("pendulum_unconstrained")
    ref = tt.solve(prob64, options=TIGHT)
    prob = tt.problems.get("pendulum_unconstrained", dtype=torch.float32)
    sol = tt.solve(prob, options=tt.ILQROptions(cost_tolerance=1e-6, gradient_tolerance=1e-3))
    assert sol.X.dtype == torch.float32 and sol.cost.dtype == torch.float32
    assert sol.status[0] == tt.Status.CONVERGED
    assert abs(sol.cost[0].double() - ref.cost[0]) / ref.cost[0] < 1e-4


def test_iteration_limit_is_reported():
    prob = tt.problems.get("pendulum_unconstrained")
    sol = tt.solve(prob, options=tt.ILQROptions(iterations=3))
    assert sol.status[0] == tt.Status.MAX_ITERATIONS and sol.iterations[0] == 3


def test_constrained_problem_warns_that_ilqr_ignores_constraints():
    prob = tt.problems.get("pendulum")
    with pytest.warns(UserWarning, match="ignores the constraints"):
        sol = tt.solve(prob, options=tt.ILQROptions(iterations=2))
    assert sol.max_violation[0] > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_runs_on_cuda():
    prob = tt.problems.get("pendulum_unconstrained", device="cuda")
    x0 = tt.problems.sample_x0("pendulum_unconstrained", 8, seed=0).cuda()
    sol = tt.solve(prob, x0, options=TIGHT)
    assert sol.X.device.type == "cuda" and bool((sol.status == tt.Status.CONVERGED).all())
    cpu = tt.solve(tt.problems.get("pendulum_unconstrained"), x0.cpu(), options=TIGHT)
    assert torch.allclose(sol.cost.cpu(), cpu.cost, rtol=1e-8)
