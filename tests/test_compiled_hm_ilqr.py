"""HM-iLQR's compiled kernels (``HMILQROptions(compile=True)``, torchtraj.core.compiled).

``-m slow``: Dynamo's capture alone (its ``"eager"`` backend): each kernel of a solve (the expansion, the dynamics'
curvature, the backward pass, the solve of a right-hand side, the residual at the start, a round's model, the line
search's batched rollouts and ratio test, the second-order correction's step, the iterate's measures) is one graph
with no break, and the solve is the eager one; and the same solve compiled by inductor, against eager.
"""

import pytest
from same_solutions import (
    assert_close_solutions,
    assert_compiled_matches_eager,
    assert_one_graph_per_kernel,
    needs_compiler,
)

import torchtraj as tt
from torchtraj.kkt import certificate
from torchtraj.solvers.hm_ilqr import crls, solver, trials
from torchtraj.solvers.hm_ilqr.objective import HybridObjective

pytest.importorskip("torch._inductor")


def pendulum():
    return tt.problems.get("pendulum").replace(horizon=30)


@pytest.mark.slow  # the capture of five kernels in their layouts, over a minute on two cores
def test_each_compiled_kernel_of_hm_ilqr_is_one_graph(dynamo_capture):
    x0 = tt.problems.sample_x0("pendulum", 2, seed=2)
    solution = tt.solve(pendulum(), x0, "hm-ilqr", options=tt.HMILQROptions(compile=True))
    assert_one_graph_per_kernel(dynamo_capture, {
        HybridObjective.expand, HybridObjective.dynamics_curvature, crls.factorized, crls._solve_rhs,
        trials.round_model, trials.ratio_test, trials.corrected_step, trials.start_residual, solver._measures,
        certificate._residuals})
    assert bool((solution.status == tt.Status.CONVERGED).all())
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "hm-ilqr"), tol=1e-9, costate_rtol=1e-9)


@pytest.mark.slow  # compiling the kernels takes minutes on two cores
@needs_compiler
def test_compiled_hm_ilqr_matches_eager():
    x0 = tt.problems.sample_x0("pendulum", 2, seed=2)
    assert_compiled_matches_eager(pendulum(), x0, "hm-ilqr", tt.HMILQROptions(), tol=1e-7, costate_rtol=1e-7)
