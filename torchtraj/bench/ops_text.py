"""The text tables of ``python -m torchtraj.bench --ops`` (:mod:`torchtraj.bench.ops`): one line per counted
solve, one per method of a horizon sweep (rows: :class:`~torchtraj.bench.ops.Count`), and with ``--compile`` one
per method (:class:`~torchtraj.bench.compiled_ops.CompiledCount`)."""

from __future__ import annotations

from typing import Optional, Sequence


def _line(cells, widths, right) -> str:
    return "  ".join(c.rjust(w) if r else c.ljust(w) for c, w, r in zip(cells, widths, right)).rstrip()


def _num(value: Optional[float], fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


SOLVE_COLUMNS = (("problem", 22, False), ("method", 7, False), ("N", 4, True), ("iters", 6, True),
                 ("calls/solve", 12, True), ("calls/iter", 11, True), ("status", 0, False))
_WIDTHS, _RIGHT = [w for _, w, _ in SOLVE_COLUMNS], [r for _, _, r in SOLVE_COLUMNS]


def solve_header() -> str:
    titles = _line([t for t, _, _ in SOLVE_COLUMNS], _WIDTHS, _RIGHT)
    return titles + "\n" + "-" * len(titles)


def format_count(row: Count) -> str:
    lead = [row.problem, row.method, str(row.horizon)]
    if row.error:
        return _line(lead, _WIDTHS, _RIGHT) + "  ERROR " + row.error.splitlines()[0]
    cells = [str(row.iterations), str(row.calls), _num(row.calls_per_iteration, ".0f"), row.status]
    return _line(lead + cells, _WIDTHS, _RIGHT)


def format_sweep(method: str, rows: Sequence[Count], fitted: Optional[float], horizons: Sequence[int]) -> str:
    """One line of the horizon table: calls per iteration at each horizon (``-`` where ``rows`` has none: no
    iteration counted there), then the slope."""
    by_n = {r.horizon: r for r in rows}
    cells = [method]
    for n in horizons:
        r = by_n.get(n)
        cells.append("-" if r is None else "ERROR" if r.error else _num(r.calls_per_iteration, ".0f"))
    cells.append(_num(fitted, ".1f"))
    return _line(cells, _sweep_widths(horizons), [False] + [True] * (len(horizons) + 1))


def _sweep_widths(horizons: Sequence[int]) -> list:
    return [7] + [max(8, len(f"N={n}")) for n in horizons] + [11]


def sweep_header(horizons: Sequence[int]) -> str:
    titles = _line(["method"] + [f"N={n}" for n in horizons] + ["calls/stage"], _sweep_widths(horizons),
                   [False] + [True] * (len(horizons) + 1))
    return titles + "\n" + "-" * len(titles)


COMPILED_COLUMNS = (("method", 7, False), ("iters", 7, True), ("eager: mode", 11, True), ("profiler", 8, True),
                    ("compiled: profiler", 18, True), ("kernels", 7, True), ("compile s", 9, True),
                    ("eager s", 7, True), ("compiled s", 10, True), ("status", 0, False))
_COMPILED_WIDTHS, _COMPILED_RIGHT = [w for _, w, _ in COMPILED_COLUMNS], [r for _, _, r in COMPILED_COLUMNS]


def compiled_header() -> str:
    return _line([t for t, _, _ in COMPILED_COLUMNS], _COMPILED_WIDTHS, _COMPILED_RIGHT)


def format_compiled(row: CompiledCount) -> str:
    """One method's line of ``--ops --compile``: iterations (eager/compiled where they differ), calls per iteration,
    compiled calls per iteration, seconds, status."""
    if row.error:
        return _line([row.method], _COMPILED_WIDTHS, _COMPILED_RIGHT) + "  ERROR " + row.error.splitlines()[0]
    iterations = str(row.iterations) if row.iterations == row.compiled_iterations else \
        f"{row.iterations}/{row.compiled_iterations}"
    cells = [row.method, iterations, f"{row.eager_mode_calls:.0f}", _num(row.eager_calls, ".0f"),
             f"{row.compiled_calls:.0f}", f"{row.kernels:.1f}", f"{row.compile_seconds:.1f}",
             f"{row.eager_seconds:.3f}", f"{row.compiled_seconds:.3f}", row.status]
    return _line(cells, _COMPILED_WIDTHS, _COMPILED_RIGHT)


def compiled_sweep_header(horizons: Sequence[int]) -> str:
    titles = _line(["method"] + [f"N={n}" for n in horizons] + ["calls/stage", "compile s"],
                   _sweep_widths(horizons) + [24], [False] + [True] * (len(horizons) + 1) + [False])
    return titles + "\n" + "-" * len(titles)


def format_compiled_sweep(method: str, rows: Sequence[CompiledCount], fitted: Optional[float],
                          horizons: Sequence[int]) -> str:
    """One line of the compiled horizon table: the compiled solve's calls per iteration past its setup at each
    horizon (``-`` where none was counted), their slope over N, and each horizon's compile seconds."""
    by_n = {r.horizon: r for r in rows}
    cells = [method] + ["-" if by_n.get(n) is None else _num(by_n[n].past_setup_calls, ".0f") for n in horizons]
    seconds = " / ".join("-" if by_n.get(n) is None else _num(by_n[n].compile_seconds, ".0f") for n in horizons)
    return _line(cells + [_num(fitted, ".1f"), seconds], _sweep_widths(horizons) + [24],
                 [False] + [True] * (len(horizons) + 1) + [False])
