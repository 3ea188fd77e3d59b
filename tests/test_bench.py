"""The benchmark CLI: its rows report what tt.solve and the CasADi references really return."""

import importlib.util
import io
import json

import gymnasium as gym
import pytest
import torch

import torchtraj as tt
from torchtraj import problems
from torchtraj.bench import __main__ as bench_main
from torchtraj.bench.__main__ import main

# loose enough that a pendulum instance converges in about 8 iterations (~0.5 s)
LOOSE = ["--cost-tolerance", "1e-3", "--gradient-tolerance", "1e-1", "--iterations", "20", "--warmup-iterations", "2"]
HAS_CASADI = importlib.util.find_spec("casadi") is not None


def run(args):
    out = io.StringIO()
    code = main(args, out=out)
    return code, out.getvalue()


def rows_of(text, problem):
    return [line.split() for line in text.splitlines() if line.startswith(problem + " ")]


def test_torchtraj_row_matches_a_direct_solve(tmp_path):
    path = tmp_path / "rows.json"
    code, text = run(["--problems", "pendulum_unconstrained", "--batch", "2", "--no-reference", "--json", str(path)]
                     + LOOSE)
    assert code == 0, text
    assert "cost_tolerance=0.001, gradient_tolerance=0.1, iterations=20" in text  # the header names the tolerances
    header = next(line for line in text.splitlines() if line.startswith("problem "))
    assert header.split()[-1] == "status"
    (row,) = rows_of(text, "pendulum_unconstrained")
    assert row[1:4] == ["ilqr", "2", "2"]
    data = json.loads(path.read_text())
    (jrow,) = data["rows"]
    assert data["header"]["settings"] == {"cost_tolerance": 1e-3, "gradient_tolerance": 1e-1, "iterations": 20}

    # the same instances solved here: the row must report exactly this solution
    options = tt.ILQROptions(cost_tolerance=1e-3, gradient_tolerance=1e-1, iterations=20)
    sol = tt.solve(problems.get("pendulum_unconstrained"), problems.sample_x0("pendulum_unconstrained", 2, 0),
                   options=options)
    assert jrow["costs"] == pytest.approx(sol.cost.tolist(), rel=1e-12)
    assert jrow["iterations_max"] == int(sol.iterations.max())
    assert jrow["status"] == tt.Status.counts(sol.status)
    line = next(line for line in text.splitlines() if line.startswith("pendulum_unconstrained "))
    assert line.endswith(", ".join(f"{k} {v}" for k, v in jrow["status"].items()))
    assert jrow["ms_per_instance"] == pytest.approx(1e3 * jrow["seconds"] / 2)
    assert "no FATROP result" in text


def test_constrained_problems_are_skipped_with_the_reason():
    code, text = run(["--problems", "pendulum", "--batch", "1", "--no-reference"] + LOOSE)
    assert code == 0
    assert "skipped (ilqr ignores constraints, which these problems have): pendulum" in text
    assert rows_of(text, "pendulum") == []


def test_a_failing_row_is_reported_and_the_run_goes_on(monkeypatch):
    # sample_x0 is undefined for car_escape (no spread), so its B > 1 row fails; let ilqr try it anyway
    monkeypatch.setattr(bench_main, "skip_reason", lambda method, problem: None)
    code, text = run(["--problems", "car_escape", "pendulum_unconstrained", "--batch", "2", "--no-reference"] + LOOSE)
    assert code == 1
    (failed,) = rows_of(text, "car_escape")
    assert failed[:5] == ["car_escape", "ilqr", "2", "ERROR", "ValueError:"]
    (row,) = rows_of(text, "pendulum_unconstrained")
    # the next row ran to the end: both instances have a final status (LOOSE's tolerances stop short of the
    # KKT certificate, hence stalled)
    assert row[-2:] == ["stalled", "2"]


@pytest.mark.skipif(not HAS_CASADI, reason="casadi is not installed")
def test_reference_rows_reproduce_ipopt_and_fatrop(reference, tmp_path):
    path = tmp_path / "rows.json"
    code, text = run(["--problems", "pendulum_unconstrained", "--batch", "1", "--json", str(path)] + LOOSE)
    assert code == 0, text
    methods = [row[1] for row in rows_of(text, "pendulum_unconstrained")]
    assert methods == ["ilqr", "ipopt", "fatrop"]
    rows = {r["method"]: r for r in json.loads(path.read_text())["rows"]}
    for solver in ("ipopt", "fatrop"):
        expected = reference["pendulum_unconstrained"][solver]
        assert rows[solver]["status"] == {"ok": 1}
        assert rows[solver]["costs"][0] == pytest.approx(expected["cost"], rel=1e-8)
        assert rows[solver]["iterations_max"] == expected["iterations"]
    ours, ipopt = rows["ilqr"]["costs"][0], rows["ipopt"]["costs"][0]
    assert rows["ilqr"]["vs_ipopt"] == pytest.approx(abs(ours - ipopt) / abs(ipopt))
    assert "ratio ilqr/FATROP" in text


def test_compile_flag_reaches_the_solver_options():
    from torchtraj.bench import mpc as mpc_bench
    from torchtraj.bench.runs import compiled, with_compile

    altro = with_compile("altro", tt.ALTROOptions(iterations_outer=3))
    assert altro.ilqr.compile and altro.iterations_outer == 3 and compiled("altro", altro)
    assert compiled("ilqr", with_compile("ilqr", tt.ILQROptions())) and not compiled("altro", tt.ALTROOptions())
    assert with_compile("ipm", tt.IPOptions()).compile and not compiled("ipm", None)
    assert mpc_bench.parser().parse_args(["--compile"]).compile
    assert bench_main.parser().parse_args(["--grad", "--compile"]).compile


@pytest.mark.slow  # a minute of Dynamo tracing; the default run keeps the compiled kernels' own tests
def test_compiled_rows_report_the_run_that_compiled_them(tmp_path, dynamo_capture):
    """``--compile``: the untimed run of the batch that compiles the kernels is timed and reported next to the
    timed row and in the throughput line (the kernels captured by Dynamo and run as captured, to keep it short)."""
    path = tmp_path / "rows.json"
    code, text = run(["--problems", "pendulum_unconstrained", "--batch", "2", "--no-reference", "--compile",
                      "--json", str(path)] + LOOSE)
    assert code == 0, text
    (row,) = json.loads(path.read_text())["rows"]
    assert row["compile_seconds"] > 0 and row["seconds"] > 0
    assert f"which compiled the kernels: {row['compile_seconds']:.1f} s" in text
    assert f"the untimed run before, which compiled them, took {row['compile_seconds']:.1f} s" in text
    # an eager row has none
    code, text = run(["--problems", "pendulum_unconstrained", "--batch", "2", "--no-reference", "--json", str(path)]
                     + LOOSE)
    assert json.loads(path.read_text())["rows"][0]["compile_seconds"] is None and "compiled" not in text


def test_record_flag_reaches_the_solver_options_and_its_rows_are_the_eager_ones(tmp_path):
    from torchtraj.bench.runs import with_record

    assert with_record("altro", tt.ALTROOptions()).ilqr.record and with_record("ipm", tt.IPOptions()).record
    assert with_record("al-ilqr", tt.ALTROOptions()).ilqr.record and with_record("eilqr", tt.EILQROptions()).record
    with pytest.raises(SystemExit):  # a method without the option (plain iLQR's expansion is not recorded)
        main(["--method", "ilqr", "--record"], out=io.StringIO())
    rows = []
    for flags in ([], ["--record"]):
        path = tmp_path / f"rows{len(flags)}.json"
        code, text = run(["--method", "ipm", "--problems", "pendulum", "--batch", "1", "--no-reference", "--json",
                          str(path)] + flags)
        assert code == 0, text
        rows.append(json.loads(path.read_text())["rows"][0])
    assert rows[0]["costs"] == rows[1]["costs"] and rows[0]["iterations_max"] == rows[1]["iterations_max"]
    # the recorded row's untimed run of the batch first, which records: reported, and not in the eager row
    assert rows[0]["record_seconds"] is None and rows[1]["record_seconds"] > 0
    assert f"which recorded the kernels: {rows[1]['record_seconds']:.1f} s" in text
    assert f"the untimed runs before, which recorded them, took {rows[1]['record_seconds']:.1f} s" in text


def test_a_recorded_row_warms_up_until_a_run_traces_nothing_new():
    from torchtraj.bench import runs

    for new_traces, expected_runs in (([2, 0, 0], 2), ([1, 1, 1, 1], runs.RECORD_WARM_UPS)):
        count, made = {"traces": 0}, []

        def run():
            count["traces"] += new_traces[len(made)]
            made.append(1)

        assert runs._record_warm_up(run, torch.device("cpu"), lambda: count["traces"]) >= 0
        assert len(made) == expected_runs


def test_mehrotra_rows_of_the_gradient_benchmark():
    """``--grad --method ipm --barrier mehrotra``: the linear_box rows run the IPM's Mehrotra mode and say so, and
    their gradients agree with central differences; the flag is refused where it would not apply."""
    from torchtraj.bench import grad as bench_grad
    from torchtraj.solve import default_method

    parser = bench_main.parser()
    for args in (["--barrier", "mehrotra"], ["--grad", "--method", "altro", "--barrier", "mehrotra"],
                 ["--grad", "--method", "ipm", "--barrier", "mehrotra", "--compile"]):
        with pytest.raises(SystemExit):
            bench_main._check(parser, parser.parse_args(args))
    # without --method, --grad runs what tt.solve picks for its constrained problems (the IPM), which takes the flag
    args = bench_main.parsed(parser, ["--grad", "--barrier", "mehrotra"])
    bench_main._check(parser, args)
    assert args.method == default_method(bench_grad.lq_problem(bench_grad.linear_system(0))) == "ipm"
    assert bench_main.parsed(parser, ["--grad", "--method", "ilqr"]).method == "ilqr"
    lines = []
    rows = bench_grad.run([4], seed=0, method="ipm", say=lambda text="": lines.append(text), with_mpc=False,
                          lq_options=tt.IPOptions(barrier_strategy="mehrotra"))
    ours = next(r for r in rows if r.solver == "torchtraj/ipm+mehrotra")
    assert ours.converged == "4/4" and ours.grad_vs_fd < 1e-6, lines


# ---------------------------------------------------------------------------------------------- --ops
def test_operator_counter_counts_each_call_the_dispatcher_sees():
    from torchtraj.bench.ops import OperatorCounter

    a, b = torch.ones(3, 3), torch.ones(3, 3)
    with OperatorCounter() as ops:
        c = a + b
        torch.mm(c, b)
        torch.matmul(a, b)  # composite: reaches the dispatcher as one aten.mm
        torch.matmul(torch.ones(2, 3, 3), b)  # folded into one mm: view, mm, _unsafe_view (+ ones: aten.ones)
    a * b  # outside the block
    assert ops.by_name == {"aten.add.Tensor": 1, "aten.mm.default": 3, "aten.ones.default": 1,
                           "aten.view.default": 1, "aten._unsafe_view.default": 1}
    assert ops.total == 7


def test_operator_counter_counts_inside_torch_func_transforms():
    from torchtraj.bench.ops import OperatorCounter

    x = torch.randn(5, 3)
    with OperatorCounter() as ops:
        torch.func.vmap(lambda r: r.sin() * 2)(x)
    # one call per batched operator, not one per batch element (which would be 10)
    assert ops.by_name == {"aten.sin.default": 1, "aten.mul.Tensor": 1}
    with OperatorCounter() as ops:
        torch.func.vmap(torch.func.jacrev(lambda r: r.sin().sum()))(x)
    # the forward, and the vector-Jacobian product's cos(r) * v: jacrev's backward is counted too
    assert ops.by_name["aten.sin.default"] == 1 and ops.by_name["aten.cos.default"] == 1
    assert ops.by_name["aten.mul.Tensor"] == 1


def test_slope_is_the_least_squares_fit():
    import numpy as np

    from torchtraj.bench.ops import slope

    horizons = [25, 50, 100, 200]
    assert slope(horizons, [1000 + 300 * n for n in horizons]) == pytest.approx(300)
    noisy = [7000.0, 14500.0, 30800.0, 59000.0]
    assert slope(horizons, noisy) == pytest.approx(np.polyfit(horizons, noisy, 1)[0], rel=1e-12)
    assert slope([50], [7000.0]) is None and slope([50, 50], [1.0, 2.0]) is None


def test_ops_report_counts_the_solves_it_prints(tmp_path):
    from torchtraj.bench.ops import MPC_WARMUP, OperatorCounter, with_horizon

    path = tmp_path / "ops.json"
    code, text = run(["--ops", "--method", "al-ilqr", "--problems", "double_integrator", "--ops-horizons", "5", "10",
                      "--ops-iterations", "2", "--ops-mpc-steps", "2", "--ops-mpc-iterations", "1",
                      "--json", str(path)])
    assert code == 0, text
    data = json.loads(path.read_text())
    (solved,) = data["solves"]
    assert (solved["problem"], solved["method"], solved["horizon"], solved["iteration_cap"]) == (
        "double_integrator", "al-ilqr", 20, None)
    assert solved["calls_per_iteration"] == pytest.approx(solved["calls"] / solved["iterations"])

    # the same solve counted here: the report must give exactly its calls and iterations
    problem = problems.get("double_integrator")
    with OperatorCounter() as ops:
        sol = tt.solve(problem, method="al-ilqr")
    assert (solved["calls"], solved["iterations"]) == (ops.total, int(sol.iterations.max()))
    (row,) = rows_of(text, "double_integrator")
    assert row == ["double_integrator", "al-ilqr", "20", str(solved["iterations"]), str(ops.total),
                   f"{solved['calls_per_iteration']:.0f}", "converged"]
    assert solved["status"] == "converged" and tt.Status(int(sol.status[0])) == tt.Status.CONVERGED

    sweep = data["horizons"]
    assert sweep["problem"] == "double_integrator" and sweep["iterations"] == 2
    five, ten = sweep["rows"]
    assert (five["horizon"], ten["horizon"]) == (5, 10)
    assert all(r["iteration_cap"] == 2 and 1 <= r["iterations"] <= 2 for r in (five, ten))
    assert ten["calls_per_iteration"] > five["calls_per_iteration"]  # the stages cost calls
    expected = (ten["calls_per_iteration"] - five["calls_per_iteration"]) / 5
    assert sweep["slopes"] == {"al-ilqr": pytest.approx(expected)}
    line = next(line for line in text.splitlines() if line.startswith("al-ilqr "))
    assert line.split() == ["al-ilqr", f"{five['calls_per_iteration']:.0f}", f"{ten['calls_per_iteration']:.0f}",
                            f"{expected:.1f}"]
    assert "first 2 iterations" in text
    assert data["header"]["torch"] == torch.__version__

    # past the setup: iterations 3 and 4 alone, a solve capped at 4 less one capped at 2, counted here again
    later = sweep["past_setup"]
    solver = tt.solvers.get("al-ilqr")
    for row, short in zip(later["rows"], (five, ten)):
        problem = with_horizon(problems.get("double_integrator"), row["horizon"])
        with OperatorCounter() as ops:
            sol = tt.solve(problem, method=solver, options=solver.step_options(solver.default_options(), 4))
        assert row["calls"] == ops.total - short["calls"]
        assert row["iterations"] == int(sol.iterations.max()) - short["iterations"] > 0
    first, second = (r["calls_per_iteration"] for r in later["rows"])
    assert later["slopes"] == {"al-ilqr": pytest.approx((second - first) / 5)}
    assert "past the setup on double_integrator: calls per iteration of iterations 3 to 4 together" in text

    # each iteration alone: iteration 3 is the solve capped at 3 less the one capped at 2, iteration 4 the one
    # capped at 4 less that; the cheapest at each horizon and its slope
    from torchtraj.bench.ops import count_solve  # one solve's count, checked against a direct count above

    alone = sweep["each_iteration"]
    cheapest = []
    for rows, short, n in zip(alone["rows"]["al-ilqr"], (five, ten), (5, 10)):
        counts = [(short["calls"], short["iterations"])]
        for cap in (3, 4):
            row = count_solve(with_horizon(problems.get("double_integrator"), n), solver,
                              solver.step_options(solver.default_options(), cap))
            counts.append((row.calls, row.iterations))
        expected = [(b[0] - a[0], b[1] - a[1]) for a, b in zip(counts, counts[1:])]
        assert [(r["calls"], r["iterations"]) for r in rows] == expected
        cheapest.append(min(c for c, its in expected if its == 1))
    assert [r["calls"] for r in alone["cheapest"]] == cheapest
    assert alone["slopes"] == {"al-ilqr": pytest.approx((cheapest[1] - cheapest[0]) / 5)}
    listed = " ".join(str(r["calls"]) if r["iterations"] == 1 else "-" for r in alone["rows"]["al-ilqr"][0])
    assert f"  al-ilqr N=5, iterations 3 to 4: {listed}" in text

    # the MPC row: two control steps of the pendulum controller (one iteration each, --ops-mpc-iterations) after
    # MPC_WARMUP uncounted, counted here again
    (step,) = data["mpc"]
    assert step["iterations"] == data["header"]["mpc_iterations"] == 1 and "method, 1), B = 1" in text
    env = gym.make("torchtraj/Pendulum-v0").unwrapped
    policy = tt.MPC(env.problem(horizon=30), "al-ilqr", 1)
    obs, _ = env.reset(seed=0)
    for _ in range(MPC_WARMUP):
        obs, *_ = env.step(policy(obs))
    with OperatorCounter() as ops:
        for _ in range(2):
            obs, *_ = env.step(policy(obs))
    assert (step["method"], step["steps"], step["calls"], step["error"]) == ("al-ilqr", 2, ops.total, None)
    assert next(line for line in text.splitlines()[::-1] if line.startswith("al-ilqr ")).split() == [
        "al-ilqr", f"{ops.total / 2:.0f}"]


def test_ops_record_counts_the_solves_again_with_recorded_kernels(tmp_path):
    """``--ops --record``: each full solve again with ``record=True``, after an uncounted one that records: the
    same iterations and status with fewer calls."""
    path = tmp_path / "ops.json"
    code, text = run(["--ops", "--record", "--method", "al-ilqr", "--problems", "pendulum_unconstrained",
                      "--ops-horizons", "5", "--ops-iterations", "2", "--ops-mpc-steps", "0", "--json", str(path)])
    assert code == 0, text
    data = json.loads(path.read_text())
    (plain,), (recorded,) = data["solves"], data["recorded"]
    assert (recorded["method"], recorded["iterations"], recorded["status"]) == (
        plain["method"], plain["iterations"], plain["status"])
    assert recorded["calls"] < plain["calls"]
    assert "with recorded kernels" in text


def test_ops_sweep_of_whole_solves(tmp_path):
    """``--ops-iterations 0``: the sweep counts whole solves with the method's default options, as tt.solve runs
    them at that horizon (no setup spread over a few capped iterations)."""
    from torchtraj.bench.ops import OperatorCounter, with_horizon

    path = tmp_path / "ops.json"
    code, text = run(["--ops", "--method", "al-ilqr", "--problems", "double_integrator", "--ops-horizons", "5", "10",
                      "--ops-iterations", "0", "--ops-mpc-steps", "0", "--json", str(path)])
    assert code == 0, text
    assert "over whole solves with the method's default options" in text
    rows = json.loads(path.read_text())["horizons"]["rows"]
    for row, n in zip(rows, (5, 10)):
        problem = with_horizon(problems.get("double_integrator"), n)
        with OperatorCounter() as ops:
            sol = tt.solve(problem, method="al-ilqr")
        assert (row["horizon"], row["iteration_cap"]) == (n, None)
        assert (row["calls"], row["iterations"]) == (ops.total, int(sol.iterations.max()))


def test_ops_skips_like_the_bench_and_defaults_to_every_method(tmp_path, monkeypatch):
    from torchtraj import solvers
    from torchtraj.bench import ops_report

    path = tmp_path / "ops.json"
    code, text = run(["--ops", "--method", "ilqr", "--problems", "double_integrator", "--ops-horizons", "5",
                      "--json", str(path)])
    assert code == 0, text
    assert "skipped (ilqr ignores constraints, which these problems have): ilqr on double_integrator" in text
    data = json.loads(path.read_text())
    assert data["solves"] == [] and data["horizons"]["rows"] == []
    assert data["skipped"] == [{"problem": "double_integrator", "method": "ilqr",
                                "reason": "ilqr ignores constraints, which these problems have"}]

    seen = []
    empty = {"solves": [], "horizons": {"rows": []}}
    monkeypatch.setattr(ops_report, "run", lambda *args, **kwargs: seen.append(args[:4]) or empty)
    assert run(["--ops"])[0] == 0
    assert run(["--ops", "--method", "ilqr", "--ops-horizons", "5", "7", "--ops-iterations", "3"])[0] == 0
    assert seen == [(solvers.names(), ["pendulum", "cartpole", "car_3obs"], [25, 50, 100, 200], 5),
                    (["ilqr"], ["pendulum", "cartpole", "car_3obs"], [5, 7], 3)]
    parser = bench_main.parser()
    for args in (["--ops", "--grad"], ["--ops", "--ops-horizons", "0"], ["--ops", "--ops-iterations", "-1"],
                 ["--ops", "--ops-mpc-steps", "-1"], ["--ops", "--ops-mpc-iterations", "0"]):
        with pytest.raises(SystemExit):
            bench_main._check(parser, parser.parse_args(args))


def test_a_repeated_row_reports_the_median_of_its_timed_solves(monkeypatch):
    """``--repeat K``: torchtraj's row is the median of K timed solves of the batch (after the warm-up), a
    reference's row each instance's median of K solves; a clock that the solves advance by set amounts stands in
    for the real one."""
    from torchtraj.bench import runs
    from torchtraj.bench.reference import ReferenceResult

    now, durations, calls = [0.0], iter([9.0, 3.0, 1.0, 2.0]), []  # the warm-up, then three timed solves
    solve = runs.solve

    def timed_solve(*args, **kwargs):
        calls.append(kwargs["options"])
        now[0] += next(durations)
        return solve(*args, **kwargs)

    monkeypatch.setattr(runs, "solve", timed_solve)
    monkeypatch.setattr(runs.time, "perf_counter", lambda: now[0])
    options = tt.ILQROptions(cost_tolerance=1e-3, gradient_tolerance=1e-1, iterations=20)
    row = runs.run_torchtraj(problems.get("pendulum_unconstrained"), "ilqr", 2, 0, options, 2, repeat=3)
    assert row.error is None, row.error
    assert len(calls) == 4 and calls[0].iterations == 2 and all(c is options for c in calls[1:])
    assert (row.seconds, row.ms_per_instance, row.repeat) == (2.0, 1e3, 3)

    class Scripted:  # two instances, three solves each, taking these seconds
        solver_name, seconds = "fatrop", iter([5.0, 1.0, 3.0, 2.0, 8.0, 4.0])

        def solve(self, x0):
            return ReferenceResult(ok=True, cost=1.0, iterations=3, max_violation=0.0, seconds=next(self.seconds),
                                   X=None, U=None, status="Solve_Succeeded")

    reference = runs.run_reference(Scripted(), "pendulum", 2, 0, 16, repeat=3)
    assert reference.error is None, reference.error
    assert (reference.instances, reference.seconds, reference.ms_per_instance) == (2, 7.0, 3.5e3)
    with pytest.raises(SystemExit):
        run(["--repeat", "0", "--problems", "pendulum_unconstrained", "--no-reference"])
