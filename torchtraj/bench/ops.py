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

Then the horizon sweep on the first problem (``pendulum`` by default; :mod:`~torchtraj.bench.ops_sweep`): the
same problem at N = 25, 50, 100, 200 (``--ops-horizons``; the dynamics' time step kept, the control guess resampled,
:func:`with_horizon`), each solve capped at the first ``--ops-iterations`` iterations (the method's
:meth:`~torchtraj.solvers.base.Solver.step_options`: a full solve at N = 200 under the counter takes minutes), its
calls per iteration, and the least-squares slope of calls per iteration over N (:func:`slope`): the calls each
added stage costs an iteration. A capped solve's calls per iteration include the solve's setup (and ALTRO's
projection stage) spread over those few iterations, so they read higher than a full solve's. So the sweep also
reports past the setup (:func:`past_setup`): the calls of iterations ``k+1`` to ``2k`` together, and each of those
iterations alone, with the slope of the cheapest at each horizon (why: :mod:`~torchtraj.bench.ops_sweep`).

Last, the MPC row (:func:`count_mpc`): for each method that handles constraints, the calls per control step of
the pendulum environment's warm-started controller (N = 30, 3 iterations a step, B = 1) over 10 steps of its
swing-up, after 5 uncounted ones.

A solve under the counter runs about four times slower than without it (the mode's Python call per operator).
"""

from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from .. import solvers
from ..core.problem import Problem
from ..core.recorded import TRACE_AT, forget
from ..core.status import Status
from ..solve import solve
from .runs import state_guess, with_record

DEFAULT_PROBLEMS = ("pendulum", "cartpole", "car_3obs")
DEFAULT_HORIZONS = (25, 50, 100, 200)
#: Iterations counted per solve of the horizon sweep.
SWEEP_ITERATIONS = 5
#: Operators listed per solve in the JSON report (``top_ops``).
TOP_OPS = 10
#: The MPC row: the pendulum environment's controller over this horizon, with this many iterations a step,
#: counted over this many steps.
MPC_HORIZON, MPC_ITERATIONS, MPC_STEPS = 30, 3, 10
#: Uncounted control steps before the counted ones (:func:`count_mpc`): as many as a recorded kernel's calls before
#: its trace, so that a kernel a step calls once is traced before the count and the counted steps are the
#: controller's from then on (with 5, the count of a one-iteration step held the last eager calls of a kernel called
#: once a step).
MPC_WARMUP = TRACE_AT


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
