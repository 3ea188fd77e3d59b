"""The CasADi references reproduce the problem set's IPOPT / FATROP optima (tests/data)."""

import numpy as np
import pytest

from torchtraj import problems

pytest.importorskip("casadi")
from torchtraj.bench.reference import ReferenceSolver  # noqa: E402


def check(result, expected, name):
    assert result.ok, result.status
    assert result.cost == pytest.approx(expected["cost"], rel=1e-6)
    assert result.max_violation <= max(10 * expected["max_violation"], 1e-10)
    s = problems.spec(name)
    assert result.X.shape == (s.N + 1, s.nx) and result.U.shape == (s.N, s.nu)
    np.testing.assert_allclose(result.X[0], s.x0, rtol=0, atol=1e-9)


@pytest.mark.parametrize("solver", ["ipopt", "fatrop"])
@pytest.mark.parametrize("name", ["double_integrator", "pendulum"])
def test_reproduces_reference(reference, name, solver):
    result = ReferenceSolver(name, solver).solve()
    check(result, reference[name][solver], name)
    if solver == "ipopt":
        np.testing.assert_allclose(result.U, reference[name]["ipopt"]["U"], rtol=0, atol=1e-6)


def test_resolve_with_new_x0(reference):
    """One solver, re-solved per instance (x0 is an NLP parameter): the first pendulum batch instances.

    The batch reference started from the states held at x0 (not the rollout of the problem set's rule),
    and reproduces its iteration counts with that guess."""
    batch = reference["pendulum_batch_seed0_ipopt"]
    solver = ReferenceSolver("pendulum", "ipopt")
    for i, x0 in enumerate(problems.sample_x0("pendulum", 6, seed=0).numpy()):
        result = solver.solve(x0, X0=np.tile(x0, (51, 1)))
        assert result.ok
        np.testing.assert_allclose(result.X[0], x0, rtol=0, atol=1e-9)
        assert result.cost == pytest.approx(batch["costs"][i], rel=1e-6)


def test_rejects_bad_arguments():
    with pytest.raises(ValueError, match="solver"):
        ReferenceSolver("pendulum", "snopt")
    solver = ReferenceSolver("pendulum")
    with pytest.raises(ValueError, match="x0"):
        solver.solve(x0=np.zeros(3))
    with pytest.raises(ValueError, match="U0"):
        solver.solve(U0=np.zeros((49, 1)))


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["ipopt", "fatrop"])
@pytest.mark.parametrize("name", problems.names())
def test_reproduces_reference_everywhere(reference, name, solver):
    result = ReferenceSolver(name, solver).solve()
    check(result, reference[name][solver], name)
    assert result.iterations == reference[name][solver]["iterations"]


@pytest.mark.slow
def test_pendulum_batch(reference):
    batch = reference["pendulum_batch_seed0_ipopt"]
    solver = ReferenceSolver("pendulum", "ipopt")
    x0s = problems.sample_x0("pendulum", len(batch["costs"]), seed=0).numpy()
    results = [solver.solve(x0, X0=np.tile(x0, (51, 1))) for x0 in x0s]
    np.testing.assert_allclose([r.cost for r in results], batch["costs"], rtol=1e-6)
    assert [r.iterations for r in results] == batch["iterations"]
