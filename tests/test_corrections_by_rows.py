"""The corrections that only some instances of a batch need run on those instances' rows alone: the IPM's line-search
rounds after the first, eILQR's inertia-correction attempts, line-search rounds and second-order corrections, and
HM-iLQR's CRLS rounds after the first. Each solve is compared, bit for bit, with the same solve made on the whole
batch at every correction, on pendulum starts where some instances need a correction at some iterations and others
do not (the IPM's on double integrator starts, whose line searches need a second round more often); the rows' paths
must have been taken."""

import pytest
from same_solutions import assert_same_solutions

import torchtraj as tt
from torchtraj.globalization import line_search as backtracking

PENDULUM = tt.problems.get("pendulum")
X0 = tt.problems.sample_x0("pendulum", 6, 0)


@pytest.fixture
def rounds_of_rows(monkeypatch):
    """The sizes of the line-search rounds made on rows (``backtrack``'s ``by_rows``)."""
    sizes = []
    of_rows = backtracking._round_of_rows

    def counted(evaluate, alphas, looking, *args):
        sizes.append(looking.numel())
        return of_rows(evaluate, alphas, looking, *args)

    monkeypatch.setattr(backtracking, "_round_of_rows", counted)
    return sizes


def whole_batch_rounds(monkeypatch, module):
    """``module``'s line search with every round on the whole batch."""
    plain = backtracking.backtrack
    monkeypatch.setattr(module, "backtrack", lambda *args, by_rows=False, **kwargs: plain(*args, **kwargs))


def test_ipm_line_search_rounds_on_rows(monkeypatch, rounds_of_rows):
    from torchtraj.solvers.ipm import line_search

    problem, x0 = tt.problems.get("double_integrator"), tt.problems.sample_x0("double_integrator", 8, 0)
    options = tt.IPOptions(compact_below=0.0)
    by_rows = tt.solve(problem, x0, method="ipm", options=options)
    assert rounds_of_rows and max(rounds_of_rows) < x0.shape[0], rounds_of_rows
    whole_batch_rounds(monkeypatch, line_search)
    assert_same_solutions(by_rows, tt.solve(problem, x0, method="ipm", options=options))


def test_eilqr_corrections_on_rows(monkeypatch, rounds_of_rows):
    from torchtraj.solvers.eilqr import globalization, merit, newton

    written = []
    write = newton.write_direction

    def counted(step, rows, new):
        written.append(rows.numel())
        return write(step, rows, new)

    monkeypatch.setattr(newton, "write_direction", counted)
    monkeypatch.setattr(globalization, "write_direction", counted)
    options = tt.EILQROptions(iterations=20)
    by_rows = tt.solve(PENDULUM, X0, method="eilqr", options=options)
    assert written and max(written) < X0.shape[0], written  # inertia corrections and second-order corrections
    assert rounds_of_rows and max(rounds_of_rows) < X0.shape[0], rounds_of_rows
    whole_batch_rounds(monkeypatch, merit)
    attempts = newton.corrected_attempts
    monkeypatch.setattr(newton, "corrected_attempts", lambda *args: attempts(*args[:-1]))  # no write: whole batch
    monkeypatch.setattr(globalization, "_correction_rows", lambda d, initial, need: None)  # the whole batch
    assert_same_solutions(by_rows, tt.solve(PENDULUM, X0, method="eilqr", options=options))


def test_hm_ilqr_crls_rounds_on_rows(monkeypatch):
    from torchtraj.solvers.hm_ilqr import crls

    gathered = []
    pending_rows = crls._pending_rows

    def counted(pending):
        index = pending_rows(pending)
        if index is not None:
            gathered.append(index.numel())
        return index

    monkeypatch.setattr(crls, "_pending_rows", counted)
    options = tt.HMILQROptions(iterations=40)
    by_rows = tt.solve(PENDULUM, X0, method="hm-ilqr", options=options)
    assert gathered and max(gathered) < X0.shape[0], gathered
    monkeypatch.setattr(crls, "_pending_rows", lambda pending: None)
    assert_same_solutions(by_rows, tt.solve(PENDULUM, X0, method="hm-ilqr", options=options))
