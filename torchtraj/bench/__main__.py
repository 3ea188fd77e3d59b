"""``python -m torchtraj.bench``: time torchtraj on the benchmark problems, next to IPOPT and FATROP.

For every problem and batch size B it prints one row for the torchtraj method and, when CasADi is
installed, one row each for IPOPT and FATROP solving the same initial states, then per problem a
throughput line comparing torchtraj's ms/instance at the largest B with FATROP's. B = 1 uses the
problem's own x0; B > 1 uses ``torchtraj.problems.sample_x0(problem, B, seed)``. Nothing is written
unless ``--json PATH`` is given. Exit status: 0, or 1 if some row failed (its error is in the row).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
from typing import Optional, TextIO

import torch

from .. import problems, solvers
from ..core.progress import Progress
from ..solve import solve
from ..solvers.altro.options import ALTROOptions
from ..solvers.base import Solver
from . import compiled_ops, grad, launches, ops, ops_report, profile, table
from .runs import (
    Row,
    batch_x0,
    make_options,
    relative_difference,
    run_reference,
    run_torchtraj,
    skip_reason,
    state_guess,
    with_compile,
    with_record,
)

REFERENCE_SOLVERS = ("ipopt", "fatrop")
#: Batch of the ALTRO throughput line (issue: pendulum, sample_x0 seed 0, B = 1024 in one batch).
THROUGHPUT_BATCH = 1024


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m torchtraj.bench", description=__doc__.split("\n\n", 1)[1],
    )  # each help text states its default once (argparse's defaults formatter repeated them)
    p.add_argument("--problems", nargs="+", metavar="NAME", choices=problems.names(),
                   help=f"problems to run, from {problems.names()}; default: every problem the method can solve "
                        "(ilqr: those without constraints); the others are listed as skipped, with the reason")
    p.add_argument("--method", default="ilqr", choices=solvers.names(),
                   help="torchtraj method (default: ilqr; with --grad, tt.solve's choice for its problems: ipm)")
    p.add_argument("--batch", nargs="+", type=int, default=[1, 64, 1024], metavar="B",
                   help="batch sizes (default: 1 64 1024; 16 64 256 with --grad)")
    p.add_argument("--seed", type=int, default=0, help="seed of sample_x0 for B > 1 (default: 0)")
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                   help="dtype of the problems and the solve (default: float64)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="device of the torchtraj rows; the references run on the CPU (default: cpu)")
    p.add_argument("--cost-tolerance", type=float, default=1e-8,
                   help="the method options' cost_tolerance (default: 1e-8)")
    p.add_argument("--gradient-tolerance", type=float, default=1e-6,
                   help="the method options' gradient_tolerance (default: 1e-6)")
    p.add_argument("--iterations", type=int, default=None,
                   help="the method options' iteration cap (default: the options' own default)")
    p.add_argument("--warmup-iterations", type=int, default=5,
                   help="iteration cap of the untimed one-instance warm-up solve before each timed row (default: 5)")
    p.add_argument("--repeat", type=int, default=1, metavar="K",
                   help="time each row K times: torchtraj's time is the median of K solves of the batch, a "
                        "reference's each instance's median of K solves (default: 1)")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's choice)")
    p.add_argument("--no-reference", action="store_true", help="skip the CasADi IPOPT / FATROP rows")
    p.add_argument("--reference-instances", type=int, default=16,
                   help="IPOPT / FATROP solve the first min(B, this) of a row's initial states (default: 16)")
    p.add_argument("--reference-tolerance", type=float, default=1e-8, help="IPOPT / FATROP tol (default: 1e-8)")
    p.add_argument("--json", metavar="PATH", help="also write the header and all rows as JSON to PATH")
    p.add_argument("--profile", action="store_true",
                   help="after the rows, solve the throughput batch again under cProfile and print where its time "
                        "goes (torchtraj.bench.profile.parts_of)")
    p.add_argument("--grad", action="store_true",
                   help="run the gradient benchmark instead (torchtraj.bench.grad: forward/backward times and "
                        "agreement with finite differences next to mpc.pytorch); --batch then defaults to "
                        "16 64 256 (the pendulum rows use those <= 64) and --method to tt.solve's choice: ipm")
    p.add_argument("--gradients", choices=("implicit", "unrolled"), default="implicit",
                   help="with --grad: tt.solve's gradients mode (unrolled: the final iLQR step's derivative, "
                        "approximate where the dynamics or constraints are curved; default: implicit)")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the solver's kernels (ILQROptions.compile); every row first runs untimed at "
                        "its own batch size, which compiles, and says how long that took")
    p.add_argument("--record", action="store_true",
                   help="replay the expansion from recorded operator graphs (the options' record=True; "
                        "torchtraj.core.recorded: a signature is traced at its TRACE_AT-th call); every row first "
                        "runs untimed at its own batch size, again while a run traces anything new (at most 3), and "
                        "says how long that took, so that the timed solve is one of repeated solves (as FATROP's, "
                        "built once); with --ops, also count every full solve again with them, after an uncounted "
                        "solve that records")
    p.add_argument("--cuda-graphs", action="store_true",
                   help="with --method ipm (the timing rows or --grad): replay the IPM's per-iteration kernels from "
                        "CUDA graphs (IPOptions.cuda_graphs; no effect on a CPU); a timing row first runs untimed at "
                        "its own batch size, again while a run captures a new graph (at most 3)")
    p.add_argument("--barrier", choices=("monotone", "mehrotra"), default="monotone",
                   help="with --grad --method ipm: the barrier strategy of the linear_box rows "
                        "(IPOptions.barrier_strategy; mehrotra is for convex problems, so the pendulum rows stay "
                        "monotone; default: monotone)")
    p.add_argument("--mpc", action="store_true",
                   help="run the MPC acceptance runs and timing instead (torchtraj.bench.mpc, with options of its "
                        "own: python -m torchtraj.bench --mpc --help)")
    p.add_argument("--scale-out", action="store_true",
                   help="time one batch on 1, 2, ... local processes instead (torchtraj.bench.scale_out, with options "
                        "of its own: python -m torchtraj.bench --scale-out --help)")
    p.add_argument("--minimum-time", action="store_true",
                   help="run FATROP's minimum-time benchmark in kind instead (torchtraj.bench.minimum_time, with "
                        "options of its own: python -m torchtraj.bench --minimum-time --help)")
    p.add_argument("--ops", action="store_true",
                   help="report eager torch operator calls per solve and per iteration instead (torchtraj.bench.ops: "
                        "B = 1, each method's default options, so the tolerance and --iterations flags do not apply; "
                        "then a horizon sweep on the first problem); --method then defaults to every registered "
                        "method and --problems to pendulum cartpole car_3obs; with --compile, the library calls and "
                        "compiled-kernel calls per iteration of solves with compiled kernels instead, next to the "
                        "eager counts, the compile time and both solve times (torchtraj.bench.compiled_ops; the "
                        "first problem only, pendulum by default)")
    p.add_argument("--defaults", action="store_true",
                   help="run every method that handles the problems' constraints with its default options and no "
                        "guess on the problem set instead, against IPOPT (torchtraj.bench.defaults); --method then "
                        "defaults to every such method, --batch to 1 (B > 1: sample_x0 batches, the first "
                        "--reference-instances compared with IPOPT)")
    ops_report.add_arguments(p)
    launches.add_arguments(p)
    return p


def _check(p: argparse.ArgumentParser, args) -> None:
    if any(b < 1 for b in args.batch):
        p.error(f"--batch sizes must be >= 1, got {args.batch}")
    if min(args.reference_instances, args.warmup_iterations, args.repeat) < 1:
        p.error("--reference-instances, --warmup-iterations and --repeat must be >= 1")
    if args.threads is not None and args.threads < 1:
        p.error(f"--threads must be >= 1, got {args.threads}")
    if args.cuda_graphs and not (_has_option(args.method, "cuda_graphs") and not (args.compile or args.ops)):
        p.error("--cuda-graphs goes with --method ipm, without --compile and --ops")
    if args.barrier != "monotone" and not (args.grad and _has_option(args.method, "barrier_strategy")
                                           and not args.compile and not args.cuda_graphs):
        p.error("--barrier mehrotra goes with --grad --method ipm, without --compile and --cuda-graphs")
    if args.record and (args.grad or args.compile
                        or not (args.ops or solvers.get(args.method).records)):
        p.error("--record goes with --ops, or with the timing rows of a method with a record option (ipm, altro, "
                "al-ilqr, eilqr, hm-ilqr), without --grad and --compile")
    if args.compile and not args.ops and args.method in solvers.names() and not solvers.get(args.method).compiles:
        p.error(f"--compile: method {args.method} has no compiled kernels (its compile option runs eager)")
    if args.ops and (args.grad or args.profile or (args.compile and args.record)):
        p.error("--ops goes without --grad and --profile, and with --compile or --record, not both")
    ops_report.check(p, args)
    launches.check(p, args)
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch.cuda.is_available() is False")


def parsed(p: argparse.ArgumentParser, argv: list) -> argparse.Namespace:
    """``p``'s arguments of ``argv``, where ``--grad`` names no ``--method`` with the one ``tt.solve`` picks for the
    gradient benchmark's problems (:func:`torchtraj.bench.grad.default_method`)."""
    args = p.parse_args(argv)
    if args.grad and _named_method(argv) is None:
        args.method = grad.default_method()
    return args


def _named_method(argv: list) -> Optional[str]:
    """The ``--method`` that ``argv`` names (the timing rows' default, ilqr, too), or None where it names none."""
    probe = parser()
    probe.set_defaults(method=None)
    return probe.parse_args(argv).method


def _has_option(method: str, name: str) -> bool:
    """Whether ``method``'s options class has the field ``name`` (the flags that set one go with those methods)."""
    return name in {f.name for f in dataclasses.fields(solvers.get(method).options_class)}


def _reference_available(args) -> tuple:
    """``(available, why not / casadi version)``."""
    if args.no_reference:
        return False, "off (--no-reference)"
    try:
        from .casadi_models import import_casadi
        return True, f"casadi {import_casadi().__version__}"
    except ImportError:
        return False, "off (casadi is not importable: pip install torchtraj[bench])"


def _build_references(name: str, tol: float) -> dict:
    """``{solver: ReferenceSolver or the exception text of its construction}``."""
    from .reference import ReferenceSolver

    built = {}
    for solver in REFERENCE_SOLVERS:
        try:
            built[solver] = ReferenceSolver(name, solver, tol=tol)
        except Exception as exc:  # reported in each of its rows
            built[solver] = f"{type(exc).__name__}: {exc}"
    return built


def _profile_line(problem, method: Solver, batch: int, seed: int, options) -> str:
    """The batch of the throughput row solved again under cProfile: the share of each solver part."""
    x0, X0 = batch_x0(problem.name, batch, seed), state_guess(method, problem)
    seconds, parts = profile.split(lambda: solve(problem, x0, method, X0=X0, options=options),
                                   profile.parts_of(method.name))
    return (f"  where the time goes ({problem.name}, B={batch}, profiled run of {seconds:.1f} s): "
            f"{profile.format_split(parts)}")


def main(argv: Optional[list] = None, out: Optional[TextIO] = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--mpc" in argv:
        from . import mpc
        return mpc.main([a for a in argv if a != "--mpc"], out)
    if "--scale-out" in argv:
        from . import scale_out
        return scale_out.main([a for a in argv if a != "--scale-out"], out)
    if "--minimum-time" in argv:
        from . import minimum_time
        return minimum_time.main([a for a in argv if a != "--minimum-time"], out)
    p = parser()
    args = parsed(p, argv)
    if args.compile:
        profile.quiet_inductor()
    _check(p, args)
    out = out or sys.stdout
    bar = Progress(label=f"bench {args.method}", unit="rows")  # on stderr, between the timed solves

    def say(text: str = "") -> None:
        bar.clear()  # a table line never lands on the bar's line
        print(text, file=out, flush=True)

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dtype, device = getattr(torch, args.dtype), torch.device(args.device)
    if args.ops:
        methods = [chosen] if (chosen := _named_method(argv)) else solvers.names()
        if args.compile:
            counter = compiled_ops
            report = compiled_ops.run(methods, (args.problems or ["pendulum"])[0], say, dtype, device,
                                      args.ops_horizons if "--ops-horizons" in argv else None, args.ops_iterations)
        else:
            counter = ops_report
            report = ops_report.run(methods, args.problems or list(ops.DEFAULT_PROBLEMS), args.ops_horizons,
                                     args.ops_iterations, say, dtype, device, args.ops_mpc_steps, record=args.record,
                                     mpc_iterations=args.ops_mpc_iterations)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(report, f, indent=1)
        return 1 if counter.failed(report) else 0
    if args.defaults:
        from . import defaults
        chosen = _named_method(argv)
        batches = args.batch if args.batch != p.get_default("batch") else [1]
        rows = defaults.run([chosen] if chosen else solvers.names(), args.problems or problems.names(), batches,
                            args.seed, args.reference_instances, say)
        return 0 if all(r.converged == r.batch for r in rows) else 1
    if args.grad:
        batches = args.batch if args.batch != p.get_default("batch") else [16, 64, 256]
        name = args.method
        pendulum = [b for b in batches if b <= 64] or batches[:1]  # each FD direction re-solves the batch twice
        defaults = solvers.get(name).options_class
        options = None
        if args.compile:
            options = with_compile(name, defaults())
        if args.cuda_graphs:  # _check: the method's options have the field
            options = defaults(cuda_graphs=True)
        lq_options = None
        if args.barrier != "monotone":
            lq_options = defaults(barrier_strategy=args.barrier)
        rows = grad.run(batches, args.seed, name, say, dtype, device, pendulum, options=options,
                        with_mpc=not args.no_reference, gradients=args.gradients, lq_options=lq_options)
        return 1 if any(r.solver.startswith("torchtraj") and r.forward_s != r.forward_s for r in rows) else 0
    method = solvers.get(args.method)
    options, applied = make_options(method, cost_tolerance=args.cost_tolerance,
                                    gradient_tolerance=args.gradient_tolerance, iterations=args.iterations)
    ignored = sorted({"cost_tolerance", "gradient_tolerance"} - set(applied))
    # the problem set has options of its own for the methods run by ALTROOptions (problems.altro_options): those,
    # not the CLI's, and the time-penalised problems (ALTRO §III-C) after the rows
    augmented = method.options_class is ALTROOptions
    if augmented:
        ignored = []
    default_batches = args.batch == p.get_default("batch")
    with_reference, reference_note = _reference_available(args)

    todo, skipped = [], []
    for name in args.problems or problems.names():
        problem = problems.get(name, dtype=dtype, device=device)
        reason = skip_reason(method, problem)
        if reason:
            skipped.append((name, reason))
        else:
            todo.append(problem)

    settings = {k: getattr(options, k) for k in ("cost_tolerance", "gradient_tolerance", "iterations")
                if hasattr(options, k)}
    head = {
        "method": method.name, "options": type(options).__name__, "settings": settings,
        "dtype": args.dtype, "device": str(device), "threads": torch.get_num_threads(), "seed": args.seed,
        "batch": args.batch, "torch": torch.__version__, "python": platform.python_version(),
        "reference": reference_note, "reference_tolerance": args.reference_tolerance,
        "reference_instances": args.reference_instances, "skipped": dict(skipped),
    }
    say(f"torchtraj bench: method {method.name}, {type(options).__name__}("
        + ", ".join(f"{k}={v:g}" for k, v in settings.items()) + ")"
        + (f"; {type(options).__name__} has no {', '.join(ignored)}, not applied" if ignored else ""))
    say(f"{args.dtype} on {device}, {torch.get_num_threads()} threads, torch {torch.__version__}, seed {args.seed}; "
        f"reference IPOPT/FATROP: " + (f"{reference_note}, tol {args.reference_tolerance:g}, up to "
                                       f"{args.reference_instances} instances per row" if with_reference
                                       else reference_note))
    for reason in dict.fromkeys(r for _, r in skipped):
        say(f"skipped ({reason}): " + ", ".join(n for n, r in skipped if r == reason))
    say()
    say(table.header())

    rows: list = []
    throughput: list = []
    bar.total = sum(len(args.batch) if not (augmented and default_batches) else 1 + (p.name == "pendulum")
                    for p in todo)
    for problem in todo:
        refs = _build_references(problem.name, args.reference_tolerance) if with_reference else {}
        problem_rows = []
        batches = args.batch
        if augmented and default_batches:  # every problem once, the throughput line on the pendulum batch
            batches = [1, THROUGHPUT_BATCH] if problem.name == "pendulum" else [1]
        # for al-ilqr, its solve turns the projection off
        problem_options = problems.altro_options(problem.name) if augmented else options
        if args.compile:
            problem_options = with_compile(method, problem_options)
        if args.record:
            problem_options = with_record(method, problem_options)
        if args.cuda_graphs:  # _check: the method's options have the field
            problem_options = dataclasses.replace(problem_options, cuda_graphs=True)
        for batch in batches:
            ours = run_torchtraj(problem, method, batch, args.seed, problem_options, args.warmup_iterations,
                                 args.repeat)
            group = [ours]
            for solver, built in refs.items():
                if isinstance(built, str):
                    group.append(Row(problem.name, solver, batch, error=built))
                else:
                    group.append(run_reference(built, problem.name, batch, args.seed, args.reference_instances,
                                               args.repeat))
            ipopt = next((r for r in group if r.method == "ipopt"), None)
            for row in group:
                if ipopt is not None and row is not ipopt:
                    row.vs_ipopt = relative_difference(row, ipopt)
                say(table.format_row(row))
                if row.compile_seconds is not None:
                    say(f"  (the untimed run of this batch before it, which compiled the kernels: "
                        f"{row.compile_seconds:.1f} s)")
                if row.record_seconds is not None:
                    say(f"  (the untimed runs of this batch before it, which recorded the kernels"
                        f"{' (CUDA graphs)' if args.cuda_graphs else ''}: {row.record_seconds:.1f} s)")
            problem_rows += group
            bar.update(converged=torch.tensor(ours.instance_ok or [False], dtype=torch.bool),
                       violation=ours.max_violation, problem=problem.name)
        throughput.append(table.throughput(problem.name, problem_rows, max(batches), REFERENCE_SOLVERS))
        if args.profile and max(batches) > 1:
            throughput.append(_profile_line(problem, method, max(batches), args.seed, problem_options))
        if args.launches:
            x0, X0 = batch_x0(problem.name, max(batches), args.seed), state_guess(method, problem)
            throughput.append(launches.report(problem, method.name, max(batches), lambda: solve(
                problem, x0, method, X0=X0, options=problem_options)))
        rows += problem_rows
    bar.close()
    say()
    for line in throughput:
        say(line)
    if augmented and default_batches:
        from .time_penalized import report_time_penalized
        say()
        for line in report_time_penalized(method.name, dtype, device):
            say(line)
    say(table.legend())

    if args.json:
        with open(args.json, "w") as f:
            json.dump({"header": head, "rows": [r.to_json() for r in rows], "throughput": throughput}, f, indent=1)
    return 1 if any(r.error for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
