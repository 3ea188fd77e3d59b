"""``python -m torchtraj.bench --scale-out``: throughput of one batch solved by 1, 2, ... local processes.

For every process count W it spawns W processes joined in a Gloo process group (``torch.multiprocessing``, a free
local TCP port), each with ``--threads`` threads. Every rank first solves one instance untimed (imports, first-call
costs), the ranks meet at a barrier, and then :func:`torchtraj.distributed.solve` solves the batch of
``sample_x0(problem, B, seed)`` with the result gathered on rank 0; the time from the barrier to the gathered solution
is the row's wall time and ``B / wall`` its throughput in instances per second. Each W is a fresh launch, so the rows
do not share warm caches. The header states the CPUs this process may use, each row the load average before and
after it: processes only add throughput where cores are free. So each row also gives the largest CPU time a rank
spent in the timed solve (``time.process_time``) and ``B`` divided by it: the throughput the same launch would reach
with a free core for every rank, which load from other work does not change much. With ``--fatrop K``, FATROP
(CasADi, built once, as the throughput rows of ``python -m torchtraj.bench`` run it) first solves the first K of the
same instances one at a time in this process, and each row gives its wall time per instance as a multiple of FATROP's
median (below 1: faster than FATROP). With ``--compile`` the method runs its compiled kernels
(:mod:`torchtraj.core.compiled`), which specialise to a rank's share of the batch: every rank's untimed first solve
is then its share of the whole batch, which compiles them (or loads them from Inductor's cache on disk), and each row
gives that warm-up's wall time.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import socket
import sys
import tempfile
import time
from typing import Optional, TextIO

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from .. import distributed, problems, solvers
from ..core.status import Status
from ..solve import solve
from .runs import make_options, run_reference, with_compile


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m torchtraj.bench --scale-out", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--problem", default="pendulum", choices=problems.names())
    p.add_argument("--method", default="ilqr", choices=solvers.names())
    p.add_argument("--batch", type=int, default=256, help="instances in the batch")
    p.add_argument("--processes", nargs="+", type=int, default=[1, 2], metavar="W", help="process counts")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process")
    p.add_argument("--seed", type=int, default=0, help="seed of sample_x0")
    p.add_argument("--horizon", type=int, default=None, help="re-grid the problem to N intervals (at_horizon)")
    p.add_argument("--timeout", type=float, default=3600.0, help="collective timeout of each launch, seconds")
    p.add_argument("--compile", action="store_true",
                   help="run the method's compiled kernels (torch.compile); the untimed warm-up solves the whole batch")
    p.add_argument("--fatrop", type=int, default=0, metavar="K",
                   help="also solve the first K instances with FATROP (needs the bench extra) and compare (0: off)")
    p.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    return p


def fatrop_time(args) -> tuple:
    """``(ms, note)``: FATROP's median time per instance (ms) on the first ``args.fatrop`` instances of the batch and
    a line that says so, or ``(None, why not)``."""
    try:
        from .reference import ReferenceSolver

        solver = ReferenceSolver(args.problem, "fatrop", tol=1e-8)
    except Exception as exc:  # no CasADi, or no FATROP plugin in it
        return None, f"FATROP: not run ({type(exc).__name__}: {exc})"
    row = run_reference(solver, args.problem, args.batch, args.seed, args.fatrop)
    if row.error is not None:
        return None, f"FATROP: failed ({row.error})"
    failed = row.status.get("failed", 0)
    return row.ms_per_instance, (f"FATROP (CasADi, built once, one instance at a time in this process): "
                                 f"{row.ms_per_instance:.2f} ms per instance, the median of {row.instances}"
                                 + (f" ({failed} failed)" if failed else ""))


def _options(args):
    if solvers.get(args.method).options_class.__name__ == "ALTROOptions":
        options = problems.altro_options(args.problem)
    else:
        options = make_options(args.method, cost_tolerance=1e-8, gradient_tolerance=1e-6)[0]
    return with_compile(args.method, options) if args.compile else options


def _rank(rank: int, world: int, port: int, args, path: str) -> None:
    os.environ["OMP_NUM_THREADS"] = str(args.threads)
    torch.set_num_threads(args.threads)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world,
                            timeout=datetime.timedelta(seconds=args.timeout))
    try:
        name = problems.at_horizon(args.problem, args.horizon) if args.horizon else args.problem
        problem, options = problems.get(name), _options(args)
        x0 = problems.sample_x0(args.problem, args.batch, seed=args.seed)
        warmup = time.perf_counter()
        if args.compile:  # the kernels of this rank's share of the batch (compiled kernels specialise to it)
            distributed.solve(problem, x0, args.method, options=options, gather=0)
        else:
            solve(problem, x0[:1], args.method, options=options)  # untimed: imports and first-call costs
        dist.barrier()
        warmup = time.perf_counter() - warmup
        start, cpu = time.perf_counter(), time.process_time()
        sol = distributed.solve(problem, x0, args.method, options=options, gather=0)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
        cpus = [None] * world
        dist.all_gather_object(cpus, cpu)
        if rank == 0:
            converged = float((sol.status == Status.CONVERGED).double().mean())
            with open(path, "w") as f:
                json.dump({"wall_s": wall, "cpu_s": cpus, "converged": converged,
                           "iterations_max": int(sol.iterations.max()), "warmup_s": warmup}, f)
        dist.barrier()
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_row(args, world: int) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "row.json")
        load_before = os.getloadavg()[0]
        mp.start_processes(_rank, args=(world, _free_port(), args, path), nprocs=world, start_method="spawn")
        with open(path) as f:
            row = json.load(f)
    row.update(processes=world, instances_per_s=args.batch / row["wall_s"], load_before=load_before,
               load_after=os.getloadavg()[0], free_core_instances_per_s=args.batch / max(row["cpu_s"]))
    return row


def main(argv: Optional[list] = None, out: Optional[TextIO] = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.batch < 1 or args.threads < 1 or any(w < 1 for w in args.processes) or args.fatrop < 0:
        p.error("--batch, --threads and --processes must be >= 1, --fatrop >= 0")
    if args.fatrop and args.horizon:
        p.error("--fatrop compares the problem set's own problem: leave out --horizon")
    out = out or sys.stdout

    def say(text: str = "") -> None:
        print(text, file=out, flush=True)

    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    say(f"torchtraj scale-out: {args.problem}"
        + (f" at N = {args.horizon}" if args.horizon else "")
        + f", method {args.method}"
        + (" (compiled kernels; compile s: the untimed warm-up of each launch)" if args.compile else "")
        + f", B = {args.batch} (sample_x0 seed {args.seed}), {args.threads} thread(s) per "
          f"process, Gloo; {cpus} CPU(s) usable, torch {torch.__version__}")
    fatrop_ms, note = fatrop_time(args) if args.fatrop else (None, None)
    if note:
        say(note)
    say(f"{'processes':>9} {'wall s':>9} {'inst/s':>9} {'speed-up':>9} {'rank CPU s':>11} {'free-core inst/s':>16} "
        f"{'converged':>9} {'max it':>7}" + (f" {'x FATROP':>9}" if fatrop_ms else "")
        + (f" {'compile s':>9}" if args.compile else "") + "  load avg before/after")
    rows = []
    for world in args.processes:
        row = run_row(args, world)
        rows.append(row)
        base = rows[0]["instances_per_s"]
        if fatrop_ms:
            row["times_fatrop"] = 1e3 * row["wall_s"] / args.batch / fatrop_ms
        say(f"{world:>9d} {row['wall_s']:>9.2f} {row['instances_per_s']:>9.2f} {row['instances_per_s'] / base:>9.2f} "
            f"{max(row['cpu_s']):>11.2f} {row['free_core_instances_per_s']:>16.2f} {100 * row['converged']:>8.1f}% "
            f"{row['iterations_max']:>7d}" + (f" {row['times_fatrop']:>9.2f}" if fatrop_ms else "")
            + (f" {row['warmup_s']:>9.1f}" if args.compile else "")
            + f"  {row['load_before']:.2f}/{row['load_after']:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"settings": vars(args), "cpus": cpus, "fatrop_ms_per_instance": fatrop_ms, "rows": rows}, f,
                      indent=1)
    return 0
