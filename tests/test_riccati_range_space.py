"""Terminal rows by the range-space method against a dense KKT solve and against the constraint back-propagation."""

import dataclasses

import pytest
import torch
from test_riccati import dense_kkt, random_lqr

from torchtraj.riccati import factorize
from torchtraj.riccati.range_space import RangeSpaceFactor


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
