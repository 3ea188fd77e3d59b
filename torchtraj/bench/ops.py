r"""``python -m torchtraj.bench --ops``: eager torch operator calls per solve and per solver iteration.

The project's performance currency is the number of operator calls an iteration makes: it does not depend on the
machine or on its load, unlike a timing, and the solvers spend most of their time dispatching many tiny calls
(Python loops over stages), so fewer calls is faster.

What is counted
---------------
:class:`OperatorCounter` is a :class:`~torch.utils._python_dispatch.TorchDispatchMode`; inside its ``with`` block
every call that reaches the dispatcher's Python mode key counts once::

    with OperatorCounter() as ops:
        tt.solve(problem)
    ops.total, ops.by_name.most_common(5)

- ATen operators, after the decomposition of the composite ones (``torch.matmul`` of two matrices counts as one
  ``aten.mm``, of a stack of matrices by a matrix as ``aten.view``, ``aten.mm``, ``aten._unsafe_view``): views,
  in-place updates, copies, factories (``torch.zeros``), ``Tensor.item()`` (``aten._local_scalar_dense``) and
  autograd's backward calls all count;
- inside ``torch.func`` transforms, the calls left after the transforms' rules have run: an operator under
  ``vmap`` counts once per batched call, however large the batch, and ``jacrev`` counts the calls of its forward
  and of its vector-Jacobian products (all of them batched under an enclosing ``vmap``);
- not counted: Python work between the calls, and anything that runs inside a kernel. Solves are counted eager:
  a kernel compiled by ``torch.compile`` (``compile=True`` options, off by default) runs eager under the mode;
  :mod:`~torchtraj.bench.compiled_ops` (``--ops --compile``) counts the solves with compiled kernels by the
  profiler instead.

The report
----------
For each method (every registered one, unless ``--method``) on each problem (``pendulum``, ``cartpole``,
``car_3obs``, unless ``--problems``): one solve at B = 1 from the problem's own ``x0`` with the method's default
options, its operator calls, ``Solution.iterations``, calls per iteration and status. A method that ignores constraints
is skipped on a constrained problem, with the reason (:func:`~torchtraj.bench.runs.skip_reason`).

Then the horizon sweep on the first problem (``pendulum`` by default): the same problem at N = 25, 50, 100, 200
(``--ops-horizons``; the dynamics' time step kept, the control guess resampled, :func:`with_horizon`), each
solve capped at the first ``--ops-iterations`` iterations (the method's
:meth:`~torchtraj.solvers.base.Solver.step_options`: a full solve at N = 200 under the counter takes minutes), its
calls per iteration, and the least-squares slope of calls per iteration over N (:func:`slope`): the calls each
added stage costs an iteration. A capped solve's calls per iteration include the solve's setup (and ALTRO's
projection stage) spread over those few iterations, so they read higher than a full solve's. So the sweep counts the
same solves capped at twice as many iterations too, and reports past the setup (:func:`past_setup`): the calls of
iterations ``k+1`` to ``2k`` alone (the longer solve's calls less the shorter's, over the iterations between them),
and their slope over N, the calls an added stage costs an iteration once the solve has started.

Last, the MPC row (:func:`count_mpc`): for each method that handles constraints, the calls per control step of
the pendulum environment's warm-started controller (N = 30, 3 iterations a step, B = 1) over 10 steps of its
swing-up, after 5 uncounted ones.

A solve under the counter runs about four times slower than without it (the mode's Python call per operator).
"""

from __future__ import annotations

import collections
import dataclasses
import datetime
import platform
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from .. import problems as problem_set
from .. import solvers
from ..core.problem import Problem
from ..core.recorded import forget
from ..core.status import Status
from ..solve import solve
from .ops_text import format_count, format_sweep, solve_header, sweep_header
from .runs import skip_reason, state_guess, with_record

DEFAULT_PROBLEMS = ("pendulum", "cartpole", "car_3obs")
DEFAULT_HORIZONS = (25, 50, 100, 200)
#: Iterations counted per solve of the horizon sweep.
SWEEP_ITERATIONS = 5
#: Operators listed per solve in the JSON report (``top_ops``).
TOP_OPS = 10
#: The MPC row: the pendulum environment's controller over this horizon, with this many iterations a step,
#: counted over this many steps.
MPC_HORIZON, MPC_ITERATIONS, MPC_STEPS = 30, 3, 10
#: Uncounted control steps before the counted ones (:func:`count_mpc`).
MPC_WARMUP = 5


class OperatorCounter(TorchDispatchMode):
    """Counts the operator calls made inside its ``with`` block (module docstring: what is counted).

    Attributes:
        total: number of calls.
        by_name: ``collections.Counter`` of calls per operator overload name (``"aten.add.Tensor"``).
    """

    def __init__(self) -> None:
        super().__init__()
        # keyed by the OpOverload itself: naming it on every call would cost more than the call
        self._calls: dict = {}

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self._calls[func] = self._calls.get(func, 0) + 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self._calls.values())

    @property
    def by_name(self) -> collections.Counter:
        return collections.Counter({str(func): n for func, n in self._calls.items()})


@dataclass
class Count:
    """The operator calls of one counted solve; ``iteration_cap`` None for a full solve with default options."""

    problem: str
    method: str
    horizon: int
    iteration_cap: Optional[int] = None
    calls: Optional[int] = None
    iterations: Optional[int] = None
    #: ``Status`` name of the solve (B = 1): the calls of a solve that stopped short are those of its iterations.
    status: Optional[str] = None
    top_ops: dict = dataclasses.field(default_factory=dict)
    error: Optional[str] = None

    @property
    def calls_per_iteration(self) -> Optional[float]:
        if self.calls is None or not self.iterations:
            return None
        return self.calls / self.iterations

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "calls_per_iteration": self.calls_per_iteration}


def count_solve(problem: Problem, method, options=None, iteration_cap: Optional[int] = None,
                cold: bool = True) -> Count:
    """Count the calls of ``tt.solve(problem, method=method, options=options)`` at B = 1 (the problem's x0 and
    state guess, :func:`~torchtraj.bench.runs.state_guess`); ``cold``: as a new process's first solve, without the
    records and call counts of earlier solves (:func:`~torchtraj.core.recorded.forget`), so that a count does not
    depend on what ran before it. Never raises: an exception is kept in ``error``."""
    solver = solvers.get(method)
    if cold:
        forget()
    row = Count(problem.name, solver.name, problem.horizon, iteration_cap)
    try:
        with OperatorCounter() as ops:
            sol = solve(problem, None, solver, X0=state_guess(solver, problem), options=options)
        row.calls, row.iterations = ops.total, int(sol.iterations.max())
        row.status = ", ".join(Status.describe(sol.status))
        row.top_ops = dict(ops.by_name.most_common(TOP_OPS))
    except Exception as exc:  # one failing solve must not stop the report
        row.error = f"{type(exc).__name__}: {exc}"
    return row


def count_recorded(problem: Problem, method) -> Count:
    """:func:`count_solve` of ``method``'s default options with recorded kernels (``record=True``,
    :mod:`torchtraj.core.recorded`), after one uncounted solve of the same problem that records them."""
    solver = solvers.get(method)
    options = with_record(solver, solver.default_options())
    forget()
    try:
        solve(problem, None, solver, X0=state_guess(solver, problem), options=options)
    except Exception:  # the counted solve fails the same way, and reports it
        pass
    return count_solve(problem, solver, options, cold=False)


@dataclass
class StepCount:
    """The operator calls of ``steps`` control steps of :class:`~torchtraj.MPC` with ``method`` (B = 1)."""

    method: str
    horizon: int
    iterations: int
    steps: int
    calls: Optional[int] = None
    error: Optional[str] = None

    @property
    def calls_per_step(self) -> Optional[float]:
        return None if self.calls is None else self.calls / self.steps

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "calls_per_step": self.calls_per_step}


def count_mpc(method, horizon: int = MPC_HORIZON, iterations: int = MPC_ITERATIONS, steps: int = MPC_STEPS,
              seed: int = 0) -> StepCount:
    """Count ``steps`` control steps of ``tt.MPC(env.problem(horizon), method, iterations)`` on the pendulum
    environment from its seeded reset (swing-up), after :data:`MPC_WARMUP` uncounted steps (the first solve is cold,
    ``torch.func`` traces on first use, and the steps' recorded kernels trace each signature at its
    :data:`~torchtraj.core.recorded.TRACE_AT`-th call). Never raises: an exception is kept in ``error``."""
    import gymnasium as gym

    from ..control.mpc import MPC

    solver = solvers.get(method)
    row = StepCount(solver.name, horizon, iterations, steps)
    try:
        env = gym.make("torchtraj/Pendulum-v0").unwrapped
        policy = MPC(env.problem(horizon=horizon), solver, iterations)
        forget()  # the warm-up steps record what the steps replay, whatever ran before
        obs, _ = env.reset(seed=seed)
        for _ in range(MPC_WARMUP):
            obs, *_ = env.step(policy(obs))
        with OperatorCounter() as ops:
            for _ in range(steps):
                action = policy(obs)
                obs, *_ = env.step(action)
        row.calls = ops.total
    except Exception as exc:  # one failing controller must not stop the report
        row.error = f"{type(exc).__name__}: {exc}"
    return row


def with_horizon(problem: Problem, horizon: int) -> Problem:
    """``problem`` with ``horizon`` intervals: the same functions (so the same time step), the control guess
    ``(N, nu)`` and any state guess ``(N+1, nx)`` resampled to the new length (nearest knot: a constant guess stays
    the same constant)."""
    def resample(guess: Optional[torch.Tensor], length: int) -> Optional[torch.Tensor]:
        if guess is None:
            return None
        index = torch.linspace(0, guess.shape[0] - 1, length).round().long()
        return guess[index]

    return problem.replace(horizon=horizon, u_init=resample(problem.u_init, horizon),
                           X_init=resample(problem.X_init, horizon + 1))


def slope(horizons: Sequence[float], values: Sequence[float]) -> Optional[float]:
    """Least-squares slope of ``values`` over ``horizons`` (None with fewer than two distinct horizons)."""
    n = len(horizons)
    if n != len(values):
        raise ValueError(f"slope: {n} horizons but {len(values)} values")
    mean_n, mean_v = sum(horizons) / max(n, 1), sum(values) / max(n, 1)
    spread = sum((h - mean_n) ** 2 for h in horizons)
    if n < 2 or spread == 0:
        return None
    return sum((h - mean_n) * (v - mean_v) for h, v in zip(horizons, values)) / spread


def past_setup(short: Count, long: Count) -> Count:
    """The calls of the iterations that ``long`` made past ``short`` (the same solve capped at fewer iterations):
    ``long``'s calls and iterations less ``short``'s (none where ``long`` made no more iterations)."""
    row = Count(long.problem, long.method, long.horizon, long.iteration_cap, status=long.status,
                error=long.error or short.error)
    if row.error is None and long.iterations is not None and short.iterations is not None:
        row.calls, row.iterations = long.calls - short.calls, long.iterations - short.iterations
    return row


# ---------------------------------------------------------------------------------------------- report
def run(methods: Sequence[str], names: Sequence[str], horizons: Sequence[int], iterations: int,
        say: Callable[..., None], dtype: torch.dtype = torch.float64, device=None, mpc_steps: int = MPC_STEPS,
        record: bool = False) -> dict:
    """Count, print the two tables as their rows come (``say``) and return the report as JSON-able data:
    ``header``, ``skipped`` (``[{problem, method, reason}]``), ``solves`` (:meth:`Count.to_json` each) and
    ``horizons`` (``problem``, ``iterations`` cap, ``rows``, ``slopes`` per method) and ``mpc``
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
    say()
    over = (f"over the first {iterations} iterations of each solve (the method's step_options), so its setup is "
            f"spread over those" if iterations else "over whole solves with the method's default options")
    say(f"horizon sweep on {sweep_name} (the same time step, the control guess resampled): calls per iteration "
        f"{over}; calls/stage: the least-squares slope over N")
    say(sweep_header(horizons))
    sweep, slopes, swept = [], {}, []
    for m in methods:
        if skip_reason(m, built[sweep_name]):
            continue
        solver = solvers.get(m)
        rows = _sweep_rows(solver, sweep_name, horizons, iterations, dtype, device)
        slopes[solver.name] = _say_sweep(solver.name, rows, horizons, say)
        sweep += rows
        swept.append((solver, rows))
    later, later_slopes = [], {}
    if iterations:
        say()
        say(f"past the setup on {sweep_name}: calls per iteration of iterations {iterations + 1} to "
            f"{2 * iterations} alone (the solve capped at {2 * iterations} less the one capped at {iterations}); "
            f"calls/stage: the least-squares slope over N")
        say(sweep_header(horizons))
        for solver, rows in swept:
            longer = _sweep_rows(solver, sweep_name, horizons, 2 * iterations, dtype, device)
            differences = [past_setup(short, long) for short, long in zip(rows, longer)]
            later_slopes[solver.name] = _say_sweep(solver.name, differences, horizons, say)
            later += differences
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
        "horizons": {"problem": sweep_name, "iterations": iterations, "rows": [r.to_json() for r in sweep],
                     "slopes": slopes,
                     "past_setup": {"rows": [r.to_json() for r in later], "slopes": later_slopes}},
        "mpc": [r.to_json() for r in steps],
    }


def _sweep_rows(solver, name: str, horizons: Sequence[int], iterations: int, dtype, device) -> list:
    """The counts of ``solver`` on problem ``name`` at each horizon, capped at ``iterations`` (0: whole solves)."""
    options = solver.step_options(solver.default_options(), iterations) if iterations else None
    return [count_solve(with_horizon(problem_set.get(name, dtype=dtype, device=device), n), solver, options,
                        iteration_cap=iterations or None) for n in horizons]


def _say_sweep(method: str, rows: Sequence[Count], horizons: Sequence[int], say) -> Optional[float]:
    """Print one line of a horizon table (and the rows' errors); return its slope."""
    good = [r for r in rows if r.calls_per_iteration is not None]
    fitted = None if len(good) < len(rows) else slope([r.horizon for r in good],
                                                      [r.calls_per_iteration for r in good])
    say(format_sweep(method, rows, fitted, horizons))
    for r in rows:
        if r.error:
            say(f"  {method} N={r.horizon}: ERROR {r.error.splitlines()[0]}")
    return fitted


def failed(report: dict) -> bool:
    """Whether some counted solve or control step of ``report`` (:func:`run`) raised."""
    later = report["horizons"].get("past_setup", {}).get("rows", [])
    return any(r["error"] for r in report["solves"] + report["horizons"]["rows"] + later + report.get("mpc", []))
