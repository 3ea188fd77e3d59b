"""One benchmark row: a timed batched ``tt.solve``, or IPOPT / FATROP solving the same instances.

A :class:`Row` summarises B instances of one problem solved by one method: iterations (median, max),
cost (median, and every instance's), the largest constraint violation, status counts and time.
Rows never raise: an exception is caught and kept in ``Row.error`` so the rest of a run goes on.

Timing. torchtraj is timed around one ``tt.solve`` of the whole batch (``time.perf_counter``, with
``torch.cuda.synchronize`` on CUDA) after an untimed warm-up solve of one instance; its
``ms_per_instance`` is the total divided by B. With ``repeat`` K > 1 (``--repeat``) the batch is solved K times and
its time is their median, and a reference solver solves each instance K times and takes each instance's median: a
short solve's single time moves with the machine's load and the garbage collector by more than a change measures.
The warm-up's few iterations leave the recorded kernels' call counts low (:mod:`torchtraj.core.recorded`): with
the default ``record=None`` a long timed solve traces the shapes it evaluates often within its own time, as a user's
first solve would, and a short one runs eager. A reference solver is timed around each solve call alone (its NLP is
built once beforehand,
:class:`~torchtraj.bench.reference.ReferenceSolver`); its ``ms_per_instance`` is the median over instances and
``seconds`` their sum.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import torch

from .. import problems, solvers
from ..core.graphs import captures as graph_captures
from ..core.graphs import graphs_used
from ..core.problem import Problem
from ..core.recorded import traces as recorded_traces
from ..core.status import Status
from ..solve import solve
from ..solvers.base import Solver


@dataclass
class Row:
    """Summary of one (problem, method, batch size) run; see the module docstring for the timing."""

    problem: str
    method: str
    batch: int
    instances: int = 0
    iterations_median: float = float("nan")
    iterations_max: int = -1
    cost_median: float = float("nan")
    costs: list = field(default_factory=list)
    max_violation: float = float("nan")
    status: dict = field(default_factory=dict)
    #: per instance: torchtraj converged / the reference solver reported success.
    instance_ok: list = field(default_factory=list)
    seconds: float = float("nan")
    ms_per_instance: float = float("nan")
    #: timed solves of the batch (torchtraj) or of each instance (references) whose median is the time
    repeat: int = 1
    #: max over the compared instances of ``|J − J_ipopt| / |J_ipopt|`` (None where not compared).
    vs_ipopt: Optional[float] = None
    #: compiled kernels: seconds of the untimed run of the whole batch before the timed one, which compiles them
    #: (the kernels that already have a graph for these shapes in this process take none).
    compile_seconds: Optional[float] = None
    #: recorded kernels: seconds of the untimed runs of the whole batch before the timed one, which record the
    #: signatures they call often enough (``TRACE_AT``), repeated while a run traces anything new (at most
    #: :data:`RECORD_WARM_UPS`), so that the timed solve replays them: the state of repeated solves
    record_seconds: Optional[float] = None
    error: Optional[str] = None

    def to_json(self) -> dict:
        out = dataclasses.asdict(self)
        for key, value in out.items():  # JSON has no NaN
            if isinstance(value, float) and not np.isfinite(value):
                out[key] = None
        out["costs"] = [c if np.isfinite(c) else None for c in self.costs]
        return out


def skip_reason(method, problem: Problem) -> Optional[str]:
    """Why ``method`` (a name or a :class:`~torchtraj.solvers.base.Solver`) cannot solve ``problem`` (None if it
    can)."""
    solver = solvers.get(method)
    if not solver.handles_constraints and problem.has_constraints:
        return f"{solver.name} ignores constraints, which these problems have"
    return None


def state_guess(solver: Solver, problem: Problem):
    """The state guess of a row: the problem's own (``Problem.X_init``: ALTRO's infeasible start of car_escape)
    for every method that takes one, else None."""
    return problem.X_init if solver.takes_state_guess else None


def make_options(method, **values) -> tuple:
    """The method's options dataclass with those of ``values`` that it has as fields (None values skipped).

    Returns ``(options, applied)``, ``applied`` the dict of the values actually set.
    """
    cls = solvers.get(method).options_class
    names = {f.name for f in dataclasses.fields(cls)}
    applied = {k: v for k, v in values.items() if v is not None and k in names}
    return cls(**applied), applied


def compiled(method, options) -> bool:
    """Whether ``options`` of ``method`` (a name or a solver; ``None`` options: its defaults) run compiled kernels:
    they ask for them (:meth:`~torchtraj.solvers.base.Solver.kernel_options`) and the method has them
    (:attr:`~torchtraj.solvers.base.Solver.compiles`)."""
    solver = solvers.get(method)
    return solver.compiles and bool(solver.kernel_setting(options, "compile"))


def recorded(method, options) -> bool:
    """Whether ``options`` of ``method`` replay recorded kernels from their eighth call on (``record=True``,
    :meth:`~torchtraj.solvers.base.Solver.kernel_options`; the default ``None`` records only where it pays)."""
    solver = solvers.get(method)
    return solver.records and solver.kernel_setting(options, "record") is True


def with_record(method, options):
    """``options`` of ``method`` with recorded kernels (``record=True`` where the method keeps it,
    :meth:`~torchtraj.solvers.base.Solver.with_kernels`)."""
    return solvers.get(method).with_kernels(options, record=True)


def with_compile(method, options):
    """``options`` of ``method`` with compiled kernels (``compile=True`` where the method keeps it)."""
    return solvers.get(method).with_kernels(options, compile=True)


def batch_x0(name: str, batch: int, seed: int) -> Optional[torch.Tensor]:
    """The initial states of a row: None (the problem's own x0) for B = 1, else ``sample_x0``'s ``(B, nx)``."""
    return None if batch == 1 else problems.sample_x0(name, batch, seed)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run_torchtraj(problem: Problem, method, batch: int, seed: int, options,
                  warmup_iterations: int, repeat: int = 1) -> Row:
    """Warm up on one instance (at most ``warmup_iterations`` iterations), then time the batch (the median of
    ``repeat`` timed solves). With compiled
    kernels (``ILQROptions.compile``), which specialise to the batch size, the warm-up is the whole batch, timed
    (``compile_seconds``); so it is with recorded kernels (``record=True``), whose records are per batch size too,
    repeated while a run traces anything new (``record_seconds``, :func:`_record_warm_up`): the timed solve is then
    one of repeated solves, as a solver built once is timed."""
    method = solvers.get(method)
    row = Row(problem.name, method.name, batch)
    try:
        x0 = batch_x0(problem.name, batch, seed)
        X0 = state_guess(method, problem)
        if hasattr(options, "iterations"):
            warm = dataclasses.replace(options, iterations=min(options.iterations, warmup_iterations))
        else:
            warm = dataclasses.replace(options, iterations_outer=1, iterations_inner=warmup_iterations)
        if compiled(method, options):
            start = time.perf_counter()
            solve(problem, x0, method, X0=X0, options=options)
            _sync(problem.device)
            row.compile_seconds = time.perf_counter() - start
        elif recorded(method, options):
            row.record_seconds = _record_warm_up(lambda: solve(problem, x0, method, X0=X0, options=options),
                                                 problem.device, recorded_traces)
        elif graphs_used(options, problem.device):
            row.record_seconds = _record_warm_up(lambda: solve(problem, x0, method, X0=X0, options=options),
                                                 problem.device, graph_captures)
        else:
            solve(problem, None, method, X0=X0, options=warm)
        _sync(problem.device)
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            sol = solve(problem, x0, method, X0=X0, options=options)
            _sync(problem.device)
            times.append(time.perf_counter() - start)
        row.seconds, row.repeat = statistics.median(times), repeat
        iters = sol.iterations.cpu().tolist()
        row.instances = len(iters)
        row.iterations_median, row.iterations_max = float(statistics.median(iters)), int(max(iters))
        row.costs = sol.cost.double().cpu().tolist()
        row.cost_median = float(statistics.median(row.costs))
        row.max_violation = float(sol.max_violation.max())
        row.status = Status.counts(sol.status.cpu())
        row.instance_ok = (sol.status == Status.CONVERGED).cpu().tolist()
        row.ms_per_instance = 1e3 * row.seconds / row.instances
    except Exception as exc:  # one failing row must not stop the run
        row.error = f"{type(exc).__name__}: {exc}"
    return row


#: Untimed runs of a recorded row at most: a run records the signatures it calls TRACE_AT times, and one that it
#: calls fewer times a run (a compacted batch's sizes) records in a later one.
RECORD_WARM_UPS = 3


def _record_warm_up(run: Callable, device, recordings: Callable) -> float:
    """Seconds of the untimed runs before a recorded row's timed one (recorded kernels or CUDA graphs): again while
    a run recorded something new (``recordings()``, a count, grew; at most :data:`RECORD_WARM_UPS` runs), so that
    the timed run replays what a run of repeated solves replays."""
    start = time.perf_counter()
    for _ in range(RECORD_WARM_UPS):
        before = recordings()
        run()
        _sync(device)
        if recordings() == before:
            break
    return time.perf_counter() - start


def run_reference(solver, name: str, batch: int, seed: int, instances: int, repeat: int = 1) -> Row:
    """Solve the first ``min(batch, instances)`` of the row's initial states with a built ``ReferenceSolver``, each
    ``repeat`` times (its time: the median)."""
    row = Row(name, solver.solver_name, batch, repeat=repeat)
    try:
        x0 = batch_x0(name, batch, seed)
        starts = [None] if x0 is None else list(x0[: min(batch, instances)].numpy())
        solves = [[solver.solve(x) for _ in range(repeat)] for x in starts]
        results = [each[0] for each in solves]
        row.instances = len(results)
        iters = [r.iterations for r in results]
        row.iterations_median, row.iterations_max = float(statistics.median(iters)), int(max(iters))
        row.costs = [r.cost for r in results]
        row.cost_median = float(statistics.median(row.costs))
        row.max_violation = max(r.max_violation for r in results)
        ok = sum(r.ok for r in results)
        row.status = {k: v for k, v in (("ok", ok), ("failed", len(results) - ok)) if v}
        times = [statistics.median(r.seconds for r in each) for each in solves]
        row.seconds, row.ms_per_instance = sum(times), 1e3 * statistics.median(times)
        row.instance_ok = [r.ok for r in results]
    except Exception as exc:
        row.error = f"{type(exc).__name__}: {exc}"
    return row


def relative_difference(row: Row, ipopt: Row) -> Optional[float]:
    """Max over the instances IPOPT solved (``ok``) of ``|J − J_ipopt| / |J_ipopt|``; None if none compares."""
    if row.error or ipopt.error:
        return None
    pairs = [(j, ji) for j, ji, good in zip(row.costs, ipopt.costs, ipopt.instance_ok) if good]
    diffs = [abs(j - ji) / max(abs(ji), 1e-300) for j, ji in pairs]
    # a NaN cost must show as a failure, not vanish inside max()
    return max((d if np.isfinite(d) else float("inf") for d in diffs), default=None)
