"""The CUDA-graph contract checked on the CPU (``torchtraj.core.graphs.emulated``): every graphed kernel of an
interior-point solve runs as if captured, under a dispatch mode that refuses host reads, and the solve is the
eager one. A GPU run found the range-space method's ``eigh`` in the Newton step; these tests would have."""

import contextlib
import warnings

import pytest
import torch
from small_problems import oscillator

import torchtraj as tt
from torchtraj import problems
from torchtraj.core import graphs

F64 = torch.float64


@pytest.mark.parametrize("read", [lambda x: x * float(x.sum()), lambda x: torch.linalg.eigh(x @ x.mT)[0],
                                  lambda x: x[x > 0], lambda x: torch.linalg.cholesky(x @ x.mT + torch.eye(3))],
                         ids=["item", "eigh", "mask", "cholesky-checked"])
def test_an_emulated_capture_refuses_a_host_read_and_runs_the_kernel_eager(read):
    x = torch.randn(3, 3)
    with graphs.emulated(), pytest.warns(RuntimeWarning, match="runs without a CUDA graph"):
        out = graphs.Graphed(read)(x)
    torch.testing.assert_close(out, read(x))


def test_an_emulated_capture_lets_a_kernel_without_host_reads_run():
    x = torch.randn(4, 3, 3, dtype=F64)
    kernel = graphs.Graphed(lambda x: torch.linalg.cholesky_ex(x @ x.mT + torch.eye(3, dtype=F64))[0] * 2.0)
    with graphs.emulated(), warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = kernel(x)
    assert not kernel.eager and out.shape == (4, 3, 3)
    assert not graphs.capturing()


CASES = dict(general=dict(terminal_eq=None), declared=dict(linear_quadratic=True, terminal_eq=None),
             bounds=dict(linear_quadratic=True, state_ineq=None, terminal_eq=None), terminal={})


@pytest.mark.parametrize("case", list(CASES))
def test_graphed_interior_point_kernels_read_nothing_on_the_host(case):
    """The cases of ``tests/test_interior_point.py``'s CUDA-graph test (the oscillator with inequality rows,
    declared linear-quadratic, with bounds alone, with its terminal row): no graphed kernel falls back, and the
    statuses, iterations, solutions and gradients are the eager solve's to rounding."""
    problem = oscillator(**CASES[case])
    x0s = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2]], dtype=F64)
    out = []
    for emulate in (False, True):
        x0 = x0s.clone().requires_grad_(True)
        k = problem.params["k"].clone().requires_grad_(True)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # every kernel "captured": none falls back to eager
            with graphs.emulated() if emulate else contextlib.nullcontext():
                sol = tt.solve(problem.with_params(k=k), x0, method="ipm", options=tt.IPOptions(cuda_graphs=True))
                grads = torch.autograd.grad((sol.U ** 2).sum() + sol.X[:, -5:].sum(), [x0, k])
        assert bool(sol.converged.all()), sol.status
        out.append((sol, grads))
    (eager, g_eager), (emulated, g_emulated) = out
    assert torch.equal(emulated.iterations, eager.iterations)
    torch.testing.assert_close(emulated.X, eager.X, rtol=0, atol=1e-10)
    torch.testing.assert_close(emulated.U, eager.U, rtol=0, atol=1e-10)
    for a, b in zip(g_emulated, g_eager):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-10)


def test_a_graphed_pendulum_solve_reads_nothing_on_the_host():
    """The GPU target's problem: its goal rows take the range-space method, whose pseudo-inverses are Jacobi
    rotations while captured."""
    problem, x0 = problems.get("pendulum"), problems.sample_x0("pendulum", 4, seed=0)
    eager = tt.solve(problem, x0, "ipm", options=tt.IPOptions(cuda_graphs=True))
    with graphs.emulated(), warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        emulated = tt.solve(problem, x0, "ipm", options=tt.IPOptions(cuda_graphs=True))
    assert bool(eager.converged.all()) and torch.equal(emulated.iterations, eager.iterations)
    torch.testing.assert_close(emulated.X, eager.X, rtol=0, atol=1e-10)
