"""The problem API: construction-time checks, clear errors, and input broadcasting in tt.solve."""

import pytest
import torch

import torchtraj as tt


def make(**changes):
    base = dict(
        dynamics=tt.rk4(lambda x, u, p: torch.stack([x[1], u[0] - p["k"] * x[0]]), 0.1),
        stage_cost=lambda x, u, p: 0.5 * (x * x).sum() + 0.5 * (u * u).sum(),
        terminal_cost=lambda x, p: 10.0 * (x * x).sum(),
        x0=torch.tensor([1.0, 0.0], dtype=torch.float64),
        horizon=10,
        nu=1,
        params={"k": torch.tensor(2.0, dtype=torch.float64)},
    )
    base.update(changes)
    return tt.Problem(**base)


def test_wrong_dynamics_shape_names_the_function():
    with pytest.raises(ValueError, match=r"dynamics must return shape \(2,\)"):
        make(dynamics=lambda x, u, p: torch.cat([x, u]))


def test_non_scalar_cost_and_non_finite_output_are_rejected():
    with pytest.raises(ValueError, match="stage_cost must return a scalar"):
        make(stage_cost=lambda x, u, p: x * x)
    with pytest.raises(ValueError, match="terminal_cost returned non-finite"):
        make(terminal_cost=lambda x, p: (x * x).sum() / 0.0)


def test_a_failing_function_is_named():
    with pytest.raises(ValueError, match="stage_eq failed on a probe call"):
        make(stage_eq=lambda x, u, p: x[5])


def test_bad_bounds_and_guesses_are_rejected():
    with pytest.raises(ValueError, match=r"u_lower must have shape \(1,\)"):
        make(u_lower=torch.zeros(2))
    with pytest.raises(ValueError, match="u_lower exceeds"):
        make(u_lower=torch.ones(1), u_upper=-torch.ones(1))
    with pytest.raises(ValueError, match="u_init must have shape"):
        make(u_init=torch.zeros(3, 1))


def test_solve_checks_and_broadcasts_inputs():
    prob = make()
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\) or \(B, \*\(2,\)\)"):
        tt.solve(prob, x0=torch.zeros(3))
    with pytest.raises(ValueError, match="batch sizes disagree"):
        tt.solve(prob, x0=torch.zeros(3, 2), U0=torch.zeros(4, 10, 1))
    with pytest.raises(ValueError, match="unknown method"):
        tt.solve(prob, method="newton")
    with pytest.raises(TypeError, match="options for method 'ilqr'"):
        tt.solve(prob, options=3)
    with pytest.raises(ValueError, match="cannot take X0"):
        tt.solve(prob, X0=torch.zeros(11, 2))
    sol = tt.solve(prob, x0=torch.randn(3, 2, dtype=torch.float64), options={"cost_tolerance": 1e-10})
    assert sol.X.shape == (3, 11, 2) and sol.status.shape == (3,)


def test_batched_parameters_solve_each_instance_with_its_own_value():
    prob = make()
    stiff = torch.tensor([0.5, 2.0, 4.0], dtype=torch.float64)
    batched = tt.solve(prob.with_params(k=stiff), options={"cost_tolerance": 1e-12})
    for i in range(3):
        alone = tt.solve(prob.with_params(k=stiff[i]), options={"cost_tolerance": 1e-12})
        assert torch.allclose(batched.U[i], alone.U[0], atol=1e-9)
    with pytest.raises(ValueError, match="unknown parameters"):
        prob.with_params(mass=stiff)


def test_linear_quadratic_declaration_is_checked():
    """``linear_quadratic=True`` is accepted for an affine model with quadratic costs (RK4 of a linear ODE is
    linear) and refused, naming the function, where a Jacobian or a cost Hessian is not constant."""
    assert make(linear_quadratic=True).linear_quadratic
    with pytest.raises(ValueError, match="dynamics is not affine"):
        make(dynamics=lambda x, u, p: torch.stack([x[1], u[0] - p["k"] * torch.sin(x[0])]), linear_quadratic=True)
    with pytest.raises(ValueError, match="stage_cost is not quadratic"):
        make(stage_cost=lambda x, u, p: (x ** 4).sum() + (u * u).sum(), linear_quadratic=True)
    with pytest.raises(ValueError, match="terminal_ineq is not affine"):
        make(terminal_ineq=lambda x, p: (x * x).sum(-1, keepdim=True) - 1.0, linear_quadratic=True)
    make(stage_ineq=lambda x, u, p: torch.cat([x[:1] - 2.0, u - 1.0]), linear_quadratic=True)


def test_to_takes_a_dtype_and_a_device_as_tensor_to_does():
    """``problem.to("cpu")`` and ``problem.to(torch.float32)`` read as ``Tensor.to``'s: the first positional argument
    was once the dtype, so a device string reached ``Tensor.to`` as a dtype and raised a TypeError about it."""
    problem = make(u_lower=torch.tensor([-1.0], dtype=torch.float64), u_upper=torch.tensor([1.0], dtype=torch.float64))
    for moved in (problem.to(torch.float32), problem.to("cpu", torch.float32), problem.to(torch.float32, "cpu"),
                  problem.to(dtype=torch.float32, device="cpu")):
        for t in (moved.x0, moved.params["k"], moved.u_lower, moved.u_upper):
            assert (t.dtype, t.device) == (torch.float32, torch.device("cpu"))
    same = problem.to("cpu")
    assert (same.x0.dtype, same.x0.device) == (torch.float64, torch.device("cpu"))
    assert problem.to(torch.device("cpu"), dtype=torch.float32).u_lower.dtype == torch.float32
    with pytest.raises(TypeError, match="takes a dtype and a device"):
        problem.to(1.5)
    with pytest.raises(TypeError, match="takes a dtype and a device"):
        problem.to(torch.float32, torch.float64)
