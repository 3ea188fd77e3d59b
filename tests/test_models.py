"""The torch models against their independent CasADi twins and the problem set's formulas; torch.func use."""

import math

import numpy as np
import pytest
import torch
from torch.func import hessian, jacfwd, jacrev, vmap

from torchtraj import models

SCALES = {  # typical magnitudes of the state and control components, for random test points
    "double_integrator": ([2.0, 2.0], [3.0]),
    "pendulum": ([math.pi, 5.0], [3.0]),
    "cartpole": ([1.0, math.pi, 2.0, 5.0], [3.0]),
    "unicycle": ([3.0, 3.0, math.pi], [2.0, 2.0]),
    "quadrotor2d": ([5.0, 5.0, 1.0, 2.0, 2.0, 2.0], [10.0, 10.0]),
    "acrobot": ([math.pi, math.pi, 5.0, 5.0], [5.0]),
}


def points(name: str, count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    xs, us = (np.asarray(s) for s in SCALES[name])
    X = rng.uniform(-1, 1, (count, len(xs))) * xs
    U = rng.uniform(-1, 1, (count, len(us))) * us
    return torch.from_numpy(X), torch.from_numpy(U)


def perturbed_params(model: models.Model, seed: int = 0) -> dict:
    """Each parameter scaled by its own factor in [0.5, 1.5], so swapped parameters cannot agree by chance."""
    rng = np.random.default_rng(seed)
    return {k: v * float(rng.uniform(0.5, 1.5)) for k, v in model.params.items()}


def test_registry():
    assert models.names() == ["double_integrator", "pendulum", "cartpole", "unicycle", "quadrotor2d", "acrobot"]
    assert set(SCALES) == set(models.names())
    assert float(models.get("pendulum", mass=2.0).params["mass"]) == 2.0
    with pytest.raises(ValueError, match="unknown model"):
        models.get("bicycle")


@pytest.mark.parametrize("name", models.names())
def test_model_shapes_and_params(name):
    model = models.get(name)
    assert (len(model.state_names), len(model.control_names)) == (model.nx, model.nu)
    for key, value in model.params.items():
        assert value.dtype == torch.float64 and value.dim() == 0, key
        assert key not in {"goal", "Q", "R", "Qf", "obstacles"}
    X, U = points(name, 1)
    assert model.dynamics(X[0], U[0], model.params).shape == (model.nx,)


@pytest.mark.parametrize("name", models.names())
@pytest.mark.parametrize("params", ["default", "perturbed"])
def test_matches_casadi_twin(name, params):
    pytest.importorskip("casadi")
    from torchtraj.bench import casadi_models

    model = models.get(name)
    p = model.params if params == "default" else perturbed_params(model)
    X, U = points(name, 20)
    ours = vmap(model.dynamics, in_dims=(0, 0, None))(X, U, p)
    floats = {k: float(v) for k, v in p.items()}
    theirs = np.stack([casadi_models.evaluate(name, x, u, floats) for x, u in zip(X.numpy(), U.numpy())])
    np.testing.assert_allclose(ours.numpy(), theirs, rtol=1e-12, atol=1e-12)


def test_pendulum_is_problems_md_formula():
    model = models.pendulum()
    X, U = points("pendulum", 50)
    theta, omega, tau = X[:, 0], X[:, 1], U[:, 0]
    expected = torch.stack([omega, tau / 0.25 - 9.81 * torch.sin(theta) / 0.5 - 0.1 * omega / 0.25], 1)
    ours = vmap(model.dynamics, in_dims=(0, 0, None))(X, U, model.params)
    torch.testing.assert_close(ours, expected, rtol=1e-13, atol=1e-13)


def test_cartpole_satisfies_problems_md_manipulator_equation():
    """H q̈ = −(C q̇ + G − [F, 0]) with the problem set's matrices, checked row by row."""
    model = models.cartpole()
    mc, mp, l, g = 1.0, 0.2, 0.5, 9.81
    X, U = points("cartpole", 50)
    xdot = vmap(model.dynamics, in_dims=(0, 0, None))(X, U, model.params)
    th, thd, F = X[:, 1], X[:, 3], U[:, 0]
    s, c = torch.sin(th), torch.cos(th)
    xdd, thdd = xdot[:, 2], xdot[:, 3]
    row1 = (mc + mp) * xdd + mp * l * c * thdd - (mp * thd * l * s * thd + F)
    row2 = mp * l * c * xdd + mp * l**2 * thdd + mp * g * l * s
    torch.testing.assert_close(row1, torch.zeros_like(row1), atol=1e-12, rtol=0)
    torch.testing.assert_close(row2, torch.zeros_like(row2), atol=1e-12, rtol=0)
    torch.testing.assert_close(xdot[:, :2], X[:, 2:])


def test_quadrotor_inertia_from_mass_and_arm():
    model = models.quadrotor2d(mass=2.0, arm_length=0.5)
    x, u = torch.zeros(6, dtype=torch.float64), torch.tensor([1.0, 3.0], dtype=torch.float64)
    J = 0.2 * 2.0 * 0.5**2
    assert float(model.dynamics(x, u, model.params)[5]) == pytest.approx(0.25 * 2.0 / J, rel=1e-14)


@pytest.mark.parametrize("name", models.names())
def test_torch_func_transforms(name):
    """vmap matches a loop; jacrev = jacfwd on x, u and the parameters; the Hessian is symmetric."""
    model = models.get(name)
    p = model.params
    X, U = points(name, 5)
    batched = vmap(model.dynamics, in_dims=(0, 0, None))(X, U, p)
    looped = torch.stack([model.dynamics(x, u, p) for x, u in zip(X, U)])
    torch.testing.assert_close(batched, looped, rtol=0, atol=0)

    jr = vmap(jacrev(model.dynamics, argnums=(0, 1)), in_dims=(0, 0, None))(X, U, p)
    jf = vmap(jacfwd(model.dynamics, argnums=(0, 1)), in_dims=(0, 0, None))(X, U, p)
    assert jr[0].shape == (5, model.nx, model.nx) and jr[1].shape == (5, model.nx, model.nu)
    torch.testing.assert_close(jr, jf)

    if p:
        jp = jacrev(model.dynamics, argnums=2)(X[0], U[0], p)
        assert set(jp) == set(p) and all(v.shape == (model.nx,) for v in jp.values())

    H = hessian(lambda x: model.dynamics(x, U[0], p).sum())(X[0])
    torch.testing.assert_close(H, H.T)


@pytest.mark.parametrize("name", models.names())
def test_discrete_step(name):
    model = models.get(name)
    X, U = points(name, 3)
    x, u, p = X[0], U[0], model.params
    dt = 0.01
    f = model.dynamics(x, u, p)
    torch.testing.assert_close(model.discrete(dt, "euler")(x, u, p), x + dt * f)
    # RK4 agrees with Euler to O(dt²) and with a fine Euler integration to far better
    fine = x
    for _ in range(1000):
        fine = fine + dt / 1000 * model.dynamics(fine, u, p)
    rk4 = model.discrete(dt)(x, u, p)
    assert float((rk4 - fine).abs().max()) < 1e-5 * (1 + float(f.abs().max()))
    with pytest.raises(ValueError, match="integrator"):
        model.discrete(dt, "midpoint")
