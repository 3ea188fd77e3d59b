"""The report of ``python -m torchtraj.bench --ops`` (what it counts: :mod:`torchtraj.bench.ops`): the full solves,
the horizon sweep (:mod:`torchtraj.bench.ops_sweep`) and the MPC rows, printed as their rows come and returned as
JSON-able data."""

from __future__ import annotations

import argparse
import datetime
import platform
from typing import Callable, Sequence

import torch

from .. import problems as problem_set
from .. import solvers
from .ops import (
    DEFAULT_HORIZONS,
    MPC_HORIZON,
    MPC_ITERATIONS,
    MPC_STEPS,
    SWEEP_ITERATIONS,
    count_mpc,
    count_recorded,
    count_solve,
)
from .ops_sweep import sweep
from .ops_text import format_count, solve_header
from .runs import skip_reason


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--ops-*`` options of ``python -m torchtraj.bench`` (with ``--ops``), which :func:`run` takes."""
    p.add_argument("--ops-horizons", nargs="+", type=int, metavar="N", default=list(DEFAULT_HORIZONS),
                   help=f"with --ops: the horizons of the sweep (default: {' '.join(map(str, DEFAULT_HORIZONS))}); "
                        "with --ops --compile, only where given: each compiles every kernel anew")
    p.add_argument("--ops-iterations", type=int, metavar="K", default=SWEEP_ITERATIONS,
                   help="with --ops: the sweep counts iterations 1 to K, K+1 to 2K, and each of K+1 to 2K alone "
                        f"(0: whole solves, default options, no setup in their slope; default: {SWEEP_ITERATIONS})")
    p.add_argument("--ops-mpc-steps", type=int, metavar="K", default=MPC_STEPS,
                   help=f"with --ops: control steps counted per MPC row (0: no MPC rows; default: {MPC_STEPS})")
    p.add_argument("--ops-mpc-iterations", type=int, metavar="K", default=MPC_ITERATIONS,
                   help=f"with --ops: solver iterations per counted control step (default: {MPC_ITERATIONS})")


def check(p: argparse.ArgumentParser, args) -> None:
    """Refuse ``--ops-*`` values that count nothing (``p.error``)."""
    if args.ops_mpc_steps < 0 or args.ops_mpc_iterations < 1:
        p.error(f"--ops-mpc-steps must be >= 0 and --ops-mpc-iterations >= 1, got {args.ops_mpc_steps}, "
                f"{args.ops_mpc_iterations}")
    if any(n < 1 for n in args.ops_horizons) or args.ops_iterations < 0:
        p.error(f"--ops-horizons must be >= 1 and --ops-iterations >= 0, got {args.ops_horizons}, "
                f"{args.ops_iterations}")


def run(methods: Sequence[str], names: Sequence[str], horizons: Sequence[int], iterations: int,
        say: Callable[..., None], dtype: torch.dtype = torch.float64, device=None, mpc_steps: int = MPC_STEPS,
        record: bool = False, mpc_iterations: int = MPC_ITERATIONS) -> dict:
    """Count, print the tables as their rows come (``say``) and return the report as JSON-able data:
    ``header``, ``skipped`` (``[{problem, method, reason}]``), ``solves`` (:meth:`Count.to_json` each) and
    ``horizons`` (``problem``, ``iterations`` cap and :func:`~torchtraj.bench.ops_sweep.sweep`'s tables) and ``mpc``
    (:meth:`StepCount.to_json` each, ``mpc_iterations`` solver iterations a step; ``mpc_steps = 0``: none).
    ``record``: also ``recorded``, the full solves again with recorded kernels (:func:`count_recorded`), for the
    methods that have them."""
    header = {
        "methods": list(methods), "problems": list(names), "horizons": list(horizons), "sweep_iterations": iterations,
        "mpc_iterations": mpc_iterations,
        "dtype": str(dtype).replace("torch.", ""), "device": str(torch.device(device or "cpu")),
        "torch": torch.__version__, "python": platform.python_version(), "date": datetime.date.today().isoformat(),
    }
    built = {name: problem_set.get(name, dtype=dtype, device=device) for name in names}
    skipped = [{"problem": name, "method": solvers.get(m).name, "reason": skip_reason(m, problem)}
               for name, problem in built.items() for m in methods if skip_reason(m, problem)]
    say(f"torchtraj bench --ops: eager torch operator calls (torchtraj.bench.ops.OperatorCounter) at B = 1, "
        f"{header['dtype']} on {header['device']}, torch {torch.__version__}, {header['date']}")
    for reason in dict.fromkeys(s["reason"] for s in skipped):
        which = [s for s in skipped if s["reason"] == reason]
        say(f"skipped ({reason}): " + "; ".join(
            f"{m} on " + ", ".join(s["problem"] for s in which if s["method"] == m)
            for m in dict.fromkeys(s["method"] for s in which)))
    say()
    say("full solves from the problem's x0, each method's default options")
    say(solve_header())
    solves = []
    for name in names:
        for m in methods:
            if not skip_reason(m, built[name]):
                # a problem of its own per solve: a solve's one-time setup on a problem is always counted
                row = count_solve(problem_set.get(name, dtype=dtype, device=device), m)
                say(format_count(row))
                solves.append(row)
    recorded = []
    if record:
        say()
        say("the same solves with recorded kernels (record=True), each after an uncounted solve that records them")
        say(solve_header())
        for name in names:
            for m in methods:
                if not skip_reason(m, built[name]) and solvers.get(m).records:
                    row = count_recorded(problem_set.get(name, dtype=dtype, device=device), m)
                    say(format_count(row))
                    recorded.append(row)

    sweep_name = names[0]
    swept = sweep(methods, sweep_name, horizons, iterations, say, dtype, device)
    steps = []
    if mpc_steps:
        say()
        say(f"MPC on the pendulum environment (tt.MPC(env.problem(horizon={MPC_HORIZON}), method, {mpc_iterations}), "
            f"B = 1): calls per control step over {mpc_steps} steps of the swing-up")
    for m in methods if mpc_steps else ():
        if solvers.get(m).handles_constraints:
            row = count_mpc(m, iterations=mpc_iterations, steps=mpc_steps)
            calls = f"ERROR {row.error.splitlines()[0]}" if row.error else f"{row.calls_per_step:.0f}"
            say(f"{row.method:7s}  {calls}")
            steps.append(row)
    return {
        "header": header, "skipped": skipped, "solves": [r.to_json() for r in solves],
        "recorded": [r.to_json() for r in recorded],
        "horizons": {"problem": sweep_name, "iterations": iterations, **swept},
        "mpc": [r.to_json() for r in steps],
    }


def failed(report: dict) -> bool:
    """Whether some counted solve or control step of ``report`` (:func:`run`) raised."""
    later = report["horizons"].get("past_setup", {}).get("rows", [])
    return any(r["error"] for r in report["solves"] + report["horizons"]["rows"] + later + report.get("mpc", []))
