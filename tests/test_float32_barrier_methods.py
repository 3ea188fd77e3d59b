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
    float32's rounding of the row exceeds it. The floor is measured here: the soft problem's float64 optimum, rounded
    to float32, has the stationarity residual 2.7e-3, 5.0e-3 and 3.1e-3 for three of the eight starts, at most 4.8e-4
    for the others. Every instance reaches its floor (at most twice it, or 1e-5); those above the tolerance stop once
    their full Newton step is below float32's resolution and are reported ``STALLED``, the others converge, at IPOPT's
    optimum and gradient up to the soft barrier's gap (1.1e-4 and 1.4e-4 relative in float64). Before the fixed
    weight's convergence test took the multipliers' distance to the barrier's, ``|z − w s(t)|``, two instances whose
    floor is 1e-6 and 4e-5 stopped one Newton step early, at 1.2e-3, ``STALLED``."""
    x0 = torch.tensor([r["x0"] for r in REFERENCE], dtype=F32, requires_grad=True)
    with pytest.warns(RuntimeWarning, match="did not converge"):
        sol = tt.solve(double_integrator(), x0, method="eilqr", options=FIXED)
        (grad,) = torch.autograd.grad(sol.cost.sum(), x0)
    converged = sol.status == tt.Status.CONVERGED
    assert bool((converged | (sol.status == tt.Status.STALLED)).all()), sol.status
    assert int(sol.iterations.max()) < 100
    floor = rounded_soft_optimum_stationarity(x0.detach())
    assert bool((sol.kkt["stationarity"] <= 2 * floor + 1e-5).all()), (sol.kkt["stationarity"], floor)
    assert int(converged.sum()) == int((floor < 1e-3).sum()) == 5
    tolerance = 1e-3  # the certificate's float32 stationarity tolerance
    assert bool((sol.kkt["stationarity"][~converged] > tolerance).all())
    cost = torch.tensor([r["cost"] for r in REFERENCE], dtype=torch.float64)[converged]
    expected = torch.tensor([r["grad_x0"] for r in REFERENCE], dtype=torch.float64)[converged]
    assert float(((sol.cost.detach().double()[converged] - cost) / cost).abs().max()) < 2e-4
    relative = (grad.double()[converged] - expected).norm(dim=-1) / expected.norm(dim=-1)
    assert float(relative.max()) < 1e-3, relative


def rounded_soft_optimum_stationarity(x0):
    """The certificate's stationarity ``(B,)`` of the soft problem at its float64 optimum rounded to float32: the
    best a float32 point can do."""
    from torchtraj.core.batch import Batch
    from torchtraj.core.constraints import Constraints
    from torchtraj.kkt.certificate import residuals
    from torchtraj.solvers.eilqr.barrier import soft_problem

    exact = tt.solve(double_integrator(torch.float64), x0.double(), method="eilqr", options=FIXED)
    assert bool((exact.status == tt.Status.CONVERGED).all())
    soft = soft_problem(double_integrator(), FIXED.barrier_weight, FIXED.barrier_relaxation)
    params = Batch.build(soft, x0).params
    return residuals(soft, exact.X.float(), exact.U.float(), {}, params, x0,
                     Constraints.of(soft, ignored=True)).stationarity
