r"""``python -m torchtraj.bench --ops --compile``: the library calls a solve still makes with compiled kernels.

:class:`~torchtraj.bench.ops.OperatorCounter` cannot count such a solve: under a dispatch mode, Dynamo runs a
compiled function's Python eagerly, so the count is that of the eager code (a compiled IPM solve of the pendulum
counts about 3,800 calls an iteration under it, its kernels unused). This count reads the profiler instead
(:class:`LibraryCalls`, a ``torch.profiler`` session on the CPU), which sees what runs and changes nothing:

- ``calls``: the ATen operator calls made outside any other ATen call: the eager code's between the kernels, and
  those a compiled kernel makes through the library (the operators inductor writes no loop for: ``linalg``'s
  factorisations, ``pinv``, ``eigh``). A composite operator counts once here (``torch.matmul`` of two stacks of
  matrices), where the dispatch-mode counter sees what it decomposes into (``view``, ``bmm``, ``_unsafe_view``),
  so an eager solve counts fewer calls by this measure: each row gives both for the eager solve, side by side.
- ``kernels``: the calls of compiled functions (Dynamo's ``Torch-Compiled Region`` events); each checks its guards,
  then runs one inductor kernel of C++ loops.

For each method with compiled kernels (every registered one, unless ``--method``; those without,
:attr:`~torchtraj.solvers.base.Solver.compiles`, are named as skipped) on the pendulum (unless ``--problems``; the first
problem only) at B = 1 from the problem's ``x0``, default options with ``compile=True``: an untimed solve that
compiles the kernels (its seconds reported: inductor's cache makes a second process's much shorter), the counted
solve, and one timed solve each way without the profiler, so that the compile time stands next to the gain.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch
from torch.profiler import ProfilerActivity, profile

from .. import problems as problem_set
from .. import solvers
from ..core.problem import Problem
from ..core.recorded import forget
from ..core.status import Status
from ..solve import solve
from .ops import OperatorCounter, slope, with_horizon
from .ops_text import compiled_header, compiled_sweep_header, format_compiled, format_compiled_sweep
from .runs import skip_reason, state_guess, with_compile

#: Where Dynamo's call of a compiled function shows in the profiler.
KERNEL_EVENT = "Torch-Compiled Region"
#: The utility calls that the profiler's event list leaves out (``torch.autograd.profiler_util._filter_name``).
UNLISTED = frozenset({"aten::is_leaf", "aten::output_nr", "aten::_version"})
#: Why a method without compiled kernels (:attr:`~torchtraj.solvers.base.Solver.compiles`) has no row.
NO_KERNELS = "no compiled kernels: its compile option runs eager"


class LibraryCalls:
    """Counts, inside its ``with`` block, the ATen calls made outside other ATen calls (``calls``) and the calls
    of ``torch.compile``'d functions (``kernels``); module docstring."""

    def __init__(self) -> None:
        self.calls = 0
        self.kernels = 0
        self._profile = profile(activities=[ProfilerActivity.CPU])

    def __enter__(self) -> "LibraryCalls":
        self._profile.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._profile.__exit__(*exc)
        calls, kernels = count_events(self._profile.profiler.kineto_results.events())
        self.calls += calls
        self.kernels += kernels


def count_events(events) -> tuple:
    """``(calls, kernels)`` of the profiler's raw events (``kineto_results.events()``): the ATen calls on the CPU
    that no other ATen call on their thread encloses, and the calls of compiled functions. An event encloses
    another as the profiler's event tree nests them (``EventList``: sorted by start, the later end first; a later
    event outside an open one closes it), read from the raw intervals because building that tree takes the profiler
    seconds a solve (minutes and gigabytes for a long eager one)."""
    kernels = 0
    by_thread: dict = {}
    for event in events:
        name = event.name()
        if (event.device_type() != torch.autograd.DeviceType.CPU or event.is_async() or name in UNLISTED
                or event.start_thread_id() != event.end_thread_id() or event.is_hidden_event()):
            continue
        if name.startswith(KERNEL_EVENT):
            kernels += 1
        elif name.startswith("aten::"):
            start = event.start_ns()
            by_thread.setdefault(event.start_thread_id(), []).append((start, -(start + event.duration_ns())))
    calls = 0
    for intervals in by_thread.values():
        intervals.sort()
        open_ends: list = []  # ends of the enclosing ATen calls, innermost last
        for start, negated_end in intervals:
            end = -negated_end
            while open_ends and (start >= open_ends[-1] or end > open_ends[-1]):
                open_ends.pop()
            calls += not open_ends
            open_ends.append(end)
    return calls, kernels


@dataclass
class CompiledCount:
    """One method's solve at B = 1, eager and with compiled kernels; calls are per iteration."""

    problem: str
    method: str
    horizon: Optional[int] = None
    #: of the eager and the compiled solve (their arithmetic agrees to rounding, not to the bit)
    iterations: Optional[int] = None
    compiled_iterations: Optional[int] = None
    #: of the compiled solve
    status: Optional[str] = None
    #: the eager solve: the dispatch-mode count (:class:`~torchtraj.bench.ops.OperatorCounter`) and this module's
    eager_mode_calls: Optional[float] = None
    eager_calls: Optional[float] = None
    #: the compiled solve: ATen calls and compiled-function calls (module docstring)
    compiled_calls: Optional[float] = None
    kernels: Optional[float] = None
    #: with a horizon sweep: the compiled solve's calls per iteration past the setup (the solve capped at ``2k``
    #: iterations less the one capped at ``k``, over the iterations between), where it made ``2k``
    past_setup_calls: Optional[float] = None
    compile_seconds: Optional[float] = None
    eager_seconds: Optional[float] = None
    compiled_seconds: Optional[float] = None
    error: Optional[str] = None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def count_compiled(problem: Problem, method, setup: int = 0) -> CompiledCount:
    """Count and time ``method``'s solve of ``problem`` (B = 1, its ``x0``) eager and compiled (module docstring);
    ``setup > 0``: also the compiled calls past the first ``setup`` iterations (``past_setup_calls``), and the eager
    solve is not profiled (``eager_calls`` None: the profiler's events of a long eager solve take gigabytes). Never
    raises: an exception is kept in ``error``."""
    solver = solvers.get(method)
    row = CompiledCount(problem.name, solver.name, problem.N)
    eager = solver.default_options()
    compiled = with_compile(solver, eager)

    def run(options):
        return solve(problem, None, solver, X0=state_guess(solver, problem), options=options)

    try:
        forget()  # each solve counted cold, as those of torchtraj.bench.ops (the compiled kernels stay compiled)
        with OperatorCounter() as mode:
            sol = run(eager)
        iterations = int(sol.iterations.max())
        if not setup:
            forget()
            with LibraryCalls() as library:
                run(eager)
            row.eager_calls = library.calls / iterations
        start = time.perf_counter()
        run(compiled)
        row.compile_seconds = time.perf_counter() - start
        forget()
        with LibraryCalls() as kernels:
            sol_c = run(compiled)
        row.eager_seconds, row.compiled_seconds = _seconds(run, eager), _seconds(run, compiled)
        row.iterations, row.compiled_iterations = iterations, int(sol_c.iterations.max())
        row.status = ", ".join(Status.describe(sol_c.status))
        row.eager_mode_calls = mode.total / iterations
        row.compiled_calls = kernels.calls / row.compiled_iterations
        row.kernels = kernels.kernels / row.compiled_iterations
        if setup:
            row.past_setup_calls = _past_setup(run, solver, compiled, setup)
    except Exception as exc:  # one failing method must not stop the report
        row.error = f"{type(exc).__name__}: {exc}"
    return row


def _past_setup(run: Callable, solver, options, k: int) -> Optional[float]:
    """Library calls per iteration of iterations ``k+1`` to ``2k``: the solve capped at ``2k`` (the method's
    :meth:`~torchtraj.solvers.base.Solver.step_options`) less the one capped at ``k``; None where it ended before
    ``2k``."""
    counts = []
    for cap in (k, 2 * k):
        forget()
        with LibraryCalls() as library:
            sol = run(solver.step_options(options, cap))
        counts.append((library.calls, int(sol.iterations.max())))
    (short, k_made), (long, made) = counts
    return (long - short) / (made - k_made) if made == 2 * k and k_made == k else None


def _seconds(run: Callable, options) -> float:
    """Wall seconds of one more solve, without the records and call counts of the solves before it (an eager solve
    as a new process's: its expansions would otherwise reach the call that traces them), the compiled kernels warm."""
    forget()
    start = time.perf_counter()
    run(options)
    return time.perf_counter() - start


def run(methods: Sequence[str], name: str, say: Callable[..., None], dtype: torch.dtype = torch.float64,
        device=None, horizons: Optional[Sequence[int]] = None, setup: int = 5) -> dict:
    """Count each of ``methods`` on problem ``name`` (skipping those that cannot solve it), print the table as its
    rows come (``say``) and return ``{"problem", "rows"}`` (:meth:`CompiledCount.to_json` each). ``horizons``: the
    same problem at each of these horizons (:func:`~torchtraj.bench.ops.with_horizon`; each compiles its kernels
    anew, the stage loops unrolled), then per method the compiled calls per iteration past the first ``setup``
    iterations at each horizon (whole solves take other paths at other horizons: restorations, more corrections),
    their least-squares slope over N, and each horizon's compile time."""
    say(f"torchtraj bench --ops --compile: {name} at B = 1, {str(dtype).replace('torch.', '')}, torch "
        f"{torch.__version__}; calls and kernels per iteration (torchtraj.bench.compiled_ops)")
    base = problem_set.get(name, dtype=dtype, device=device)
    todo = []
    for m in methods:
        reason = skip_reason(m, base) or (None if solvers.get(m).compiles else NO_KERNELS)
        if reason:
            say(f"{solvers.get(m).name:7s}  skipped ({reason})")
        else:
            todo.append(m)
    rows = []
    for n in horizons or [None]:
        problem = base if n is None else with_horizon(base, n)
        if n is not None:
            say(f"N = {n}:")
        say(compiled_header())
        for m in todo:
            row = count_compiled(problem, m, setup if n is not None else 0)
            say(format_compiled(row))
            rows.append(row)
    if horizons and len(horizons) > 1:
        say()
        say(compiled_sweep_header(horizons))
        for m in todo:
            mine = [r for r in rows if r.method == solvers.get(m).name and r.past_setup_calls is not None]
            fitted = slope([r.horizon for r in mine], [r.past_setup_calls for r in mine]) if len(mine) > 1 else None
            say(format_compiled_sweep(solvers.get(m).name, mine, fitted, horizons))
    return {"problem": name, "rows": [r.to_json() for r in rows]}


def failed(report: dict) -> bool:
    return any(r["error"] for r in report["rows"])
