"""``python -m torchtraj.bench --ops --compile``: the profiler's count of library calls and compiled-function calls,
and the report's rows (torchtraj.bench.compiled_ops)."""

import io
import json

import pytest
import torch

import torchtraj as tt
from torchtraj import problems, solvers
from torchtraj.bench import compiled_ops
from torchtraj.bench.__main__ import main
from torchtraj.bench.compiled_ops import LibraryCalls
from torchtraj.bench.ops import OperatorCounter, with_horizon
from torchtraj.bench.runs import compiled, state_guess, with_compile
from torchtraj.core.recorded import forget


def run(args):
    out = io.StringIO()
    code = main(args, out=out)
    return code, out.getvalue()


def test_library_calls_count_the_calls_made_outside_other_calls():
    a, b = torch.ones(3, 3), torch.ones(3, 3)
    with LibraryCalls() as library:
        c = a + b
        torch.mm(c, b)
        torch.matmul(a, b)  # composite: one call here, its mm inside it
        torch.matmul(torch.ones(2, 3, 3), b)  # ones, and matmul (its view, mm, _unsafe_view inside it)
    a * b  # outside the block
    assert (library.calls, library.kernels) == (5, 0)


def test_the_count_from_raw_events_is_the_profilers_event_trees(dynamo_capture):
    """``count_events`` reads the profiler's raw intervals; the ATen calls with no ATen ancestor in the profiler's
    own event tree (``profile.events()``, seconds to build a solve's) and its compiled-region events are the same
    numbers, for an eager solve and for calls of a compiled function among eager ones."""
    from torch.profiler import ProfilerActivity, profile

    def by_tree(prof):
        calls = kernels = 0
        for event in prof.events():
            if event.name.startswith(compiled_ops.KERNEL_EVENT):
                kernels += 1
            elif event.name.startswith("aten::"):
                parent = event.cpu_parent
                while parent is not None and not parent.name.startswith("aten::"):
                    parent = parent.cpu_parent
                calls += parent is None
        return calls, kernels

    compiled = torch.compile(lambda x: (x.sin() * 2).sum())  # Dynamo's capture alone (the fixture)
    x = torch.randn(4)
    compiled(x)  # captured before the count
    problem = with_horizon(problems.get("double_integrator"), 6)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        tt.solve(problem, method="eilqr", options=tt.EILQROptions(iterations=3))
        for _ in range(3):
            compiled(x) + 1
    calls, kernels = compiled_ops.count_events(prof.profiler.kineto_results.events())
    assert (calls, kernels) == by_tree(prof)
    assert calls > 100 and kernels == 3


def test_library_calls_count_each_call_of_a_compiled_function(dynamo_capture):
    def f(x):
        return (x.sin() * 2).sum()

    compiled = torch.compile(f)  # Dynamo's capture alone (the fixture): no C++ compiler needed
    x = torch.randn(4)
    compiled(x)  # captured here, outside the count
    with LibraryCalls() as library:
        for _ in range(3):
            compiled(x)
    # the eager backend runs the captured operators as library calls: sin, mul and sum, three times
    assert library.kernels == 3 and library.calls == 9


def test_ops_compile_rows_count_the_solves_they_report(tmp_path, monkeypatch):
    """The row's eager counts are those of the same solve counted here; with the compile option left off (so that
    the default run compiles nothing) the 'compiled' solve is that eager solve again, and counts the same."""
    monkeypatch.setattr(compiled_ops, "with_compile", lambda solver, options: options)
    path = tmp_path / "compiled.json"
    code, text = run(["--ops", "--compile", "--method", "al-ilqr", "--problems", "double_integrator", "cartpole",
                      "--json", str(path)])
    assert code == 0, text
    report = json.loads(path.read_text())
    assert report["problem"] == "double_integrator"  # the first problem only
    (row,) = report["rows"]
    assert (row["problem"], row["method"], row["error"]) == ("double_integrator", "al-ilqr", None)

    problem = problems.get("double_integrator")
    forget()
    with OperatorCounter() as mode:
        sol = tt.solve(problem, method="al-ilqr")
    forget()
    with LibraryCalls() as library:
        tt.solve(problem, method="al-ilqr")
    iterations = int(sol.iterations.max())
    assert row["iterations"] == row["compiled_iterations"] == iterations
    assert row["eager_mode_calls"] == pytest.approx(mode.total / iterations)
    assert row["eager_calls"] == pytest.approx(library.calls / iterations)
    assert row["compiled_calls"] == pytest.approx(row["eager_calls"]) and row["kernels"] == 0
    assert row["eager_calls"] < row["eager_mode_calls"]  # composites count once here
    assert row["compile_seconds"] > 0 and row["eager_seconds"] > 0 and row["compiled_seconds"] > 0
    assert row["status"] == "converged"
    (line,) = [line.split() for line in text.splitlines() if line.startswith("al-ilqr ")]
    assert line == ["al-ilqr", str(iterations), f"{row['eager_mode_calls']:.0f}", f"{row['eager_calls']:.0f}",
                    f"{row['compiled_calls']:.0f}", "0.0", f"{row['compile_seconds']:.1f}",
                    f"{row['eager_seconds']:.3f}", f"{row['compiled_seconds']:.3f}", "converged"]


def test_ops_compile_sweeps_the_horizons_given_and_fits_the_calls_per_stage(tmp_path, monkeypatch):
    """With ``--ops-horizons`` the compiled count runs at each horizon (with the compile option left off, as above,
    so that nothing compiles), counts the iterations past the first ``--ops-iterations`` (the solve capped at 2k
    less the one capped at k) and its table gives their least-squares slope over N."""
    monkeypatch.setattr(compiled_ops, "with_compile", lambda solver, options: options)
    path = tmp_path / "sweep.json"
    code, text = run(["--ops", "--compile", "--method", "eilqr", "--problems", "double_integrator",
                      "--ops-horizons", "4", "8", "--ops-iterations", "1", "--json", str(path)])
    assert code == 0, text
    rows = json.loads(path.read_text())["rows"]
    assert [r["horizon"] for r in rows] == [4, 8] and all(r["error"] is None for r in rows)
    assert all(r["eager_calls"] is None for r in rows)  # the eager solves are not profiled in a sweep
    solver = solvers.get("eilqr")
    problem = with_horizon(problems.get("double_integrator"), 8)
    tt.solve(problem, None, solver, X0=state_guess(solver, problem))  # the problem's caches made, as in the bench
    counts = []
    for cap in (1, 2):  # the second iteration's calls at N = 8, counted here
        forget()
        with LibraryCalls() as library:
            tt.solve(problem, None, solver, X0=state_guess(solver, problem),
                     options=solver.step_options(solver.default_options(), cap))
        counts.append(library.calls)
    assert rows[1]["past_setup_calls"] == counts[1] - counts[0]
    calls = torch.tensor([r["past_setup_calls"] for r in rows], dtype=torch.float64)
    fitted = float(calls[1] - calls[0]) / 4
    assert fitted > 1  # eager, as run here, the calls grow with the stages
    (line,) = [line.split() for line in text.splitlines() if line.startswith("eilqr ") and "/" in line]
    assert line[1:3] == [f"{c:.0f}" for c in calls.tolist()] and line[3] == f"{fitted:.1f}"
    assert "N = 4:" in text and "calls/stage" in text


def test_ops_compile_skips_what_a_method_cannot_solve_and_checks_its_flags(monkeypatch):
    code, text = run(["--ops", "--compile", "--method", "ilqr", "--problems", "double_integrator"])
    assert code == 0 and "ilqr     skipped (" in text, text
    assert [m for m in solvers.names() if not solvers.get(m).compiles] == []  # every shipped method compiles
    # a method whose compile option runs eager (HM-iLQR standing for a registered one): no compiled row to report
    monkeypatch.setattr(type(solvers.get("hm-ilqr")), "compiles", False)
    code, text = run(["--ops", "--compile", "--method", "hm-ilqr", "--problems", "double_integrator"])
    assert code == 0 and f"skipped ({compiled_ops.NO_KERNELS})" in text, text
    assert not compiled("hm-ilqr", with_compile("hm-ilqr", solvers.get("hm-ilqr").default_options()))
    with pytest.raises(SystemExit):
        run(["--ops", "--compile", "--record"])
    with pytest.raises(SystemExit):  # a timing row would be the eager one, called compiled
        run(["--compile", "--method", "hm-ilqr", "--problems", "double_integrator"])


@pytest.mark.slow  # Dynamo's capture of the IPM's kernels: half a minute
def test_ops_compile_counts_the_kernels_of_a_compiled_solve(tmp_path, dynamo_capture):
    path = tmp_path / "compiled.json"
    code, text = run(["--ops", "--compile", "--method", "ipm", "--problems", "double_integrator", "--json", str(path)])
    assert code == 0, text
    (row,) = json.loads(path.read_text())["rows"]
    assert row["error"] is None and row["status"] == "converged"
    assert row["kernels"] >= 1  # the iterations run compiled functions
