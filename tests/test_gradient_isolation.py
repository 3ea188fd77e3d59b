"""A failed instance contributes exactly zero to every gradient, shared parameters included (issue 23, item 4).

The reference of each gradient is the same solve without the failed instance: a batch of instances solved
together must give the gradients of the instances solved alone, whatever the others do.
"""

import warnings

import pytest
import torch

import torchtraj as tt
from tests.small_problems import pendulum10

F64 = torch.float64
X0 = torch.tensor([[0.0, 0.0], [0.3, 0.0], [0.2, 0.1]], dtype=F64)
GOOD = [0, 2]


def goal_gradient(prob, method, x0, **params):
    """``∂(Σ_good cost)/∂goal`` with the goal shared by the batch, and the solve's statuses."""
    goal = prob.params["goal"].clone().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sol = tt.solve(prob.with_params(goal=goal, **params), x0, method=method)
    good = GOOD if x0.shape[0] == 3 else slice(None)
    (g,) = torch.autograd.grad(sol.cost[good].sum(), goal)
    return g, sol.status


@pytest.mark.parametrize("method", ["ipm", "eilqr"])
def test_a_nan_initial_state_leaves_the_shared_gradient_alone(method):
    prob = pendulum10()  # eILQR: its cost is tt.solve's own masked cost (kkt_problem)
    x0 = X0.clone()
    x0[1, 1] = float("nan")
    g, status = goal_gradient(prob, method, x0)
    reference, ref_status = goal_gradient(prob, method, X0[GOOD])
    assert status[1] != tt.Status.CONVERGED and bool((ref_status == tt.Status.CONVERGED).all())
    assert torch.isfinite(g).all()
    torch.testing.assert_close(g, reference, rtol=1e-10, atol=1e-12)


def test_an_infinite_per_instance_parameter_gets_zero_and_the_shared_one_stays_finite():
    prob = pendulum10()
    goals = torch.tensor([[2.0, 0.0], [float("inf"), 0.0], [1.5, 0.0]], dtype=F64, requires_grad=True)
    R = prob.params["R"].clone().requires_grad_(True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        sol = tt.solve(prob.with_params(goal=goals, R=R), X0, method="ipm")
    assert sol.status[1] != tt.Status.CONVERGED and bool(sol.converged[GOOD].all())
    # the failed instance's NaN cost left out of the loss by a mask
    loss = torch.where(sol.status == tt.Status.CONVERGED, sol.cost, 0).sum()
    g_goal, g_R = torch.autograd.grad(loss, (goals, R))
    assert (g_goal[1] == 0).all() and torch.isfinite(g_goal).all()
    R_ref = prob.params["R"].clone().requires_grad_(True)
    ref = tt.solve(prob.with_params(goal=goals.detach()[GOOD], R=R_ref), X0[GOOD], method="ipm")
    (reference,) = torch.autograd.grad(ref.cost.sum(), R_ref)
    torch.testing.assert_close(g_R, reference, rtol=1e-10, atol=1e-12)


def test_second_order_gradients_raise_a_clear_error():
    prob = pendulum10()
    x0 = torch.tensor([0.1, 0.0], dtype=F64, requires_grad=True)
    sol = tt.solve(prob, x0, method="ipm")
    (g,) = torch.autograd.grad(sol.cost.sum(), x0, create_graph=True)
    with pytest.raises(RuntimeError, match="first-order gradients only"):
        torch.autograd.grad(g.sum(), x0)
