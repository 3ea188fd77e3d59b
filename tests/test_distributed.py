"""torchtraj.distributed on two local Gloo processes: the gathered solution is bit for bit the one-process solve of the
whole batch (instance order, status, multipliers, penalties, costates, histories), every gather mode returns what
it says, an empty shard is harmless, and a rank whose solve raises makes every rank raise, naming it. Training
through the layer with DistributedDataParallel (``examples/learn_dynamics_ddp.py``) learns the parameters of the
one-process run on the same data.

The reference is :func:`torchtraj.solve` of the whole batch in the test's own process. Bitwise equality is what
the solvers' batch isolation promises: every per-instance operation (batched matrix products, factorisations,
line-search decisions by masks) computes instance i from instance i's data only, with the same kernels whatever B
is. The default test runs ALTRO (three outer iterations) on the double integrator (bounds, terminal equality:
non-zero multipliers, and instances that stop for different reasons); the pendulum batch of 256 is the slow
acceptance run.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import warnings
from pathlib import Path

import pytest
import ranks
import torch

import torchtraj as tt
from torchtraj import distributed
from torchtraj.core.batch import Batch

WORLD = 2
COUNT = 8


#: The default test's ALTRO runs three outer iterations: quick, and its instances stop for different reasons.
QUICK = {"iterations_outer": 3}


def _problem_and_options(name: str, **changes):
    return tt.problems.get(name), tt.problems.altro_options(name, **changes)


def _save(obj, path) -> None:
    torch.save(obj, path)


def _load(path):
    return torch.load(path, weights_only=False)


def _work_gather_modes(rank, world, name, count, out):
    """Each mode of one solve's shards, the end-to-end call, an empty shard, a failing rank; results to files."""
    warnings.simplefilter("ignore")
    problem, options = _problem_and_options(name, **QUICK)
    x0 = tt.problems.sample_x0(name, count, seed=0)
    whole = distributed.solve(problem, x0, "altro", options=options, gather="all")
    _save(whole, out / f"all-{rank}.pt")
    mine = slice(*distributed.shard(count, rank, world).indices(count)[:2])
    _save((mine.start, mine.stop), out / f"shard-range-{rank}.pt")
    # the other modes from the shard the rank solved (the collectives only: no second solve)
    local = _cut_solution(whole, mine)
    _save(distributed.exchange(local, None, gather="none")[0], out / f"none-{rank}.pt")
    _save(distributed.exchange(local, None, gather=1)[0], out / f"to1-{rank}.pt")
    # per-instance parameters are cut with the batch
    _save(distributed.solve(*_per_instance_goals(count), "ilqr"), out / f"goals-{rank}.pt")
    # one instance on two ranks: rank 1's shard is empty
    single = distributed.solve(problem, x0[:1], "ilqr", gather="rank0")
    _save(single, out / f"single-{rank}.pt")
    try:
        distributed.solve(problem, x0[:2], "ilqr" if rank == 0 else "no-such-method")
    except RuntimeError as exc:
        _save(str(exc), out / f"error-{rank}.pt")


def _per_instance_goals(count: int) -> tuple:
    """The double integrator with a goal per instance ``(B, nx)`` and a shared initial state."""
    problem = tt.problems.get("double_integrator")
    goals = problem.params["goal"] + torch.linspace(-1.0, 1.0, count, dtype=torch.float64)[:, None]
    return problem.with_params(goal=goals), None


def _cut_solution(sol, part: slice):
    """The solution's instances ``part`` (a shard as its own rank had it, histories at the whole's length)."""
    h = sol.history
    history = tt.History(*(getattr(h, k)[part] for k in distributed.HISTORY_BASE),
                         extra={k: v[part] for k, v in h.extra.items()})
    return tt.Solution(X=sol.X[part], U=sol.U[part], K=sol.K[part], cost=sol.cost[part],
                       max_violation=sol.max_violation[part], status=sol.status[part],
                       iterations=sol.iterations[part], history=history,
                       costate=None if sol.costate is None else sol.costate[part],
                       multipliers={k: v[part] for k, v in sol.multipliers.items()},
                       penalties={k: v[part] for k, v in sol.penalties.items()}, method=sol.method,
                       kkt={k: v[part] for k, v in sol.kkt.items()})


def _bits(t):
    """The tensor's bit patterns (NaN equals itself, 0.0 differs from -0.0)."""
    return t.view(torch.int64) if t.dtype == torch.float64 else t


def assert_identical(got, want) -> None:
    a, b = distributed._fields(got), distributed._fields(want)
    assert sorted(a) == sorted(b)
    different = [k for k in b
                 if a[k].dtype != b[k].dtype or a[k].shape != b[k].shape or not torch.equal(_bits(a[k]), _bits(b[k]))]
    assert not different, f"fields not bit-identical: {different}"
    assert got.method == want.method


def _reference(name: str, count: int, **changes):
    problem, options = _problem_and_options(name, **changes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return tt.solve(problem, tt.problems.sample_x0(name, count, seed=0), "altro", options=options)


def test_shards_are_balanced_contiguous_and_in_order():
    for count, size in ((8, 2), (7, 3), (1, 2), (256, 5)):
        parts = [distributed.shard(count, r, size) for r in range(size)]
        assert [p.start for p in parts] == [0] + [p.stop for p in parts[:-1]] and parts[-1].stop == count
        lengths = [p.stop - p.start for p in parts]
        assert max(lengths) - min(lengths) <= 1


def _work_everything(rank, world, out):
    _work_gather_modes(rank, world, "double_integrator", COUNT, out)
    _work_ddp(rank, world, DDP_RUN, out)


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory) -> Path:
    """The folder of what two Gloo ranks saved: the solves of :func:`_work_gather_modes`, the training of
    :func:`_work_ddp` (one launch for both: a fresh process's imports and first solve cost more than the runs)."""
    out = tmp_path_factory.mktemp("two_ranks")
    ranks.run(_work_everything, WORLD, out, timeout=300)
    return out


def test_two_ranks_gather_the_one_process_solution_bit_for_bit(two_ranks):
    tmp_path = two_ranks
    want = _reference("double_integrator", COUNT, **QUICK)
    # a meaningful comparison: multipliers that are not all zero, and instances that stopped for different reasons
    assert any(bool((v != 0).any()) for v in want.multipliers.values())
    assert len(set(want.status.tolist())) > 1 and len(set(want.iterations.tolist())) > 1
    for rank in range(WORLD):
        assert_identical(_load(tmp_path / f"all-{rank}.pt"), want)
        start, stop = _load(tmp_path / f"shard-range-{rank}.pt")
        assert_identical(_load(tmp_path / f"none-{rank}.pt"), _cut_solution(want, slice(start, stop)))
    assert _load(tmp_path / "to1-0.pt") is None
    assert_identical(_load(tmp_path / "to1-1.pt"), want)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        single = tt.solve(tt.problems.get("double_integrator"),
                          tt.problems.sample_x0("double_integrator", 1, seed=0), "ilqr")
    assert_identical(_load(tmp_path / "single-0.pt"), single)
    assert _load(tmp_path / "single-1.pt") is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        goals = tt.solve(*_per_instance_goals(COUNT), "ilqr")
    assert len(set(goals.cost.tolist())) == COUNT  # each instance has its own goal
    for rank in range(WORLD):
        assert_identical(_load(tmp_path / f"goals-{rank}.pt"), goals)
    for rank in range(WORLD):
        message = _load(tmp_path / f"error-{rank}.pt")
        assert "rank 1" in message and "no-such-method" in message and "rank 0" not in message


def test_every_solution_field_is_gathered():
    assert {f.name for f in dataclasses.fields(tt.Solution)} == set(distributed.GATHERED)


def test_without_a_process_group_it_is_tt_solve():
    problem = tt.problems.get("double_integrator")
    x0 = tt.problems.sample_x0("double_integrator", 2, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert_identical(distributed.solve(problem, x0, "ilqr"), tt.solve(problem, x0, "ilqr"))
    with pytest.raises(ValueError, match="gather"):
        distributed.solve(problem, x0, "ilqr", gather="some")


def _work_pendulum(rank, world, count, out):
    problem, options = _problem_and_options("pendulum")
    x0 = tt.problems.sample_x0("pendulum", count, seed=0)
    sol = distributed.solve(problem, x0, "altro", options=options, gather="rank0")
    if rank == 0:
        _save(sol, out / "pendulum.pt")


@pytest.mark.slow
def test_256_pendulums_on_two_ranks_equal_one_solve_bit_for_bit(tmp_path):
    count = 256
    ranks.run(_work_pendulum, WORLD, count, tmp_path, timeout=3600)
    assert_identical(_load(tmp_path / "pendulum.pt"), _reference("pendulum", count))


# ------------------------------------------------------------------ training through the layer with DDP
EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "learn_dynamics_ddp.py"
#: Small enough for the default run: two demonstrations per rank, one L-BFGS step of two iterations.
DDP_RUN = {"epochs": 1, "batch": 4, "horizon": 10, "max_iter": 2}


def _example():
    spec = importlib.util.spec_from_file_location("learn_dynamics_ddp", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _work_ddp(rank, world, run, out):
    result = _example().main(**run)
    _save(result, out / f"ddp-{rank}.pt")


def test_ddp_learns_the_parameters_of_the_one_process_run(two_ranks):
    tmp_path = two_ranks
    example = _example()
    one = example.main(**DDP_RUN)
    start = torch.tensor([example.START[k] for k in example.LEARNED], dtype=torch.float64)
    assert (one["theta"] - start).abs().min() > 1e-2 and one["loss"][-1] < 0.5 * one["loss"][0]  # it learnt
    for rank in range(WORLD):
        two = _load(tmp_path / f"ddp-{rank}.pt")
        assert (two["theta"] - one["theta"]).abs().max() < 1e-8, (two["theta"], one["theta"])
        assert two["loss"] == pytest.approx(one["loss"], rel=1e-10)


def test_bench_scale_out_rows_and_speed_up(monkeypatch):
    """``python -m torchtraj.bench --scale-out`` reaches its table (the launches replaced by fixed timings)."""
    import io

    from torchtraj.bench import __main__ as bench
    from torchtraj.bench import scale_out

    def row(args, world):
        return {"wall_s": 8.0 / world, "cpu_s": [6.0 / world] * world, "converged": 1.0, "iterations_max": 7,
                "processes": world, "instances_per_s": args.batch * world / 8.0, "load_before": 0.0,
                "load_after": 0.0, "free_core_instances_per_s": args.batch * world / 6.0}

    monkeypatch.setattr(scale_out, "run_row", row)
    out = io.StringIO()
    assert bench.main(["--scale-out", "--batch", "16", "--processes", "1", "2"], out) == 0
    lines = out.getvalue().splitlines()
    assert "B = 16" in lines[0]
    assert lines[-1].split()[:4] == ["2", "4.00", "4.00", "2.00"]  # processes, wall s, inst/s, speed-up
    # --fatrop K: FATROP's median time per instance first (replaced here by a fixed 10 ms), then each row's wall time
    # per instance as a multiple of it: 8 s / 16 instances = 500 ms, 50 times FATROP's; 25 times on two processes
    seen = []

    def fatrop(args):
        seen.append(args.fatrop)
        return 10.0, "FATROP: 10 ms"

    monkeypatch.setattr(scale_out, "fatrop_time", fatrop)
    out = io.StringIO()
    assert bench.main(["--scale-out", "--batch", "16", "--processes", "1", "2", "--fatrop", "4"], out) == 0
    lines = out.getvalue().splitlines()
    assert seen == [4] and lines[1] == "FATROP: 10 ms" and "x FATROP" in lines[2]
    assert [line.split()[8] for line in lines[-2:]] == ["50.00", "25.00"]
    with pytest.raises(SystemExit):  # FATROP solves the problem set's own horizon
        bench.main(["--scale-out", "--fatrop", "4", "--horizon", "20"], io.StringIO())
    # --compile: the ranks run the method's compiled kernels, and each row gives its warm-up (which compiles them)
    monkeypatch.setattr(scale_out, "run_row", lambda args, world: {**row(args, world), "warmup_s": 30.0 / world})
    out = io.StringIO()
    assert bench.main(["--scale-out", "--batch", "16", "--processes", "1", "2", "--method", "ipm", "--compile"],
                      out) == 0
    lines = out.getvalue().splitlines()
    assert "compiled kernels" in lines[0] and "compile s" in lines[1]
    assert [line.split()[8] for line in lines[-2:]] == ["30.0", "15.0"]
    args = scale_out.parser().parse_args(["--method", "ipm", "--compile"])
    assert scale_out._options(args).compile and not scale_out._options(
        scale_out.parser().parse_args(["--method", "ipm"])).compile


def test_the_solver_takes_a_shard_at_the_start_of_its_own_storage():
    """A rank's shard is a slice of the caller's batch, at a nonzero offset into its storage. The solver takes its
    states and per-instance parameters as copies that start their storage (``Batch.for_solver``): a compiled kernel
    guards on a nonzero storage offset, and the rows a solve gathers (finished instances left behind, a correction's
    rows) start at zero, so that every kernel compiled twice on a rank whose shard did not start the batch (rank 1
    of a compiled B = 1024 record compiled again inside its timed solve). A parameter that every instance shares
    stays a view of stride 0."""
    problem = tt.problems.get("pendulum")
    rows = distributed.shard(8, 1, 2)
    x0 = tt.problems.sample_x0("pendulum", 8, seed=0)[rows]
    masses = torch.linspace(0.5, 1.5, 8, dtype=x0.dtype)[rows]
    assert x0.storage_offset() > 0 and masses.storage_offset() > 0
    batch = Batch.build(problem.replace(params={**problem.params, "mass": masses}), x0).for_solver()
    assert batch.x0.storage_offset() == 0 and torch.equal(batch.x0, x0)
    assert batch.params["mass"].storage_offset() == 0 and torch.equal(batch.params["mass"], masses)
    assert batch.params["length"].stride(0) == 0
