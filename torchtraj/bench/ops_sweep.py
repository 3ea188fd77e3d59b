"""The horizon sweep of ``python -m torchtraj.bench --ops``: the same problem at other horizons, and what an added
stage costs an iteration.

The problem keeps its time step and resamples its control guess (:func:`~torchtraj.bench.ops.with_horizon`); each
solve is counted cold at B = 1 (:func:`~torchtraj.bench.ops.count_solve`), capped by the method's
:meth:`~torchtraj.solvers.base.Solver.step_options`. Each table has a line per method, a column per horizon and the
least-squares slope of its figures over N (:func:`~torchtraj.bench.ops.slope`), the calls an added stage costs:

1. **the first k iterations** (``--ops-iterations k``): calls per iteration of the solve capped at ``k``, its setup
   spread over them (``k = 0``: whole solves with the default options, and no other table);
2. **past the setup**: iterations ``k+1`` to ``2k`` together, the solve capped at ``2k`` less the one capped at ``k``
   (:func:`~torchtraj.bench.ops.past_setup`);
3. **each iteration alone**: the solves capped at ``k, k+1, …, 2k``, each less the one capped one iteration
   earlier, so that every iteration from ``k+1`` to ``2k`` is counted on its own; the table gives the cheapest of
   them at each horizon, and every iteration's calls follow it.

Why the third table. The iterations a solve makes at one horizon are not those it makes at another: an iteration
of a Newton method factorises its system again where a regularisation or an inertia correction was too small, or
for a second-order correction, and its line search may take more trials, as its iterates decide. Averaged over
the same iteration numbers, iterations of several kinds are mixed, and the slope over N follows the path as much as
the stages: on the pendulum the interior point's iterations 6 to 10 factorised 10, 7 and 5 times at N = 25, 50 and
100, so their average grew by 2.9 calls a stage, less than one factorisation's share. The cheapest iteration at each
horizon is the one that did the least, typically one factorisation, one solve and one trial; the slope of the
cheapest is what an added stage costs such an iteration, and every other iteration costs more (the calls of each
are listed to show by how much). It measures one kind only where the solve made an iteration of that kind at every
horizon; where it made none at some horizon (every iteration there factorised again, say), the listed calls show the
jump, and the slope mixes kinds as the average does.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence

from .. import problems as problem_set
from .. import solvers
from .ops import Count, count_solve, past_setup, slope, with_horizon
from .ops_text import format_sweep, sweep_header
from .runs import skip_reason


def sweep_rows(solver, name: str, horizons: Sequence[int], iterations: int, dtype, device) -> list:
    """The counts of ``solver`` on problem ``name`` at each horizon, capped at ``iterations`` (0: whole solves)."""
    options = solver.step_options(solver.default_options(), iterations) if iterations else None
    return [count_solve(with_horizon(problem_set.get(name, dtype=dtype, device=device), n), solver, options,
                        iteration_cap=iterations or None) for n in horizons]


def each_iteration(capped: Sequence[Sequence[Count]]) -> list:
    """``capped[j][h]``, the solves at horizon ``h`` capped at ``k + j`` iterations, as the iterations alone:
    ``[h][j]`` the calls of iteration ``k + j + 1`` (the solve capped one iteration later less this one; ``iterations``
    0 where the solve had ended before it, an error where either solve raised)."""
    return [[past_setup(short[h], long[h]) for short, long in zip(capped, capped[1:])]
            for h in range(len(capped[0]))]


def cheapest(iterations: Sequence[Count]) -> Optional[Count]:
    """The iteration of fewest calls among ``iterations`` (each one iteration alone, :func:`each_iteration`); None
    where none was counted."""
    counted = [r for r in iterations if r.calls is not None and r.iterations == 1]
    return min(counted, key=lambda r: r.calls) if counted else None


def _say_sweep(method: str, rows: Sequence[Optional[Count]], horizons: Sequence[int], say) -> Optional[float]:
    """Print one line of a horizon table (and the rows' errors); return its slope."""
    good = [r for r in rows if r is not None and r.calls_per_iteration is not None]
    fitted = None if len(good) < len(rows) else slope([r.horizon for r in good],
                                                      [r.calls_per_iteration for r in good])
    say(format_sweep(method, [r for r in rows if r is not None], fitted, horizons))
    for r in rows:
        if r is not None and r.error:
            say(f"  {method} N={r.horizon}: ERROR {r.error.splitlines()[0]}")
    return fitted


def sweep(methods: Sequence[str], name: str, horizons: Sequence[int], iterations: int, say: Callable[..., None],
          dtype, device) -> dict:
    """Count and print the sweep's tables (module docstring) for the methods that take problem ``name``; return
    them as JSON-able data: ``rows`` and ``slopes`` of the first, ``past_setup`` and ``each_iteration`` (``rows``
    ``[method][h][j]``, ``cheapest`` rows, ``slopes``) with their ``rows`` and ``slopes`` (both empty for
    ``iterations = 0``)."""
    problem = problem_set.get(name, dtype=dtype, device=device)
    taken = [solvers.get(m) for m in methods if not skip_reason(m, problem)]
    say()
    over = (f"over the first {iterations} iterations of each solve (the method's step_options), so its setup is "
            f"spread over those" if iterations else "over whole solves with the method's default options")
    say(f"horizon sweep on {name} (the same time step, the control guess resampled): calls per iteration "
        f"{over}; calls/stage: the least-squares slope over N")
    say(sweep_header(horizons))
    first, slopes, capped = [], {}, {}
    for solver in taken:
        rows = sweep_rows(solver, name, horizons, iterations, dtype, device)
        slopes[solver.name] = _say_sweep(solver.name, rows, horizons, say)
        first += rows
        capped[solver.name] = [rows]
    report = {"rows": [r.to_json() for r in first], "slopes": slopes,
              "past_setup": {"rows": [], "slopes": {}},
              "each_iteration": {"rows": {}, "cheapest": [], "slopes": {}}}
    if not iterations:
        return report
    for solver in taken:  # the solves capped at k + 1, ..., 2k
        capped[solver.name] += [sweep_rows(solver, name, horizons, cap, dtype, device)
                                for cap in range(iterations + 1, 2 * iterations + 1)]
    say()
    say(f"past the setup on {name}: calls per iteration of iterations {iterations + 1} to {2 * iterations} together "
        f"(the solve capped at {2 * iterations} less the one capped at {iterations}); calls/stage: the "
        f"least-squares slope over N")
    say(sweep_header(horizons))
    later = report["past_setup"]
    for solver in taken:
        rows = [past_setup(short, long) for short, long in zip(capped[solver.name][0], capped[solver.name][-1])]
        later["slopes"][solver.name] = _say_sweep(solver.name, rows, horizons, say)
        later["rows"] += [r.to_json() for r in rows]
    say()
    say(f"each iteration alone on {name}: iterations {iterations + 1} to {2 * iterations}, each the solve capped "
        f"there less the one capped an iteration earlier; the cheapest at each N, and calls/stage: the "
        f"least-squares slope of the cheapest over N (every iteration's calls below)")
    say(sweep_header(horizons))
    alone = report["each_iteration"]
    for solver in taken:
        per_horizon = each_iteration(capped[solver.name])
        least = [cheapest(its) for its in per_horizon]
        alone["slopes"][solver.name] = _say_sweep(solver.name, least, horizons, say)
        for n, its in zip(horizons, per_horizon):
            say(f"  {solver.name} N={n}, iterations {iterations + 1} to {2 * iterations}: "
                + " ".join("-" if r.calls_per_iteration is None else f"{r.calls}" for r in its))
        alone["rows"][solver.name] = [[r.to_json() for r in its] for its in per_horizon]
        alone["cheapest"] += [None if r is None else r.to_json() for r in least]
    return report
