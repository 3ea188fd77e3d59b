"""The parallel-in-time Riccati sweep (``sweep="parallel"``) against the sequential sweep, a dense KKT solve and
its operator count; the option's dispatch, and iLQR with it."""

import dataclasses

import pytest
import torch
from test_riccati import dense_kkt, random_lqr

import torchtraj as tt
from torchtraj.bench.ops import OperatorCounter
from torchtraj.riccati import LQR, LQRVectors, factorization, factorize, solve_lqr
from torchtraj.riccati.parallel import ParallelRiccatiFactor, choose_sweep, factorize_parallel

FIELDS = ("dx", "du", "k", "p", "dV1", "dV2", "costate")


def relative(a, b):
    return float((a - b).abs().max() / (1 + b.abs().max()))


def with_bounds(lqr, rhs, seed):
    """``lqr`` with every control boxed (upper rows, then lower rows), random active rows and held values."""
    B, N, nu = lqr.B.shape[0], lqr.B.shape[1], lqr.B.shape[-1]
    dtype = lqr.A.dtype
    g = torch.Generator().manual_seed(seed)
    upper = torch.rand(B, N, nu, generator=g) > 0.6
    lower = (torch.rand(B, N, nu, generator=g) > 0.6) & ~upper  # never both rows of one control
    bounds = torch.cat([torch.eye(nu), -torch.eye(nu)]).to(dtype)
    held = dataclasses.replace(lqr, C=torch.zeros(B, N, 2 * nu, lqr.A.shape[-1], dtype=dtype),
                               D=bounds.expand(B, N, 2 * nu, nu), mask=torch.cat([upper, lower], -1).to(dtype),
                               bounds=bounds)
    rhs = dataclasses.replace(rhs, e=torch.randn(B, N, 2 * nu, generator=g, dtype=dtype))
    return held, rhs


@pytest.mark.parametrize("N", [1, 2, 7, 64])
def test_parallel_matches_sequential_to_round_off(N):
    """Random well-posed LQRs with cross terms, defects and random x0: step, feedforward, value function,
    expected decrease, costates, gains and ``ok`` as the sequential sweep's."""
    lqr, rhs = random_lqr(B=3, N=N, nx=3, nu=2, seed=N)
    assert rhs.c.abs().min() > 0 and lqr.S.abs().min() > 0
    sequential = factorize(lqr)
    parallel = factorize(lqr, sweep="parallel")
    assert isinstance(parallel, ParallelRiccatiFactor) and parallel.ok.all()
    a, b = sequential.solve(rhs, multipliers=True), parallel.solve(rhs, multipliers=True)
    for name in FIELDS:
        assert relative(getattr(b, name), getattr(a, name)) < 1e-10, name
    for name in ("K", "P", "Quu", "Qux"):
        assert relative(getattr(parallel, name), getattr(sequential, name)) < 1e-10, name


@pytest.mark.parametrize("N", [7, 64])
def test_held_bounds_match_the_sequential_held_bounds_solve(N):
    """Declared bounds with random active rows: the held controls sit at their values, the free ones, the
    costates and the rows' multipliers as the sequential sweep's (which test_riccati checks against the
    back-propagated rows)."""
    lqr, rhs = with_bounds(*random_lqr(B=3, N=N, nx=3, nu=2, seed=20 + N), seed=N)
    sequential, parallel = factorize(lqr), factorize(lqr, sweep="parallel")
    assert torch.equal(parallel.fixed, sequential.fixed) and 0.2 < float(parallel.fixed.mean()) < 0.8
    a, b = sequential.solve(rhs, multipliers=True), parallel.solve(rhs, multipliers=True)
    for name in FIELDS + ("nu",):
        assert relative(getattr(b, name), getattr(a, name)) < 1e-10, name
    assert relative(parallel.K, sequential.K) < 1e-10
    held_values = -(rhs.e * lqr.mask) @ lqr.bounds
    assert torch.allclose(b.du * parallel.fixed, held_values, rtol=0, atol=1e-12)


def test_held_bounds_with_a_proximal_term_match_a_dense_kkt_solve():
    """With ``ρ`` and held controls: the dense KKT solution of the problem with ``R + ρI`` and the active rows as
    equalities (``ρ`` on a held control only shifts its row's multiplier)."""
    lqr, rhs = with_bounds(*random_lqr(B=2, N=6, nx=3, nu=2, seed=30), seed=31)
    rho = torch.tensor([0.4, 1.5], dtype=torch.float64)
    sol = factorize(lqr, rho, sweep="parallel").solve(rhs, multipliers=True)
    shifted = dataclasses.replace(lqr, R=lqr.R + rho.reshape(2, 1, 1, 1) * torch.eye(2, dtype=torch.float64),
                                  bounds=None)
    for b in range(2):
        X, U, lam, _, _ = dense_kkt(shifted, rhs, b)
        assert relative(sol.dx[b], X) < 1e-12 and relative(sol.du[b], U) < 1e-12
        assert relative(sol.costate[b], lam) < 1e-12


def test_a_hessian_shift_gives_the_sequential_factorisation():
    lqr, rhs = random_lqr(B=3, N=9, nx=3, nu=2, seed=32)
    shift = torch.tensor([0.0, 0.2, 3.0], dtype=torch.float64)
    a = factorize(lqr, shift=shift).solve(rhs, multipliers=True)
    b = factorize(lqr, shift=shift, sweep="parallel").solve(rhs, multipliers=True)
    for name in FIELDS:
        assert relative(getattr(b, name), getattr(a, name)) < 1e-10, name


def test_parallel_matches_a_dense_kkt_solve():
    """A tiny instance by one dense KKT solve: step and costates; with ``ρ`` the parallel sweep's step is the
    dense solution of the problem with ``R + ρI`` (its proximal regularisation)."""
    lqr, rhs = random_lqr(B=2, N=5, nx=3, nu=2, seed=3)
    sol = solve_lqr(lqr, rhs, multipliers=True, sweep="parallel")
    rho = torch.tensor([0.0, 0.7], dtype=torch.float64)
    proximal = factorize(lqr, rho, sweep="parallel").solve(rhs, multipliers=True)
    shifted = dataclasses.replace(lqr, R=lqr.R + rho.reshape(2, 1, 1, 1) * torch.eye(2, dtype=torch.float64))
    for b in range(2):
        X, U, lam, _, _ = dense_kkt(lqr, rhs, b)
        assert relative(sol.dx[b], X) < 1e-12 and relative(sol.du[b], U) < 1e-12
        assert relative(sol.costate[b], lam) < 1e-12
        X, U, lam, _, _ = dense_kkt(shifted, rhs, b)
        assert relative(proximal.dx[b], X) < 1e-12 and relative(proximal.du[b], U) < 1e-12
        assert relative(proximal.costate[b], lam) < 1e-12


def test_float32():
    lqr, rhs = random_lqr(B=3, N=64, nx=3, nu=2, seed=5)
    reference = solve_lqr(lqr, rhs, multipliers=True)
    single = lambda v: v.float() if isinstance(v, torch.Tensor) else v  # noqa: E731
    lqr32 = LQR(**{k: single(v) for k, v in vars(lqr).items() if k not in ("W", "H")})
    rhs32 = LQRVectors(**{k: single(v) for k, v in vars(rhs).items()})
    sol = solve_lqr(lqr32, rhs32, multipliers=True, sweep="parallel")
    assert sol.dx.dtype == torch.float32
    for name in ("dx", "du", "p", "costate"):
        assert relative(getattr(sol, name).double(), getattr(reference, name)) < 1e-4, name


def test_a_non_finite_instance_leaves_the_others_unchanged():
    lqr, rhs = random_lqr(B=3, N=9, nx=3, nu=2, seed=6)
    clean = solve_lqr(lqr, rhs, multipliers=True, sweep="parallel")
    A = lqr.A.clone()
    A[1, 4, 0, 1] = float("nan")
    factor = factorize(dataclasses.replace(lqr, A=A), sweep="parallel")
    assert factor.ok.tolist() == [True, False, True]
    sol = factor.solve(rhs, multipliers=True)
    for name in FIELDS:
        assert torch.equal(getattr(sol, name)[0::2], getattr(clean, name)[0::2]), name


def test_indefinite_stage_hessians_are_flagged():
    """Where a stage's Hessian is negative definite both sweeps flag the instance, and only it."""
    lqr, _ = random_lqr(B=3, N=6, nx=3, nu=2, seed=7)
    R = lqr.R.clone()
    R[2, 3] = -5.0 * torch.eye(2, dtype=torch.float64)
    lqr = dataclasses.replace(lqr, R=R)
    assert factorize(lqr).ok.tolist() == factorize(lqr, sweep="parallel").ok.tolist() == [True, True, False]


def test_an_indefinite_stage_cost_that_the_dynamics_make_convex_takes_the_sequential_factor():
    """Instance 1's ``R`` is indefinite at one stage while its reduced ``Q_uu = R + Bᵀ P B`` is positive definite: the
    parallel elements refuse it and the sequential sweep factorises it (the same Newton system), so ``ok`` and the
    solution are the sequential sweep's for every instance; the others keep their parallel factors bit for bit."""
    lqr, rhs = random_lqr(B=3, N=8, nx=3, nu=2, seed=11)
    sequential = factorize(lqr)
    R = lqr.R.clone()
    low_R, low_Quu = (torch.linalg.eigvalsh(a[1, 4]).min() for a in (R, sequential.Quu))
    R[1, 4] -= 0.5 * (low_R + low_Quu) * torch.eye(2, dtype=torch.float64)  # R(1, 4)'s least eigenvalue < 0 < Q_uu's
    R[2, 3] = -5.0 * torch.eye(2, dtype=torch.float64)  # indefinite for both sweeps
    lqr = dataclasses.replace(lqr, R=R)
    assert torch.linalg.eigvalsh(R[1, 4]).min() < 0
    clean = factorize(dataclasses.replace(lqr, R=R.index_copy(0, torch.tensor([1, 2]), sequential.lqr.R[1:])),
                      sweep="parallel")
    sequential = factorize(lqr)
    parallel = factorize(lqr, sweep="parallel")
    assert isinstance(parallel, ParallelRiccatiFactor)
    assert sequential.ok.tolist() == parallel.ok.tolist() == [True, True, False]
    a, b = sequential.solve(rhs, multipliers=True), parallel.solve(rhs, multipliers=True)
    for name in FIELDS:
        assert relative(getattr(b, name)[:2], getattr(a, name)[:2]) < 1e-10, name
    for name in ("K", "P", "Quu", "Qux", "chol"):
        assert torch.equal(getattr(parallel, name)[1], getattr(sequential, name)[1]), name
        assert torch.equal(getattr(parallel, name)[0], getattr(clean, name)[0]), name
    assert torch.equal(b.du[0], clean.solve(rhs, multipliers=True).du[0])


def test_an_inertia_test_failed_on_the_sequential_recursion_is_not_repeated(monkeypatch):
    """Instance 1's negative definite terminal cost makes a ``Q_uu`` indefinite for both sweeps. The scan's value
    functions meet the sequential sweep's one-stage recursion, so its verdict stands without a sequential sweep
    (an interior point's inertia correction meets such systems at every rejected shift); the verdicts are the
    sequential sweep's. A scan whose ``P`` is off the recursion (one stage's scaled) is not settled."""
    lqr, _ = random_lqr(B=3, N=8, nx=3, nu=2, seed=5)
    QN = lqr.QN.clone()
    QN[1] = -50.0 * torch.eye(3, dtype=torch.float64)
    lqr = dataclasses.replace(lqr, QN=QN)
    assert factorize(lqr).ok.tolist() == [True, False, True]
    sweeps = []
    real = factorization.factorize_stages
    monkeypatch.setattr(factorization, "factorize_stages", lambda *args: sweeps.append(1) or real(*args))
    assert factorize(lqr, sweep="parallel").ok.tolist() == [True, False, True] and sweeps == []
    scan = factorize_parallel(lqr)
    one = torch.tensor([1])
    assert scan.settled(one).tolist() == [True]
    P = scan.time_major["P"].clone()
    P[3 * 3 + 1] *= 1.5  # time-major (T·B, nx, nx): stage 3 of instance 1
    off = dataclasses.replace(scan, time_major={**scan.time_major, "P": P})
    assert off.settled(one).tolist() == [False]


def calls(N, sweep):
    lqr, rhs = random_lqr(B=1, N=N, nx=2, nu=1, seed=8)
    with OperatorCounter() as ops:
        factorize(lqr, sweep=sweep).solve(rhs)
    return ops.total


def test_operator_calls_grow_like_log_n():
    """Factorise + solve, B = 1, nx = 2, nu = 1. Measured: 413 calls at N = 64 and 500 at N = 512; the lean
    sequential sweep (:mod:`torchtraj.riccati.sweep`) 854 and 5334, 10 calls a stage, 8 of them the factorisation's.
    The factorisation's scan has ⌈log₂(N+1)⌉ levels of 19 calls, the solve's two scans ⌈log₂ N⌉ levels of 5
    calls each."""
    small, large = calls(64, "parallel"), calls(512, "parallel")
    assert large <= 520
    assert large - small <= 32 * 3  # three levels more (log₂(512/64)) of 19 + 2 × 5 calls
    sequential_small, sequential_large = calls(64, "sequential"), calls(512, "sequential")
    assert sequential_large - sequential_small >= 10 * (512 - 64)  # linear in N
    assert sequential_large > 10 * large


def test_sweep_option():
    lqr, _ = random_lqr(B=2, N=6, nx=3, nu=2, m=1, seed=9)
    with pytest.raises(ValueError, match="back-propagated"):
        factorize(lqr, sweep="parallel")
    with pytest.raises(ValueError, match="sweep must be one of"):
        factorize(lqr, sweep="fast")
    auto = factorize(lqr, sweep="auto")
    assert not isinstance(auto, ParallelRiccatiFactor) and auto.stage is not None
    long, _ = random_lqr(B=1, N=400, nx=2, nu=1, seed=10)
    wide, _ = random_lqr(B=256, N=30, nx=4, nu=2, seed=10)
    assert choose_sweep(long, "auto") == "parallel" and choose_sweep(wide, "auto") == "sequential"
    assert choose_sweep(long, "sequential") == "sequential"


def test_ilqr_with_the_parallel_sweep_gives_the_sequential_solution():
    problem = tt.problems.get("pendulum_unconstrained")
    x0 = torch.as_tensor(tt.problems.sample_x0("pendulum_unconstrained", 2, 0))
    solutions = [tt.solve(problem, x0=x0, method="ilqr", options=tt.ILQROptions(sweep=sweep))
                 for sweep in ("sequential", "parallel")]
    a, b = solutions
    assert (a.status == tt.Status.CONVERGED).all() and torch.equal(a.iterations, b.iterations)
    for name in ("X", "U", "K", "costate", "cost"):
        assert (getattr(a, name) - getattr(b, name)).abs().max() < 1e-8, name


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_the_elementwise_solve_pivots_as_lapack_does(monkeypatch, n):
    """Traced or captured, the scan's small solves are Gaussian elimination with partial pivoting written out
    elementwise: LAPACK's answers to round-off, also where the leading entry is zero and elimination without a row
    exchange would divide by it."""
    from torchtraj.riccati import linalg

    g = torch.Generator().manual_seed(n)
    M = torch.randn(5, n, n, generator=g, dtype=torch.float64)
    M[0, 0, 0] = 0.0  # needs a row exchange (n > 1)
    R = torch.randn(5, n, 3, generator=g, dtype=torch.float64)
    expected = torch.linalg.solve(M, R) if n > 1 else R / M
    monkeypatch.setattr(linalg, "_elementwise", lambda size: True)
    solved = linalg._solve(M, R)
    finite = torch.isfinite(expected).flatten(1).all(-1)
    assert relative(solved[finite], expected[finite]) < 1e-12


def test_the_traced_parallel_sweep_is_the_eager_one_to_round_off():
    """Under ``torch.compile`` (Dynamo's capture alone) the scan's products are broadcast sums and its solves
    elementwise (no library call inside a kernel); the factor and the step are the eager ones to round-off, with and
    without held controls."""
    lqr, rhs = random_lqr(B=3, N=9, nx=3, nu=2, seed=4)
    for lqr_, rhs_ in ((lqr, rhs), with_bounds(lqr, rhs, seed=5)):
        def run(lqr_=lqr_, rhs_=rhs_):
            factor = factorize_parallel(lqr_)
            return factor.P, factor.K, factor.solve(rhs_, multipliers=True).dx

        torch._dynamo.reset()
        traced = torch.compile(run, backend="eager", fullgraph=False)()
        for a, b in zip(traced, run()):
            assert relative(a, b) < 1e-10
    torch._dynamo.reset()
