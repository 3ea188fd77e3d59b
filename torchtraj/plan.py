"""``python -m torchtraj.plan``: solve many instances of a benchmark problem in chunks, on one or several processes.

::

    python -m torchtraj.plan --problem pendulum --count 4096 --method altro --out plans.pt
    torchrun --nproc-per-node 2 -m torchtraj.plan --problem pendulum --count 4096 --method altro --out plans.pt

The initial states are ``torchtraj.problems.sample_x0(problem, count, seed)`` (or the ``(count, nx)`` tensor in
``--x0 FILE``, read by rank 0). They are cut into chunks of ``--chunk-size`` instances (the chunks depend on the
count and the chunk size only, never on the number of processes); the chunks still to do are dealt round-robin to
the ranks, each rank solves its chunk with :func:`torchtraj.solve`, and rank 0 receives every round's chunks through
:func:`torchtraj.distributed.exchange` (tensor collectives: no shared file system is needed) and writes each one
atomically (a temporary file, then ``os.replace``) to ``OUT.parts/chunk-<start>-<stop>.pt``. Once all chunks are
there, rank 0 merges them in instance order into ``OUT`` (atomically too) and removes ``OUT.parts``. ``OUT`` is a
dict read by ``torch.load``: ``x0``, ``X``, ``U``, ``K``, ``cost``, ``max_violation``, ``status``, ``iterations``,
``costate`` (or ``None``), ``multipliers``, ``penalties`` and ``kkt`` (dicts of per-block tensors), ``summary``
(converged fraction, cost quantiles, solve seconds per instance) and ``settings`` (the command's arguments). The
per-iteration histories are not kept (their lengths differ between chunks).

Resuming: run the same command again after an interruption. The chunks found in ``OUT.parts`` are skipped (a chunk
file exists only once it was written whole); ``OUT.parts/settings.pt`` must match the command's settings, so a
changed command cannot mix its chunks with another's. A failing rank makes every rank stop with the rank and the
reason (:mod:`torchtraj.distributed`); the chunks written before stay for the next run.
"""

from __future__ import annotations

import argparse
import datetime
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Optional

import torch
import torch.distributed as dist

from . import distributed, problems, solvers
from .core.progress import Progress
from .core.solution import Solution
from .core.status import Status
from .solve import default_method, solve

#: Test hook: exit hard (``os._exit``) after this many chunks were written by this run, as a kill would.
EXIT_AFTER_ENV = "_TORCHTRAJ_PLAN_EXIT_AFTER_CHUNKS"
FIELDS = ("X", "U", "K", "cost", "max_violation", "status", "iterations", "costate")
GROUPS = ("multipliers", "penalties", "kkt")
QUANTILES = (0.0, 0.1, 0.5, 0.9, 1.0)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m torchtraj.plan", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--problem", required=True, choices=problems.names(), help="a problem of the problem set")
    p.add_argument("--count", type=int, required=True, help="number of instances")
    p.add_argument("--method", default=None, choices=solvers.names(),
                   help="torchtraj method (default: tt.solve's rule, ipm for a constrained problem, else ilqr)")
    p.add_argument("--out", required=True, help="output file (torch.save dict); chunks go to OUT.parts/")
    p.add_argument("--seed", type=int, default=0, help="seed of torchtraj.problems.sample_x0")
    p.add_argument("--x0", metavar="FILE", help="read the (count, nx) initial states from FILE (torch.load) instead")
    p.add_argument("--chunk-size", type=int, default=64, help="instances per chunk (one solve each)")
    p.add_argument("--horizon", type=int, default=None,
                   help="re-grid the problem to this many intervals over the same final time (problems.at_horizon)")
    p.add_argument("--iterations", type=int, default=None,
                   help="the method options' iteration cap (ALTRO: its outer iterations)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="cuda: each rank on cuda:LOCAL_RANK, process group backend nccl (else gloo)")
    p.add_argument("--timeout", type=float, default=1800.0, help="collective timeout in seconds")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on rank 0's stderr")
    return p


def options_for(method: str, name: str, iterations: Optional[int]):
    """The problem set's options for ``method`` (its ALTRO options for the augmented-Lagrangian methods)."""
    cls = solvers.get(method).options_class
    if cls.__name__ == "ALTROOptions":
        changes = {} if iterations is None else {"iterations_outer": iterations}
        return problems.altro_options(name, **changes)
    fields = set(cls.__dataclass_fields__)
    return cls(**({"iterations": iterations} if iterations is not None and "iterations" in fields else {}))


def chunks(count: int, size: int) -> list:
    """``[(start, stop)]`` of the chunks, in instance order."""
    return [(start, min(start + size, count)) for start in range(0, count, size)]


def chunk_path(parts: Path, start: int, stop: int) -> Path:
    return parts / f"chunk-{start:09d}-{stop:09d}.pt"


def save_atomic(obj, path: Path) -> None:
    """``torch.save`` to a temporary file beside ``path``, then rename: ``path`` is whole or absent, never partial."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _tally(tally: dict, records: list) -> dict:
    """The bar's fields after ``records``: the converged fraction and the largest finite violation so far."""
    for r in records:
        tally["solved"] += r["status"].numel()
        tally["converged"] += int((r["status"] == Status.CONVERGED).sum())
        finite = r["max_violation"][torch.isfinite(r["max_violation"])]
        tally["violation"] = max(tally["violation"], float(finite.max()) if finite.numel() else 0.0)
    return {"converged": tally["converged"] / max(tally["solved"], 1), "violation": tally["violation"]}


def initial_states(args) -> torch.Tensor:
    if args.x0 is None:
        return problems.sample_x0(args.problem, args.count, seed=args.seed)
    x0 = torch.load(args.x0, weights_only=True)
    nx = problems.spec(args.problem).nx
    if not isinstance(x0, torch.Tensor) or tuple(x0.shape) != (args.count, nx):
        raise ValueError(f"--x0 {args.x0}: expected a tensor of shape ({args.count}, {nx}), got "
                         f"{tuple(x0.shape) if isinstance(x0, torch.Tensor) else type(x0).__name__}")
    return x0


def settings_of(args, x0: torch.Tensor) -> dict:
    keys = ("problem", "count", "method", "seed", "chunk_size", "horizon", "iterations")
    return {**{k: getattr(args, k) for k in keys}, "x0": x0.to(torch.float64).cpu()}


def same_settings(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k]
                                        for k in a)


def prepare(out: Path, settings: dict) -> str:
    """Rank 0: ``"done"`` when ``out`` holds this command's result already, else makes ``OUT.parts`` (checking a
    resumed one's settings) and returns ``"run"``."""
    parts = Path(f"{out}.parts")
    if out.exists() and not parts.exists():
        if same_settings(torch.load(out, weights_only=True)["settings"], settings):
            return "done"
        raise ValueError(f"{out} exists and holds another command's result; remove it or choose another --out")
    parts.mkdir(parents=True, exist_ok=True)
    saved = parts / "settings.pt"
    if saved.exists():
        if not same_settings(torch.load(saved, weights_only=True), settings):
            raise ValueError(f"{parts} holds chunks of another command (other problem, count, x0, method or chunk "
                             "size); remove it or run that command to resume it")
    else:
        save_atomic(settings, saved)
    return "run"


def solve_chunk(problem, x0: torch.Tensor, method: str, options, device) -> tuple:
    start = time.perf_counter()
    sol = solve(problem, x0.to(device=device, dtype=problem.dtype), method, options=options)
    return sol, time.perf_counter() - start


def chunk_record(sol, x0: torch.Tensor, seconds: float) -> dict:
    record = {k: (None if getattr(sol, k) is None else getattr(sol, k).cpu()) for k in FIELDS}
    record.update(x0=x0.cpu(), seconds=seconds, **{g: {k: v.cpu() for k, v in getattr(sol, g).items()} for g in GROUPS})
    return record


def split_record(sol, sizes: list, x0s: list, seconds: list) -> list:
    """The gathered round (ranks' chunks concatenated) back into one record per chunk."""
    records, offset = [], 0
    for size, x0, secs in zip(sizes, x0s, seconds):
        part = slice(offset, offset + size)
        offset += size
        piece = Solution(
            **{k: (None if getattr(sol, k) is None else getattr(sol, k)[part]) for k in FIELDS},
            history=sol.history, method=sol.method,
            **{g: {k: v[part] for k, v in getattr(sol, g).items()} for g in GROUPS})
        records.append(chunk_record(piece, x0, secs))
    return records


def merge(parts: Path, todo: list, settings: dict) -> dict:
    """All chunk files, in instance order, as one output dict with its summary."""
    records = [torch.load(chunk_path(parts, a, b), weights_only=True) for a, b in todo]
    out = {k: torch.cat([r[k] for r in records]) for k in ("x0",) + FIELDS if records[0][k] is not None}
    out.setdefault("costate", None)
    for group in GROUPS:
        out[group] = {k: torch.cat([r[group][k] for r in records]) for k in records[0][group]}
    cost = out["cost"][torch.isfinite(out["cost"])]
    q = torch.tensor(QUANTILES, dtype=cost.dtype)
    out["summary"] = {
        "count": int(out["status"].numel()),
        "converged_fraction": float((out["status"] == Status.CONVERGED).double().mean()),
        "status_counts": Status.counts(out["status"]),
        "cost_quantiles": dict(zip(QUANTILES, torch.quantile(cost, q).tolist())) if cost.numel() else {},
        "seconds_per_instance": sum(r["seconds"] for r in records) / max(int(out["status"].numel()), 1),
    }
    out["settings"] = settings
    return out


def run(args) -> int:
    rank, size = distributed.world()
    device = torch.device(f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}" if args.device == "cuda" else "cpu")
    out = Path(args.out)
    parts = Path(f"{out}.parts")
    state = [None, None]  # rank 0 reads the initial states (no file system shared by the ranks is needed)
    if rank == 0:
        try:
            x0 = initial_states(args)
            state = [prepare(out, settings_of(args, x0)), x0]
        except Exception as exc:
            if size == 1:
                raise
            state = [f"{type(exc).__name__}: {exc}", None]  # every rank stops with it, below
    if size > 1:
        dist.broadcast_object_list(state, src=0)
    x0 = state[1]
    settings = None if x0 is None else settings_of(args, x0)
    if state[0] == "done":
        if rank == 0:
            print(f"{out} is complete already")
        return 0
    if state[0] != "run":
        raise RuntimeError(f"rank 0: {state[0]}")
    all_chunks = chunks(args.count, args.chunk_size)
    listing = [[c for c in all_chunks if not chunk_path(parts, *c).exists()] if rank == 0 else None]
    if size > 1:
        dist.broadcast_object_list(listing, src=0)
    todo = listing[0]
    spec = problems.at_horizon(args.problem, args.horizon) if args.horizon else args.problem
    problem = problems.get(spec, device=device)
    options = options_for(args.method, args.problem, args.iterations)
    progress = Progress(len(all_chunks), label="plan", unit="chunks", enabled=rank == 0 and not args.no_progress)
    progress.count = len(all_chunks) - len(todo)  # written by an earlier run
    tally = {"solved": 0, "converged": 0, "violation": 0.0}
    exit_after = int(os.environ.get(EXIT_AFTER_ENV, "0"))
    written = 0
    for first in range(0, len(todo), size):
        round_chunks = todo[first: first + size]
        mine = round_chunks[rank] if rank < len(round_chunks) else None
        local, error, seconds = None, None, 0.0
        if mine is not None:
            try:
                local, seconds = solve_chunk(problem, x0[mine[0]: mine[1]], args.method, options, device)
            except Exception as exc:  # every rank raises together in exchange
                error = f"{type(exc).__name__}: {exc} (chunk {mine[0]}..{mine[1]})"
        timing = [seconds] * size
        if size > 1:
            dist.all_gather_object(timing, seconds)
        sol, sizes = distributed.exchange(local, error, gather=0, device=device)
        if rank == 0:
            x0s = [x0[a:b] for a, b in round_chunks]
            records = split_record(sol, sizes[: len(round_chunks)], x0s, timing[: len(round_chunks)])
            for (a, b), record in zip(round_chunks, records):
                save_atomic(record, chunk_path(parts, a, b))
            progress.update(len(records), **_tally(tally, records))
            written += len(records)
            if exit_after and written >= exit_after:
                os._exit(17)
    outcome = [None]
    if rank == 0:
        try:
            finish(parts, all_chunks, settings, out, args, size)
        except Exception as exc:
            if size == 1:
                raise
            outcome = [f"{type(exc).__name__}: {exc}"]
    if size > 1:  # the other ranks learn how the merge went (and do not wait on it past the timeout)
        dist.broadcast_object_list(outcome, src=0)
    if outcome[0] is not None:
        raise RuntimeError(f"rank 0: {outcome[0]}")
    return 0


def finish(parts: Path, all_chunks: list, settings: dict, out: Path, args, size: int) -> None:
    """Rank 0: merge the chunks into ``out``, remove ``OUT.parts``, print the summary."""
    merged = merge(parts, all_chunks, settings)
    save_atomic(merged, out)
    shutil.rmtree(parts)
    s = merged["summary"]
    quantiles = ", ".join(f"{k:g}: {v:.6g}" for k, v in s["cost_quantiles"].items())
    print(f"{out}: {s['count']} instances of {args.problem} by {args.method} on {size} process(es); converged "
          f"{100 * s['converged_fraction']:.1f}% {s['status_counts']}; cost quantiles {{{quantiles}}}; "
          f"{1e3 * s['seconds_per_instance']:.2f} ms solve time per instance")


def main(argv: Optional[list] = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.method is None:
        args.method = default_method(problems.get(args.problem))
    if args.count < 1 or args.chunk_size < 1:
        p.error(f"--count and --chunk-size must be >= 1, got {args.count}, {args.chunk_size}")
    launched = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
    if launched and not dist.is_initialized():
        backend = "nccl" if args.device == "cuda" else "gloo"
        if args.device == "cuda":
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        dist.init_process_group(backend, timeout=datetime.timedelta(seconds=args.timeout))
    try:
        code = run(args)
        if launched:  # every rank done with its collectives before any tears its group down
            dist.barrier()
        return code
    finally:
        if launched and dist.is_initialized():
            dist.destroy_process_group()


if __name__ == "__main__":
    sys.exit(main())
