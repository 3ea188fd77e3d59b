"""Time-penalised pendulum and parallel park (ALTRO §III-C) next to their fixed-time solutions."""

from __future__ import annotations

import time

from .. import models, problems
from ..core.status import Status
from ..solve import solve
from ..solvers.altro.options import ALTROOptions
from ..solvers.altro.projection import ProjectionOptions
from ..time_penalty import time_penalized

#: ``R_τ`` of eq. (34) for the demonstration problems. For the parallel park, ``R_τ = 1`` makes time dominate
#: its cost (0.054 at the fixed 3 s) and asks for a bang-bang manoeuvre along its state bounds, on which AL-iLQR
#: crawls (1e-5 cost per iteration after 600 iterations); ``R_τ = 0.01`` trades time against the original cost.
TIME_WEIGHTS = {"pendulum": 1.0, "parallel_park": 0.01}


def time_penalized_options(name: str):
    """Options with the paper's 1e-6 projection tolerance for time-penalised problems.

    The pendulum uses the problem set's accuracy (:func:`torchtraj.problems.altro_options`); the parallel park
    uses ALTRO's own tolerances: at the problem set's cost tolerance of 1e-8 each of its inner solves takes
    hundreds of iterations, and there is no reference optimum to match.
    """
    projection = ProjectionOptions(tolerance=1e-6)
    if name == "parallel_park":
        return ALTROOptions(projection_options=projection)
    return problems.altro_options(name, projection_options=projection)


def solve_time_penalized(name: str, method="altro", dtype=None, device=None):
    """``(transform, solution, seconds)`` of the time-penalised version of problem ``name``, solved by ``method``
    (a name of a method run by :class:`~torchtraj.ALTROOptions`)."""
    kwargs = {} if dtype is None else {"dtype": dtype}
    problem = problems.get(name, device=device, **kwargs)
    tp = time_penalized(problem, models.get(problems.spec(name).model).dynamics, time_weight=TIME_WEIGHTS[name])
    start = time.perf_counter()
    sol = solve(tp.problem, method=method, options=time_penalized_options(name))
    return tp, sol, time.perf_counter() - start


def report_time_penalized(method, dtype, device) -> list:
    """One line per problem: status, duration against the fixed horizon, cost, violation, iterations, time."""
    lines = []
    for name in TIME_WEIGHTS:
        try:
            tp, sol, seconds = solve_time_penalized(name, method, dtype, device)
            fixed = tp.original.dt * tp.original.N
            lines.append(
                f"time-penalised {name}: {Status(int(sol.status[0])).name.lower()}, duration "
                f"{float(tp.duration(sol.U)[0]):.4f} s vs fixed {fixed:.4f} s, cost {float(sol.cost[0]):.6g} "
                f"(R_tau={TIME_WEIGHTS[name]:g}), max violation {float(sol.max_violation[0]):.2e}, "
                f"{int(sol.iterations[0])} iterations, {seconds:.2f} s")
        except Exception as exc:  # reported, not fatal
            lines.append(f"time-penalised {name}: error {type(exc).__name__}: {exc}")
    return lines
