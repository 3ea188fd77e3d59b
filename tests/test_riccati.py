"""The Riccati core against a dense KKT solve and against the discrete algebraic Riccati equation."""

import pytest
import torch

from torchtraj.riccati import LQR, LQRVectors, factorize, solve_lqr


def random_lqr(B, N, nx, nu, m=0, mN=0, dtype=torch.float64, seed=0, deficient=False):
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.randn(*shape, generator=g, dtype=dtype)

    A = torch.eye(nx, dtype=dtype) + 0.3 * rand(B, N, nx, nx)
    Bu = rand(B, N, nx, nu)
    # a strictly convex stage cost [[Q, S'], [S, R]] with cross terms
    W = rand(B, N, nx + nu, nx + nu)
    H = W @ W.transpose(-1, -2) / (nx + nu) + 0.5 * torch.eye(nx + nu, dtype=dtype)
    Q, S, R = H[..., :nx, :nx], H[..., nx:, :nx], H[..., nx:, nx:]
    WN = rand(B, nx, nx)
    QN = WN @ WN.transpose(-1, -2) / nx + 0.5 * torch.eye(nx, dtype=dtype)
    lqr = LQR(A=A, B=Bu, Q=Q, R=R, S=S, QN=QN)
    rhs = LQRVectors(q=rand(B, N, nx), r=rand(B, N, nu), qN=rand(B, nx), c=0.1 * rand(B, N, nx), x0=rand(B, nx))
    if m:
        C, D = rand(B, N, m, nx), rand(B, N, m, nu)
        if deficient:
            # rank-deficient stage blocks: on every other stage the last row involves the state
            # only, so that only the controls of earlier stages can satisfy it
            D[:, 1::2, -1] = 0.0
        mask = torch.rand(B, N, m, generator=g, dtype=dtype) > 0.3
        lqr.C, lqr.D, lqr.mask = C, D, mask.to(dtype)
        rhs.e = rand(B, N, m)
    if mN:
        lqr.CN, lqr.maskN = rand(B, mN, nx), torch.ones(B, mN, dtype=dtype)
        rhs.eN = rand(B, mN)
    return lqr, rhs


def dense_kkt(lqr, rhs, b):
    """Solve instance b by one dense KKT system; variables [x0, u0, x1, u1, ..., xN]."""
    N, nx, nu = lqr.B.shape[1], lqr.A.shape[-1], lqr.B.shape[-1]
    dtype = lqr.A.dtype
    nz = N * (nx + nu) + nx
    xi = lambda k: slice(k * (nx + nu), k * (nx + nu) + nx)  # noqa: E731
    ui = lambda k: slice(k * (nx + nu) + nx, (k + 1) * (nx + nu))  # noqa: E731
    H = torch.zeros(nz, nz, dtype=dtype)
    h = torch.zeros(nz, dtype=dtype)
    rows, rhs_rows, kinds = [], [], []
    row = torch.zeros(nz, dtype=dtype)
    for k in range(N):
        H[xi(k), xi(k)] = lqr.Q[b, k]
        H[ui(k), ui(k)] = lqr.R[b, k]
        H[ui(k), xi(k)] = lqr.S[b, k]
        H[xi(k), ui(k)] = lqr.S[b, k].T
        h[xi(k)], h[ui(k)] = rhs.q[b, k], rhs.r[b, k]
    H[xi(N), xi(N)] = lqr.QN[b]
    h[xi(N)] = rhs.qN[b]
    # initial condition -x0 + xbar = 0, then dynamics A x + B u - x' + c = 0
    for i in range(nx):
        r = row.clone(); r[xi(0).start + i] = -1.0
        rows.append(r); rhs_rows.append(rhs.x0[b, i]); kinds.append(("init", 0, i))
    for k in range(N):
        for i in range(nx):
            r = row.clone()
            r[xi(k)] = lqr.A[b, k, i]; r[ui(k)] = lqr.B[b, k, i]; r[xi(k + 1).start + i] = -1.0
            rows.append(r); rhs_rows.append(rhs.c[b, k, i]); kinds.append(("dyn", k + 1, i))
    if lqr.C is not None:
        for k in range(N):
            for i in range(lqr.C.shape[2]):
                if lqr.mask[b, k, i] > 0:
                    r = row.clone(); r[xi(k)] = lqr.C[b, k, i]; r[ui(k)] = lqr.D[b, k, i]
                    rows.append(r); rhs_rows.append(rhs.e[b, k, i]); kinds.append(("stage", k, i))
    if lqr.CN is not None:
        for i in range(lqr.CN.shape[1]):
            r = row.clone(); r[xi(N)] = lqr.CN[b, i]
            rows.append(r); rhs_rows.append(rhs.eN[b, i]); kinds.append(("term", N, i))
    J = torch.stack(rows)
    e = torch.stack(rhs_rows)
    nc = J.shape[0]
    KKT = torch.zeros(nz + nc, nz + nc, dtype=dtype)
    KKT[:nz, :nz], KKT[:nz, nz:], KKT[nz:, :nz] = H, J.T, J
    sol = torch.linalg.solve(KKT, -torch.cat([h, e]))
    z, y = sol[:nz], sol[nz:]
    X = torch.stack([z[xi(k)] for k in range(N + 1)])
    U = torch.stack([z[ui(k)] for k in range(N)])
    lam = torch.zeros(N + 1, nx, dtype=dtype)
    nu_stage = torch.zeros(N, lqr.C.shape[2] if lqr.C is not None else 0, dtype=dtype)
    nuN = torch.zeros(lqr.CN.shape[1] if lqr.CN is not None else 0, dtype=dtype)
    for (kind, k, i), val in zip(kinds, y):
        if kind in ("init", "dyn"):
            lam[k, i] = val
        elif kind == "stage":
            nu_stage[k, i] = val
        else:
            nuN[i] = val
    return X, U, lam, nu_stage, nuN


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 2e-3)])
def test_unconstrained_matches_dense_kkt(dtype, tol):
    lqr, rhs = random_lqr(B=3, N=12, nx=4, nu=2, dtype=dtype)
    sol = solve_lqr(lqr, rhs, multipliers=True)
    for b in range(3):
        lqr64 = LQR(**{k: (v.double() if v is not None else None) for k, v in vars(lqr).items()})
        rhs64 = LQRVectors(**{k: (v.double() if v is not None else None) for k, v in vars(rhs).items()})
        X, U, lam, _, _ = dense_kkt(lqr64, rhs64, b)
        scale = 1 + X.abs().max()
        assert (sol.dx[b].double() - X).abs().max() / scale < tol
        assert (sol.du[b].double() - U).abs().max() / scale < tol
        assert (sol.costate[b].double() - lam).abs().max() / (1 + lam.abs().max()) < tol


@pytest.mark.parametrize("deficient", [False, True])
def test_equality_constrained_matches_dense_kkt(deficient):
    # m = 2 rows per stage with nu = 3, terminal rows mN = 2: every constraint is satisfiable
    lqr, rhs = random_lqr(B=4, N=10, nx=4, nu=3, m=2, mN=2, seed=1, deficient=deficient)
    sol = solve_lqr(lqr, rhs, multipliers=True)
    for b in range(4):
        X, U, lam, nus, nuN = dense_kkt(lqr, rhs, b)
        assert torch.allclose(sol.dx[b], X, atol=1e-9, rtol=0)
        assert torch.allclose(sol.du[b], U, atol=1e-9, rtol=0)
        assert torch.allclose(sol.costate[b], lam, atol=1e-9 * (1 + lam.abs().max()), rtol=0)
        assert torch.allclose(sol.nu[b], nus, atol=1e-9 * (1 + nus.abs().max()), rtol=0)
        assert torch.allclose(sol.nuN[b], nuN, atol=1e-9 * (1 + nuN.abs().max()), rtol=0)


def test_state_only_constraints_satisfied_by_earlier_controls():
    """nu = 1 and two state rows on a middle stage: they can only be met by earlier controls."""
    lqr, rhs = random_lqr(B=2, N=8, nx=3, nu=1, seed=2)
    m = 2
    C = torch.zeros(2, 8, m, 3, dtype=torch.float64)
    C[:, 5] = torch.randn(2, m, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    lqr.C, lqr.D = C, torch.zeros(2, 8, m, 1, dtype=torch.float64)
    lqr.mask = torch.zeros(2, 8, m, dtype=torch.float64)
    lqr.mask[:, 5] = 1.0
    rhs.e = torch.zeros(2, 8, m, dtype=torch.float64)
    rhs.e[:, 5] = torch.tensor([0.3, -0.2], dtype=torch.float64)
    sol = solve_lqr(lqr, rhs, multipliers=True)
    residual = (C[:, 5] @ sol.dx[:, 5].unsqueeze(-1)).squeeze(-1) + rhs.e[:, 5]
    assert residual.abs().max() < 1e-9
    for b in range(2):
        X, U, lam, nus, _ = dense_kkt(lqr, rhs, b)
        assert torch.allclose(sol.dx[b], X, atol=1e-9, rtol=0)
        assert torch.allclose(sol.nu[b], nus, atol=1e-8 * (1 + nus.abs().max()), rtol=0)


def test_new_right_hand_side_reuses_the_factor():
    lqr, rhs = random_lqr(B=2, N=9, nx=3, nu=2, m=1, mN=1, seed=4)
    factor = factorize(lqr)
    _, rhs2 = random_lqr(B=2, N=9, nx=3, nu=2, m=1, mN=1, seed=5)
    sol = factor.solve(rhs2, multipliers=True)
    for b in range(2):
        X, U, lam, _, _ = dense_kkt(lqr, rhs2, b)
        assert torch.allclose(sol.dx[b], X, atol=1e-9, rtol=0)
        assert torch.allclose(sol.du[b], U, atol=1e-9, rtol=0)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_stationary_gain_matches_scipy_dare(dtype, tol):
    scipy_linalg = pytest.importorskip("scipy.linalg")
    g = torch.Generator().manual_seed(7)
    nx, nu, N = 4, 2, 400
    A = torch.eye(nx, dtype=torch.float64) + 0.1 * torch.randn(nx, nx, generator=g, dtype=torch.float64)
    Bm = torch.randn(nx, nu, generator=g, dtype=torch.float64)
    Q = torch.eye(nx, dtype=torch.float64)
    R = 0.5 * torch.eye(nu, dtype=torch.float64)
    P = torch.as_tensor(scipy_linalg.solve_discrete_are(A.numpy(), Bm.numpy(), Q.numpy(), R.numpy()))
    K_dare = -torch.linalg.solve(R + Bm.T @ P @ Bm, Bm.T @ P @ A)
    rep = lambda M: M.to(dtype).expand(1, N, *M.shape).contiguous()  # noqa: E731
    lqr = LQR(A=rep(A), B=rep(Bm), Q=rep(Q), R=rep(R), S=rep(torch.zeros(nu, nx, dtype=torch.float64)),
              QN=Q.to(dtype).unsqueeze(0))
    factor = factorize(lqr)
    assert (factor.K[0, 0].double() - K_dare).abs().max() < tol * (1 + K_dare.abs().max())
    assert (factor.P[0, 0].double() - P).abs().max() < tol * (1 + P.abs().max())


def test_masked_rows_and_non_finite_instances_are_isolated():
    lqr, rhs = random_lqr(B=3, N=6, nx=3, nu=2, m=1, mN=1, seed=8)
    ref = solve_lqr(lqr, rhs)
    lqr.A = lqr.A.clone()
    lqr.A[1, 2, 0, 0] = float("nan")
    factor = factorize(lqr)
    sol = factor.solve(rhs)
    assert torch.equal(sol.dx[0], ref.dx[0]) and torch.equal(sol.dx[2], ref.dx[2])
    assert not bool(factor.ok[1])


@pytest.mark.parametrize("elementwise", [False, True])
@pytest.mark.parametrize("n", [1, 2, 3, 4, 6])
def test_small_cholesky_matches_lapack_and_flags_indefinite_matrices(n, elementwise, monkeypatch):
    from torchtraj.riccati import linalg as riccati

    if elementwise:  # the formulas torch.compile traces; eager runs LAPACK's
        monkeypatch.setattr(riccati, "_elementwise", lambda n: n <= riccati._SMALL)
    g = torch.Generator().manual_seed(n)
    W = torch.randn(5, n, n, generator=g, dtype=torch.float64)
    H = W @ W.transpose(-1, -2) + 0.1 * torch.eye(n, dtype=torch.float64)
    H[3] = -H[3]  # not positive definite
    L, info = riccati._cholesky(H)
    assert info.tolist() == [0, 0, 0, 1, 0]
    ok = [0, 1, 2, 4]
    assert torch.allclose(L[ok], torch.linalg.cholesky(H[ok]), atol=1e-12)
    assert torch.equal(L[3], torch.eye(n, dtype=torch.float64))
    b = torch.randn(5, n, 3, generator=g, dtype=torch.float64)
    for x in (riccati._cholesky_solve(b, L), riccati._factored_solve(H, L, info, b)):
        assert torch.allclose(x[ok], torch.linalg.solve(H[ok], b[ok]), atol=1e-9)
        assert torch.allclose(x[3], b[3], atol=1e-15)  # the identity stands in for the indefinite matrix


def test_positive_definiteness_flag_with_indefinite_stage_hessians():
    """``ok`` is False exactly where some stage's Q_uu + ρI (independently: R + BᵀP'B) is not positive
    definite; instances that fail keep the gain -Q_ux of the identity factor and do not disturb the others.
    The indefinite stages are the first, the last the backward sweep reaches: the values stay finite."""
    lqr, rhs = random_lqr(B=6, N=7, nx=5, nu=3, seed=9)
    # Q_uu at stage 0 is R_0 + B_0ᵀ P_1 B_0, and P_1 does not depend on R_0: choose it
    eye = torch.eye(3, dtype=torch.float64)
    BPB = lqr.B[:, 0].transpose(-1, -2) @ factorize(lqr).P[:, 1] @ lqr.B[:, 0]
    target = {1: -eye, 3: torch.diag(torch.tensor([1.0, 2.0, -1e-3], dtype=torch.float64)), 4: -0.5 * eye,
              5: -10.0 * eye}
    lqr.R = lqr.R.clone()
    for b, Quu0 in target.items():
        lqr.R[b, 0] = Quu0 - BPB[b]
    rho = torch.tensor([0.0, 0.0, 0.0, 0.0, 0.0, 1e3], dtype=torch.float64)  # instance 5 definite again
    factor = factorize(lqr, rho)
    Quu = lqr.R + lqr.B.transpose(-1, -2) @ factor.P[:, 1:] @ lqr.B
    assert torch.allclose(factor.Quu, Quu, atol=1e-9 * (1 + Quu.abs().max()))
    definite = (torch.linalg.eigvalsh(Quu + rho.reshape(6, 1, 1, 1) * torch.eye(3, dtype=torch.float64)) > 0).all(-1)
    assert definite.all(-1).tolist() == [True, False, True, False, False, True]
    assert factor.ok.tolist() == definite.all(-1).tolist()
    failed = ~definite
    assert torch.equal(factor.K[failed], -factor.Qux[failed])
    ref = factorize(LQR(**{k: (v[[0, 2]] if v is not None else None) for k, v in vars(lqr).items()}), rho[[0, 2]])
    assert torch.allclose(factor.K[[0, 2]], ref.K, atol=1e-12) and torch.allclose(factor.P[[0, 2]], ref.P, atol=1e-12)


def test_stacked_sanitisation_matches_the_blockwise_one():
    from torchtraj.riccati.sanitize import _sanitize, _sanitize_stacked

    lqr, _ = random_lqr(B=4, N=3, nx=3, nu=2, m=1, mN=1, seed=10)
    lqr.mask = lqr.mask > 0  # a boolean mask keeps its dtype
    lqr.A, lqr.S = lqr.A.clone(), lqr.S.clone()
    lqr.A[1, 2, 0, 1] = float("nan")
    lqr.S[2, 0, 1, 0] = -float("inf")
    blockwise, finite = _sanitize(lqr)
    stacked, finite2, W, Hs = _sanitize_stacked(lqr)
    assert finite.tolist() == finite2.tolist() == [True, False, False, True]
    for name, value in vars(blockwise).items():
        if value is not None:
            assert torch.equal(getattr(stacked, name), value), name
    # stored time-major: (N, B, ...)
    assert torch.equal(W, torch.cat([blockwise.A, blockwise.B], -1).transpose(0, 1))
    assert torch.equal(Hs[:, 1:3], torch.eye(5, dtype=torch.float64).expand(3, 2, 5, 5))


def test_all_finite_flags_each_instance_with_a_nan_or_an_infinity():
    from torchtraj.riccati import all_finite

    a = torch.randn(5, 4, 3, dtype=torch.float64).transpose(0, 1)  # a strided batch-first view
    b = torch.full((4, 2), 1e300, dtype=torch.float64)  # large, finite, and their sum too
    a[1, 2, 0] = float("nan")
    b[2, 1] = float("inf")
    a[3, 0, 0] = -float("inf")
    b[3, 0] = float("inf")  # +inf and -inf of one instance in two tensors
    assert all_finite([a, None, b]).tolist() == [True, False, False, False]
    assert all_finite([a[[0]], b.new_zeros(1, 0)]).tolist() == [True]  # a tensor without entries is skipped
    assert all_finite([None, b.new_zeros(4, 0)]) is None


def test_stacked_blocks_and_a_hessian_shift_give_the_blockwise_factorisation():
    import dataclasses

    lqr, rhs = random_lqr(B=3, N=4, nx=3, nu=2, seed=11)
    W = torch.cat([lqr.A, lqr.B], -1)
    H = torch.cat([torch.cat([lqr.Q, lqr.S.transpose(-1, -2)], -1), torch.cat([lqr.S, lqr.R], -1)], -2)
    stacked = LQR.from_blocks(W, H, lqr.QN)
    assert stacked.W is W and torch.equal(stacked.S, lqr.S)
    assert dataclasses.replace(stacked, Q=lqr.Q.clone()).W is None  # a replaced block is no view of H
    shift = torch.tensor([0.0, 0.5, 2.0], dtype=torch.float64)
    d = shift.reshape(3, 1, 1, 1)
    eye = lambda n: torch.eye(n, dtype=torch.float64)  # noqa: E731
    shifted = LQR(A=lqr.A, B=lqr.B, Q=lqr.Q + d * eye(3), R=lqr.R + d * eye(2), S=lqr.S, QN=lqr.QN + d[:, 0] * eye(3))
    ref, got = factorize(shifted), factorize(stacked, shift=shift)
    assert torch.equal(ref.K, got.K) and torch.equal(ref.P, got.P)
    assert torch.equal(got.lqr.Q, shifted.Q) and torch.equal(got.lqr.QN, shifted.QN)
    # unconstrained and unregularised: the costates are the value function's gradients, as the sweep's
    assert got.exact and not factorize(stacked, regularization=shift).exact
    by_value = got.solve(rhs, multipliers=True)
    got.exact = False
    by_sweep = got.solve(rhs, multipliers=True)
    assert torch.allclose(by_value.costate, by_sweep.costate, rtol=0, atol=1e-11)


@pytest.mark.parametrize("regularized", [False, True])
def test_declared_bounds_give_the_solution_of_the_same_rows_back_propagated(regularized):
    """Rows ``±δu_i + e = 0`` declared ``LQR.bounds`` hold their controls without the SVD recursion: the same steps,
    costates and row multipliers as the general rows, with and without ``ρ``, active rows masked per instance."""
    import dataclasses

    B, N, nx, nu = 5, 6, 3, 3
    lqr, rhs = random_lqr(B=B, N=N, nx=nx, nu=nu, seed=12)
    bounds = torch.cat([torch.eye(nu), -torch.eye(nu)]).to(torch.float64)  # upper rows, then lower rows
    g = torch.Generator().manual_seed(13)
    upper = torch.rand(B, N, nu, generator=g) > 0.6
    lower = (torch.rand(B, N, nu, generator=g) > 0.6) & ~upper  # never both on one control
    mask = torch.cat([upper, lower], -1).to(torch.float64)
    rows = LQR(A=lqr.A, B=lqr.B, Q=lqr.Q, R=lqr.R, S=lqr.S, QN=lqr.QN, C=torch.zeros(B, N, 2 * nu, nx,
               dtype=torch.float64), D=bounds.expand(B, N, 2 * nu, nu), mask=mask)
    rhs.e = torch.randn(B, N, 2 * nu, generator=g, dtype=torch.float64)
    rho = torch.full((B,), 0.3, dtype=torch.float64) if regularized else None
    general = factorize(rows, rho).solve(rhs, multipliers=True)
    declared = factorize(dataclasses.replace(rows, bounds=bounds), rho)
    assert declared.stage is None and torch.equal(declared.fixed, (upper | lower).to(torch.float64))
    held = declared.solve(rhs, multipliers=True)
    for name in ("dx", "du", "costate", "nu"):
        assert torch.allclose(getattr(held, name), getattr(general, name), rtol=0, atol=1e-10), name
    assert float(mask.sum()) > 10 and float(held.nu.abs().amax()) > 1e-2
    # both rows of one control active: one row depends on the other, as the back-propagation finds too
    from torchtraj.differentiation.implicit import dependent_rows

    both = mask.clone()
    both[1, 2, 0] = both[1, 2, nu] = 1.0
    twice = dataclasses.replace(rows, mask=both)
    counted = dependent_rows(factorize(dataclasses.replace(twice, bounds=bounds), rho))
    assert counted.tolist() == dependent_rows(factorize(twice, rho)).tolist() == [0, 1, 0, 0, 0]


@pytest.mark.parametrize("nu", [1, 2])
def test_the_traced_sweep_is_the_eager_sweep_with_and_without_held_controls(nu):
    """The sweep traced by torch.compile or autograd (its gains made again from the stack of ``H`` after the loop)
    gives the eager sweep's ``P``, ``K``, ``Q_uu``, ``Q_ux`` and tests exactly."""
    from torchtraj.riccati.sweep import _factorize_stages_traced, factorize_stages

    torch.manual_seed(nu)
    N, B, nx = 6, 3, 2
    W = torch.randn(N, B, nx, nx + nu, dtype=torch.float64)
    A = torch.randn(N, B, nx + nu, nx + nu, dtype=torch.float64)
    Hs = A @ A.transpose(-1, -2) + torch.eye(nx + nu, dtype=torch.float64)
    QN = torch.eye(nx, dtype=torch.float64).expand(B, nx, nx).clone()
    rho = torch.full((B,), 0.1, dtype=torch.float64)
    for held in (None, (torch.rand(B, N, nu) > 0.6).double()):
        eager, traced = factorize_stages(W, Hs, QN, rho, held), _factorize_stages_traced(W, Hs, QN, rho, held)
        for a, b in zip(eager[:4], traced[:4]):
            assert torch.equal(a, b)
        assert torch.equal(eager[5], traced[5])
