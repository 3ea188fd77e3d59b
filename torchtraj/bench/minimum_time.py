"""``python -m torchtraj.bench --minimum-time``: FATROP's minimum-time benchmark in kind, next to IPOPT and FATROP.

For each problem of :mod:`torchtraj.bench.minimum_time_problems` (the cart-pendulum swing-up and the quadrotor
point-to-point, FATROP's Table III in kind) it prints one row per torchtraj method — :func:`tt.minimum_time` of the
fixed-time problem, solved with the method's default options from the rollout of the control guess — and one row
each for IPOPT and FATROP on the same discretisation (:mod:`torchtraj.bench.minimum_time_reference`, from the same
guess): status, iterations, total time T, cost, max violation and wall time. A method that does not solve a
problem is listed with the status it ended with. Exit status: 0, or 1 if a row raised.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Optional, TextIO

import torch

from .. import solvers
from ..core.status import Status
from ..solve import solve
from . import minimum_time_problems

#: every registered method that takes general constraints (ilqr ignores them)
METHODS = ("ipm", "altro", "al-ilqr", "eilqr", "hm-ilqr")
REFERENCES = ("ipopt", "fatrop")
#: FATROP's Table III (its own cart-pendulum and 3-D quadrotor models): iterations of FATROP and IPOPT
PAPER_ITERATIONS = {"cartpole_swing": ("cart pendulum swing", 88, 81), "quadrotor_p2p": ("quadrotor p2p", 63, 63)}
COLUMNS = (("problem", 15), ("method", 8), ("status", 18), ("iters", 6), ("T", 12), ("cost", 12),
           ("max viol", 9), ("wall s", 8))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m torchtraj.bench --minimum-time",
                                description=__doc__.split("\n\n", 1)[1])
    p.add_argument("--problems", nargs="+", choices=minimum_time_problems.names(),
                   default=minimum_time_problems.names(), help="default: all")
    p.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                   help=f"torchtraj methods (default: {' '.join(METHODS)})")
    p.add_argument("--no-reference", action="store_true", help="skip the CasADi IPOPT / FATROP rows")
    p.add_argument("--reference-tolerance", type=float, default=1e-8, help="IPOPT / FATROP tol (default: 1e-8)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's choice)")
    return p


def _line(cells) -> str:
    return "  ".join(str(c).rjust(w) if i >= 3 else str(c).ljust(w)
                     for i, (c, (_, w)) in enumerate(zip(cells, COLUMNS))).rstrip()


def run_torchtraj(name: str, method: str) -> list:
    """The cells of one torchtraj row: the transform is built (and probed) before the clock starts."""
    transform = minimum_time_problems.get(name)
    start = time.perf_counter()
    sol = solve(transform.problem, method=method)
    seconds = time.perf_counter() - start
    return [name, method, Status(int(sol.status[0])).name, int(sol.iterations[0]),
            f"{float(transform.duration(sol.X)[0]):.8f}", f"{float(sol.cost[0]):.8f}",
            f"{float(sol.max_violation[0]):.1e}", f"{seconds:.2f}"]


def run_reference(name: str, solver: str, tol: float) -> list:
    from .minimum_time_reference import MinimumTimeReference

    result = MinimumTimeReference(name, solver, tol=tol).solve()
    return [name, solver, result.status, result.iterations, f"{result.duration:.8f}", f"{result.cost:.8f}",
            f"{result.max_violation:.1e}", f"{result.seconds:.2f}"]


def main(argv: Optional[list] = None, out: Optional[TextIO] = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    out = out or sys.stdout
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    say = lambda text="": print(text, file=out, flush=True)  # noqa: E731
    say(f"torchtraj minimum time (FATROP §V): float64 on cpu, {torch.get_num_threads()} threads, default options, "
        f"no guess beyond the control's; references tol {args.reference_tolerance:g}")
    titles = _line([t for t, _ in COLUMNS])
    say(titles)
    say("-" * len(titles))
    failed = False
    for name in args.problems:
        rows = [lambda m=m: run_torchtraj(name, solvers.get(m).name) for m in args.methods]
        if not args.no_reference:
            rows += [lambda s=s: run_reference(name, s, args.reference_tolerance) for s in REFERENCES]
        for row in rows:
            try:
                say(_line(row()))
            except Exception as exc:  # reported, not fatal
                failed = True
                say(f"{name}  ERROR {type(exc).__name__}: {exc}")
        label, fatrop, ipopt = PAPER_ITERATIONS[name]
        say(f"  FATROP's Table III, {label} (its own model): FATROP {fatrop}, IPOPT {ipopt} iterations")
    say("T: total time (s); cost: w_T T + the problem's own cost (here T alone); wall s: the solve call alone.")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
