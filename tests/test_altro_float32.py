"""ALTRO and AL-iLQR in float32 (issue 23, item 3): the constrained double integrator of the README, B = 32.

The reference is IPOPT (``tests/data/float32_di_reference.json``, ``make_float32_di_reference.py``): the optimal
costs and the derivatives of the optimal cost with respect to ``x0``, one-sided where the optimum has a weakly active
bound (there LICQ fails and the implicit layer gives zero, with a warning). Before the fixes float32 ALTRO converged 8
of 32 instances (its projection asked for defects of 1e-8, below float32's 6e-8), AL-iLQR's float32 multipliers were off
by up to 6 (penalties of 1e8 times the rounding of the constraints), and float64 AL-iLQR stopped 4 of 32 with
``λ c = 3e-6`` (certified STALLED)."""

import json
import warnings
from pathlib import Path

import pytest
import torch
from small_problems import velocity_bounded_double_integrator

import torchtraj as tt

REF = json.loads((Path(__file__).parent / "data" / "float32_di_reference.json").read_text())["instances"]


double_integrator = velocity_bounded_double_integrator  # the problem as a README user writes it


def solve_with_gradient(method, dtype):
    x0 = torch.tensor([r["x0"] for r in REF], dtype=dtype, requires_grad=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="implicit gradients")  # the LICQ instances (assert_matches_ipopt)
        sol = tt.solve(double_integrator(dtype), x0, method=method)
    grad, = torch.autograd.grad(sol.cost.sum(), x0, allow_unused=True)
    return sol, grad


def assert_matches_ipopt(sol, grad, cost_rtol, grad_rtol):
    cost = torch.tensor([r["cost"] for r in REF], dtype=torch.float64)
    forward, backward = (torch.tensor([r[k] for r in REF], dtype=torch.float64) for k in ("forward", "backward"))
    assert torch.allclose(sol.cost.double(), cost, rtol=cost_rtol, atol=0)
    scale = forward.abs().amax(-1).clamp_min(1.0)
    # the clamped speeds put 11 instances where a control bound and a speed bound meet at one knot (v_0 = 0.4, u_0 = 1
    # gives v_1 = 0.5): LICQ fails, the two one-sided derivatives differ and the implicit layer returns zero
    kink = (forward - backward).abs().amax(-1) / scale > 1e-3
    assert int(kink.sum()) == 11
    assert bool((grad[kink] == 0).all())
    error = (grad.double() - forward).abs().amax(-1) / scale
    assert float(error[~kink].max()) <= grad_rtol, error


@pytest.mark.parametrize("method", ["altro", "al-ilqr"])
def test_float32_double_integrator_converges_with_ipopts_gradients(method):
    sol, grad = solve_with_gradient(method, torch.float32)
    assert grad.dtype == torch.float32 and sol.multipliers["u_upper"].dtype == torch.float32
    assert bool((sol.status == tt.Status.CONVERGED).all()), sol.status
    assert float(sol.max_violation.max()) <= 1e-6
    assert_matches_ipopt(sol, grad, cost_rtol=1e-6, grad_rtol=1e-3)


def test_float64_al_ilqr_stops_at_complementary_points():
    sol, grad = solve_with_gradient("al-ilqr", torch.float64)
    assert bool((sol.status == tt.Status.CONVERGED).all()), sol.status  # 28 of 32 before
    assert float(sol.kkt["complementarity"].max()) <= 1e-6
    assert_matches_ipopt(sol, grad, cost_rtol=1e-7, grad_rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["altro", "al-ilqr"])
def test_float32_gradients_equal_float64s(method):
    """Issue 23's "Done when": all 32 converge in both dtypes, float32's gradients equal float64's to 1e-3."""
    s32, g32 = solve_with_gradient(method, torch.float32)
    s64, g64 = solve_with_gradient(method, torch.float64)
    assert bool((s32.status == tt.Status.CONVERGED).all()) and bool((s64.status == tt.Status.CONVERGED).all())
    assert_matches_ipopt(s64, g64, cost_rtol=1e-7, grad_rtol=1e-5)
    rel = (g32.double() - g64).norm(dim=-1) / g64.norm(dim=-1).clamp_min(1e-12)
    assert float(rel.max()) <= 1e-3, rel


def test_float32_al_ilqr_multipliers_make_the_pendulum_stationary():
    """Eq. (17)'s estimate λ + μ c carries μ times the rounding of ``x_N`` (2.4e-5 at μ = 100 and |x_N| = π), which
    the unstable dynamics amplify: stationarity 3e-3 here before (STALLED); the least-squares multipliers of the held
    rows make it a KKT point. Started from IPOPT's optimal controls, whose cost is the reference
    (``tests/data/reference.json``)."""
    reference = json.loads((Path(__file__).parent / "data" / "reference.json").read_text())["pendulum"]["ipopt"]
    U0 = torch.tensor(reference["U"], dtype=torch.float32)[None]
    sol = tt.solve(tt.problems.get("pendulum", dtype=torch.float32), method="al-ilqr", U0=U0)
    assert sol.status.tolist() == [int(tt.Status.CONVERGED)]
    assert float(sol.kkt["stationarity"].max()) <= 1e-5
    assert abs(float(sol.cost[0]) - reference["cost"]) <= 1e-5 * reference["cost"]


@pytest.mark.slow
def test_float32_al_ilqr_converges_on_a_pendulum_start():
    """An instance of the problem set's pendulum batch (stationarity 1.6e-2 before), from its default start; IPOPT's
    optimal cost of this instance is the reference."""
    x0 = tt.problems.sample_x0("pendulum", 64, 0)[1:2]
    sol = tt.solve(tt.problems.get("pendulum", dtype=torch.float32), x0.float(), method="al-ilqr")
    assert sol.status.tolist() == [int(tt.Status.CONVERGED)]
    reference = json.loads((Path(__file__).parent / "data" / "reference.json").read_text())
    optimum = reference["pendulum_batch_seed0_ipopt"]["costs"][1]
    assert abs(float(sol.cost[0]) - optimum) <= 1e-5 * optimum
