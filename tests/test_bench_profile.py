"""The profile split of the benchmarks (``torchtraj.bench.profile``): each method's parts name functions that exist,
none of them calls another, and those that a solve runs take time."""

from pathlib import Path

import pytest

import torchtraj as tt
from torchtraj import solvers
from torchtraj.bench import profile


def test_profile_parts_name_functions_that_exist():
    """Each part of every method's split names a function of the package by its file (the split matches cProfile's
    entries by path and name: a moved file made every share 0 and "other" 100 %)."""
    root = Path(tt.__file__).parent
    for method in solvers.names():
        for compiled in (False, True):
            for label, (file, name) in profile.parts_of(method, compiled).items():
                source = root / file
                assert source.is_file(), (method, label, file)
                assert f"def {name}(" in source.read_text(), (method, label, file, name)


def test_profile_split_attributes_an_mpc_step():
    """The shares of a profiled ALTRO solve: the expansion, the line search and the Riccati sweeps take time."""
    problem = tt.problems.get("pendulum").replace(horizon=10)
    _, shares = profile.split(lambda: tt.solve(problem, method="altro", options=tt.ALTROOptions(
        iterations_outer=1, iterations_inner=3)))
    for label in ("expansion (torch.func derivatives)", "line search (batched rollouts)", "Riccati factorisation",
                  "Riccati solve"):
        assert shares[label] > 0.0, (label, shares)
    assert shares["other"] < 1.0


@pytest.mark.filterwarnings("ignore:method .ilqr. ignores the constraints")
@pytest.mark.parametrize("method", ["ilqr", "ipm", "eilqr", "hm-ilqr"])
def test_every_methods_split_names_its_own_expansion_and_the_riccati_core(method):
    """A method other than ALTRO is split by its own expansion and the shared Riccati core (not by ALTRO's functions,
    which read 0 % for it): each takes time in a short solve, and no part holds another (``other`` stays ≥ 0)."""
    solver = solvers.get(method)
    problem = tt.problems.get("pendulum").replace(horizon=10)
    options = solver.step_options(solver.default_options(), 3)
    _, shares = profile.split(lambda: tt.solve(problem, method=method, options=options), profile.parts_of(method))
    assert set(shares) == {"expansion (torch.func derivatives)", "Riccati factorisation", "Riccati solve", "other",
                           *(("line search (batched rollouts)", "initial rollout") if method == "ilqr" else ())}
    for label in ("expansion (torch.func derivatives)", "Riccati factorisation", "Riccati solve"):
        assert shares[label] > 0.0, (method, label, shares)
    assert shares["other"] >= 0.0
    assert profile.parts_of(method, compiled=True) == {}
    assert profile.parts_of("al-ilqr") == profile.PARTS
    assert set(profile.parts_of("a-new-method")) == {"Riccati factorisation", "Riccati solve"}  # no line: the core
