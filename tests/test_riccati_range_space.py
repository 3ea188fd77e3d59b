"""Terminal rows by the range-space method against a dense KKT solve and against the constraint back-propagation."""

import dataclasses

import pytest
import torch
from test_riccati import dense_kkt, random_lqr

from torchtraj.riccati import factorize
from torchtraj.riccati.range_space import RangeSpaceFactor, feedforward_of


@pytest.mark.parametrize("sweep", ["sequential", "parallel"])
@pytest.mark.parametrize("nu,mN", [(1, 2), (2, 4), (3, 2)])
def test_range_space_matches_dense_kkt(sweep, nu, mN):
    """The step, costates and terminal multipliers of a dense KKT solve, for a single control and for several, and
    rows that fix the whole state (mN = nx)."""
    lqr, rhs = random_lqr(B=3, N=9, nx=4, nu=nu, mN=mN, seed=3)
    factor = factorize(lqr, sweep=sweep, terminal_rows="range-space")
    assert isinstance(factor, RangeSpaceFactor) and bool(factor.ok.all())
    sol = factor.solve(rhs, multipliers=True)
    for b in range(3):
        X, U, lam, _, nuN = dense_kkt(lqr, rhs, b)
        torch.testing.assert_close(sol.dx[b], X, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(sol.du[b], U, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(sol.costate[b], lam, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(sol.nuN[b], nuN, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("sweep", ["sequential", "parallel"])
def test_range_space_gains_and_masked_dependent_rows_match_the_back_propagation(sweep):
    """The feedback gains are the constrained problem's (the back-propagation's), including the last stages, where
    the controls left cannot reach every row; a masked row and a row that repeats another drop out."""
    lqr, rhs = random_lqr(B=4, N=8, nx=3, nu=1, mN=3, seed=5)
    CN = lqr.CN.clone()
    CN[:, 2] = 2.0 * CN[:, 0]  # dependent on row 0
    rhs.eN = rhs.eN.clone()
    rhs.eN[:, 2] = 2.0 * rhs.eN[:, 0]  # consistent
    maskN = torch.ones_like(lqr.maskN)
    maskN[1, 1] = 0.0
    lqr = dataclasses.replace(lqr, CN=CN, maskN=maskN)
    reference = factorize(lqr)
    factor = factorize(lqr, sweep=sweep, terminal_rows="range-space")
    torch.testing.assert_close(factor.K, reference.K, rtol=1e-8, atol=1e-9)
    want, got = reference.solve(rhs, multipliers=True), factor.solve(rhs, multipliers=True)
    for name in ("dx", "du", "costate"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=1e-8, atol=1e-9)
    # the multipliers of dependent rows are not unique: compare their action C_Nᵀ ν
    action = lambda nu: (lqr.CN * lqr.maskN.unsqueeze(-1)).transpose(-1, -2) @ nu.unsqueeze(-1)  # noqa: E731
    torch.testing.assert_close(action(got.nuN), action(want.nuN), rtol=1e-8, atol=1e-9)
    assert float(got.nuN[1, 1].abs()) == 0.0


def test_a_non_finite_instance_leaves_the_others_unchanged():
    lqr, rhs = random_lqr(B=3, N=6, nx=2, nu=1, mN=2, seed=7)
    alone = factorize(dataclasses.replace(lqr, **{f: getattr(lqr, f)[:2] for f in ("A", "B", "Q", "R", "S", "QN",
                                                                                        "CN", "maskN")}),
                      terminal_rows="range-space")
    CN = lqr.CN.clone()
    CN[2, 0, 0] = float("nan")
    factor = factorize(dataclasses.replace(lqr, CN=CN), terminal_rows="range-space")
    assert factor.ok.tolist() == [True, True, False]
    assert torch.equal(factor.K[:2], alone.K)


def test_the_terminal_penalty_keeps_the_inertia_of_the_back_propagation():
    """A terminal Hessian that is negative definite where the rows fix the state: the constrained problem is convex
    (the rows hold every terminal direction), so the back-propagation's inertia test passes, and so does the
    range-space method's, whose unconstrained sweep sees Q_N + ρ C_NᵀC_N."""
    lqr, rhs = random_lqr(B=2, N=6, nx=2, nu=1, mN=2, seed=11)
    lqr = dataclasses.replace(lqr, QN=-50.0 * torch.eye(2, dtype=lqr.QN.dtype).expand(2, 2, 2).clone())
    reference = factorize(lqr)
    factor = factorize(lqr, terminal_rows="range-space")
    assert bool(reference.ok.all()) and bool(factor.ok.all())
    want, got = reference.solve(rhs, multipliers=True), factor.solve(rhs, multipliers=True)
    for name in ("dx", "du", "costate", "nuN"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=1e-8, atol=1e-9)
    unpenalised = factorize(dataclasses.replace(lqr, CN=None, maskN=None))  # what the sweep would see without ρ
    assert not bool(unpenalised.ok.any())


def test_a_matrix_the_eigensolver_fails_on_fails_alone(monkeypatch):
    """LAPACK's eigensolver raises for a whole batch when it does not converge on one matrix: that matrix's instance
    gets a zero inverse and counts as failed, the others get the inverses they get without it (simulated: the
    failure is raised for a marked matrix)."""
    from torchtraj.riccati import range_space

    eigh = torch.linalg.eigh

    def failing(M):
        if bool((M[..., 0, 1] == 0.125).any()):  # the marked matrix (scaled by its largest entry, 4)
            raise torch.linalg.LinAlgError("linalg.eigh: The algorithm failed to converge")
        return eigh(M)

    g = torch.Generator().manual_seed(3)
    A = torch.randn(5, 3, 2, generator=g, dtype=torch.float64)
    M = A @ A.mT  # rank 2 of 3: the eigensolver's path (not the Cholesky's)
    M[2] = torch.tensor([[4.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    expected, _ = range_space._isolated_eigen_inverse(M, 1e-10)
    monkeypatch.setattr(torch.linalg, "eigh", failing)
    inverse, ok = range_space._isolated_eigen_inverse(M, 1e-10)
    assert ok.tolist() == [True, True, False, True, True]
    assert torch.equal(inverse[2], torch.zeros(3, 3, dtype=torch.float64))
    keep = [0, 1, 3, 4]
    torch.testing.assert_close(inverse[keep], expected[keep], rtol=0, atol=0)
    torch.testing.assert_close(expected[keep], torch.linalg.pinv(M[keep], hermitian=True), rtol=1e-9, atol=1e-9)


def test_entries_that_overflow_when_symmetrised_fail_their_instance_alone():
    """A Schur complement of a blown-up instance with finite entries near the largest float: symmetrising it
    overflows to inf (LAPACK's eigensolver then raised for the whole batch, seen on a quadrotor2d batch); that
    instance counts as not finite and the others' pseudo-inverses are unchanged."""
    from torchtraj.riccati import range_space

    g = torch.Generator().manual_seed(4)
    A = torch.randn(3, 4, 2, generator=g, dtype=torch.float64)
    M = A @ A.mT  # rank 2 of 4: the eigensolver's path
    alone, ok = range_space._pseudo_inverse(M, 1e-10)
    blown = M.clone()
    blown[1] = 1.5e308
    blown[1].diagonal().fill_(1.7e308)
    inverse, finite = range_space._pseudo_inverse(blown, 1e-10)
    assert ok.all() and finite.tolist() == [True, False, True]
    torch.testing.assert_close(inverse[[0, 2]], alone[[0, 2]], rtol=0, atol=0)


def test_gains_kept_unformed_are_the_factors_gains_row_by_row():
    """A solver keeps each instance's last gains as their parts (TerminalGains) and forms them once: selected,
    gathered and written row by row, beside gains already formed, they form the gains of the factors they came
    from, bit for bit; and Σ_0's pseudo-inverse alone is the factorisation's first stage's."""
    from torchtraj.riccati import range_space
    from torchtraj.riccati.range_space import TerminalGains, formed, gains_of, select_gains
    from torchtraj.solvers.ipm.compaction import gather_rows, write_rows

    lqr, _ = random_lqr(B=4, N=7, nx=3, nu=2, mN=2, seed=13)
    other, _ = random_lqr(B=4, N=7, nx=3, nu=2, mN=2, seed=14)
    first, second = (factorize(x, terminal_rows="range-space") for x in (lqr, other))
    assert isinstance(gains_of(first), TerminalGains) and torch.equal(gains_of(factorize(lqr)), factorize(lqr).K)
    mask = torch.tensor([True, False, False, True])
    torch.testing.assert_close(formed(select_gains(mask, first.gains, second.gains)),
                               torch.where(mask.reshape(-1, 1, 1, 1), first.K, second.K), rtol=0, atol=0)
    formed_gains = torch.randn_like(first.K)  # formed gains (an initial zero, a cross-over's) beside unformed ones
    for mixed, want in ((select_gains(mask, first.gains, formed_gains), (first.K, formed_gains)),
                        (select_gains(mask, formed_gains, first.gains), (formed_gains, first.K))):
        torch.testing.assert_close(formed(mixed), torch.where(mask.reshape(-1, 1, 1, 1), *want), rtol=0, atol=0)
    rows = torch.tensor([2, 0])
    torch.testing.assert_close(formed(gather_rows(first.gains, rows)), first.K[rows], rtol=0, atol=0)
    written = write_rows(_Holder(first.gains), rows, _Holder(second.gains[rows])).gains
    torch.testing.assert_close(formed(written), first.K.index_copy(0, rows, second.K[rows]), rtol=0, atol=0)
    everything, _ = range_space._pseudo_inverse(first.gains.sums, first.gains.tol)
    torch.testing.assert_close(first.inverse, everything[:, 0], rtol=0, atol=0)


@dataclasses.dataclass
class _Holder:
    gains: object


def test_empty_stage_rows_take_the_range_space_method_and_the_feedforward_goes_with_the_constrained_gains():
    """Stage rows with no row (``C (B, N, 0, nx)``, how HM-iLQR's model carries them beside a goal) are no stage
    rows: the range-space method takes the LQR and solves it as without them. Its ``k`` goes with the unconstrained
    gains; :func:`feedforward_of` is the one of the constrained gains ``K``, the back-propagation's ``k``, so that a
    closed-loop rollout ``δu = k + K δx`` of the linear model retraces the step."""
    lqr, rhs = random_lqr(B=3, N=7, nx=3, nu=2, mN=2, seed=13)
    B, N, nx, nu = 3, 7, 3, 2
    empty = dataclasses.replace(lqr, C=lqr.A.new_zeros(B, N, 0, nx), D=lqr.A.new_zeros(B, N, 0, nu),
                                mask=lqr.A.new_zeros(B, N, 0))
    rhs_empty = dataclasses.replace(rhs, e=lqr.A.new_zeros(B, N, 0))
    factor = factorize(empty, terminal_rows="range-space")
    assert isinstance(factor, RangeSpaceFactor) and bool(factor.ok.all())
    alone = factorize(lqr, terminal_rows="range-space")
    got, want = factor.solve(rhs_empty, multipliers=True), alone.solve(rhs, multipliers=True)
    for name in ("dx", "du", "k", "costate", "nuN"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    reference = factorize(empty)  # the back-propagation
    assert not isinstance(reference, RangeSpaceFactor)
    step = reference.solve(rhs_empty, multipliers=True)
    k = feedforward_of(factor, got)
    torch.testing.assert_close(k, step.k, rtol=1e-8, atol=1e-9)
    assert torch.equal(feedforward_of(reference, step), step.k)
    torch.testing.assert_close(factor.K, reference.K, rtol=1e-8, atol=1e-9)
    assert not torch.allclose(got.k, step.k, rtol=1e-6, atol=1e-6)  # the unconstrained gains' feedforward
    # the closed-loop recursion of the linear model from the step's δx_0 with (k, K) gives the step
    dx = got.dx[:, 0]
    for t in range(N):
        du = k[:, t] + (factor.K[:, t] @ dx.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(du, got.du[:, t], rtol=1e-8, atol=1e-9)
        dx = (lqr.A[:, t] @ dx.unsqueeze(-1) + lqr.B[:, t] @ du.unsqueeze(-1)).squeeze(-1) + rhs.c[:, t]
