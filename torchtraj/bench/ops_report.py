"""The report of ``python -m torchtraj.bench --ops`` (what it counts: :mod:`torchtraj.bench.ops`): the full solves,
the horizon sweep (:mod:`torchtraj.bench.ops_sweep`) and the MPC rows, printed as their rows come and returned as
JSON-able data."""

from __future__ import annotations

import datetime
import platform
from typing import Callable, Sequence

import torch

from .. import problems as problem_set
from .. import solvers
from .ops import MPC_HORIZON, MPC_ITERATIONS, MPC_STEPS, count_mpc, count_recorded, count_solve
from .ops_sweep import sweep
from .ops_text import format_count, solve_header
from .runs import skip_reason


def run(methods: Sequence[str], names: Sequence[str], horizons: Sequence[int], iterations: int,
        say: Callable[..., None], dtype: torch.dtype = torch.float64, device=None, mpc_steps: int = MPC_STEPS,
        record: bool = False) -> dict:
    """Count, print the tables as their rows come (``say``) and return the report as JSON-able data:
    ``header``, ``skipped`` (``[{problem, method, reason}]``), ``solves`` (:meth:`Count.to_json` each) and
    ``horizons`` (``problem``, ``iterations`` cap and :func:`~torchtraj.bench.ops_sweep.sweep`'s tables) and ``mpc``
    (:meth:`StepCount.to_json` each; ``mpc_steps = 0``: none). ``record``: also ``recorded``, the full solves again
    with recorded kernels (:func:`count_recorded`), for the methods that have them."""
    header = {
        "methods": list(methods), "problems": list(names), "horizons": list(horizons), "sweep_iterations": iterations,
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
        say(f"MPC on the pendulum environment (tt.MPC(env.problem(horizon={MPC_HORIZON}), method, {MPC_ITERATIONS}), "
            f"B = 1): calls per control step over {mpc_steps} steps of the swing-up")
    for m in methods if mpc_steps else ():
        if solvers.get(m).handles_constraints:
            row = count_mpc(m, steps=mpc_steps)
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
