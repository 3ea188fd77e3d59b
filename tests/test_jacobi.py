"""Pseudo-inverses by one-sided Jacobi rotations (``torchtraj/riccati/jacobi.py``), which the range-space method
uses on a GPU: against LAPACK's, and the range-space factorisation and an interior-point solve with them forced on
the CPU against the same with LAPACK's."""

import pytest
import test_riccati_range_space as range_space_tests
import torch

import torchtraj as tt
from torchtraj import problems
from torchtraj.riccati import jacobi, range_space

F64 = torch.float64


def relative(a, b):
    return float(((a - b).flatten(1).norm(dim=1) / b.flatten(1).norm(dim=1).clamp_min(1e-300)).max())


@pytest.mark.parametrize("shape", [(200, 1, 1), (200, 2, 2), (200, 3, 3), (200, 5, 5), (100, 2, 4), (100, 4, 2),
                                   (100, 1, 3), (100, 3, 1)])
def test_pinv_is_lapacks_for_full_rank_rank_deficient_and_graded_matrices(shape):
    g = torch.Generator().manual_seed(sum(shape))
    full = torch.randn(*shape, dtype=F64, generator=g)
    k = max(1, min(shape[1:]) - 1)
    deficient = torch.randn(shape[0], shape[1], k, dtype=F64, generator=g) @ torch.randn(shape[0], k, shape[2],
                                                                                          dtype=F64, generator=g)
    S = torch.randn(shape[0], shape[1], shape[1], dtype=F64, generator=g)
    graded = S @ S.mT * torch.logspace(0, -6, shape[1], dtype=F64)  # singular values down to about 1e-6
    graded = 0.5 * (graded + graded.mT)
    for A, tol in ((full, 1e-11), (deficient, 1e-12), (graded, 1e-9)):
        assert relative(jacobi.pinv(A, 1e-9), torch.linalg.pinv(A, rtol=1e-9)) < tol


def test_pinv_drops_singular_values_below_the_relative_tolerance_and_inverts_zero_to_zero():
    A = torch.diag_embed(torch.tensor([[1.0, 1e-10], [1.0, 1e-8], [2.0, 0.0]], dtype=F64))
    expected = torch.diag_embed(torch.tensor([[1.0, 0.0], [1.0, 1e8], [0.5, 0.0]], dtype=F64))
    torch.testing.assert_close(jacobi.pinv(A, 1e-9), expected, rtol=1e-12, atol=0)
    assert torch.equal(jacobi.pinv(torch.zeros(2, 3, 3, dtype=F64), 1e-9), torch.zeros(2, 3, 3, dtype=F64))


@pytest.mark.parametrize("sweep", ["sequential", "parallel"])
def test_range_space_by_rotations_matches_the_dense_kkt_solve_and_the_back_propagation(monkeypatch, sweep):
    monkeypatch.setattr(range_space, "by_rotations", lambda M: True)
    range_space_tests.test_range_space_matches_dense_kkt(sweep, 2, 4)
    range_space_tests.test_range_space_gains_and_masked_dependent_rows_match_the_back_propagation(sweep)


def test_an_interior_point_solve_by_rotations_is_the_solve_by_lapack(monkeypatch):
    """The pendulum's goal rows by the range-space method: the same statuses, iterations and trajectories to
    rounding."""
    problem = problems.get("pendulum")
    x0 = problems.sample_x0("pendulum", 4, seed=0)
    used = []
    lapack = tt.solve(problem, x0, "ipm")
    monkeypatch.setattr(range_space, "by_rotations", lambda M: used.append(M.shape) or True)
    rotations = tt.solve(problem, x0, "ipm")
    assert used and bool(lapack.converged.all())
    assert rotations.status.tolist() == lapack.status.tolist()
    assert rotations.iterations.tolist() == lapack.iterations.tolist()
    torch.testing.assert_close(rotations.X, lapack.X, rtol=0, atol=1e-9)
    torch.testing.assert_close(rotations.U, lapack.U, rtol=0, atol=1e-9)
