"""Float32 solves of the barrier methods (HM-iLQR, eILQR) from their default options: the constrained double
integrator a README user writes (float32 tensors), a batch of feasible starts, against IPOPT's optima and the
gradients of the optimal cost (central differences of IPOPT optima, ``tests/data/make_float32_reference.py``).

Every instance must converge (the KKT certificate's float32 tolerances) and its gradient from the implicit layer
must be IPOPT's to 1e-3: the methods' tolerances below float32's resolution are met at its resolution
(``HMILQROptions.tolerances``, ``EILQROptions.tolerance_for``)."""

import json
from pathlib import Path

import pytest
import torch
from small_problems import velocity_bounded_double_integrator

import torchtraj as tt

F32 = torch.float32
REFERENCE = json.loads((Path(__file__).parent / "data" / "float32_reference.json").read_text())[
    "double_integrator_v_bound"]


FIXED = tt.EILQROptions(barrier_continuation=False)


double_integrator = velocity_bounded_double_integrator  # float32 by default


@pytest.mark.parametrize("method", ["hm-ilqr", "eilqr"])
def test_converges_in_float32_at_ipopts_optimum_and_gradient(method):
    """Every instance converges at IPOPT's optimum, with its gradient. eILQR by its default barrier continuation
    (primal-dual steps, the last weight 1e-7 in float32); with the paper's fixed weight (the test below) the
    instances with an active velocity bound stopped STALLED, the multipliers read off the barrier carrying float32's
    rounding."""
    x0 = torch.tensor([r["x0"] for r in REFERENCE], dtype=F32, requires_grad=True)
    sol = tt.solve(double_integrator(), x0, method=method)
    (grad,) = torch.autograd.grad(sol.cost.sum(), x0)
    assert sol.X.dtype == F32
    assert bool((sol.status == tt.Status.CONVERGED).all()), (sol.status, sol.kkt)
    cost = torch.tensor([r["cost"] for r in REFERENCE], dtype=torch.float64)
    expected = torch.tensor([r["grad_x0"] for r in REFERENCE], dtype=torch.float64)
    assert float(((sol.cost.detach().double() - cost) / cost).abs().max()) < 1e-5
    relative = (grad.double() - expected).norm(dim=-1) / expected.norm(dim=-1)
    assert float(relative.max()) < 1e-3, relative


@pytest.mark.slow
def test_eilqr_in_float32_stops_at_the_resolution_of_its_soft_barrier():
    """With the paper's fixed weight (``barrier_continuation=False``), eILQR's soft problem (``w = 1e-4``, ``δ = 1e-5``)
    cannot be solved to the certificate's float32 tolerance where an active row's barrier curvature ``z*²/w`` times
    float32's rounding of the row exceeds it: the float64 optimum rounded to float32 has the same stationarity residual,
    up to 5e-3 here. Each such instance stops once its full Newton step is below float32's resolution (it ran to the
    iteration limit, 200, before) and is reported ``STALLED``; the others converge, at IPOPT's optimum and gradient up
    to the soft barrier's gap (1.1e-4 and 1.4e-4 relative in float64)."""
    x0 = torch.tensor([r["x0"] for r in REFERENCE], dtype=F32, requires_grad=True)
    with pytest.warns(RuntimeWarning, match="did not converge"):
        sol = tt.solve(double_integrator(), x0, method="eilqr", options=FIXED)
        (grad,) = torch.autograd.grad(sol.cost.sum(), x0)
    converged = sol.status == tt.Status.CONVERGED
    assert bool((converged | (sol.status == tt.Status.STALLED)).all()), sol.status
    assert int(sol.iterations.max()) < 100
    assert int(converged.sum()) >= 5  # measured: 5 of 8
    tolerance = 1e-3  # the certificate's float32 stationarity tolerance
    assert bool((sol.kkt["stationarity"][~converged] > tolerance).all())
    cost = torch.tensor([r["cost"] for r in REFERENCE], dtype=torch.float64)[converged]
    expected = torch.tensor([r["grad_x0"] for r in REFERENCE], dtype=torch.float64)[converged]
    assert float(((sol.cost.detach().double()[converged] - cost) / cost).abs().max()) < 2e-4
    relative = (grad.double()[converged] - expected).norm(dim=-1) / expected.norm(dim=-1)
    assert float(relative.max()) < 1e-3, relative
