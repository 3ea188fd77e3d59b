"""Plain aligned text for benchmark rows: fixed-width columns, the status counts last (they vary in width)."""

from __future__ import annotations

import math
from typing import Optional

from .runs import Row

#: (title, width, right-aligned)
COLUMNS = (
    ("problem", 22, False), ("method", 7, False), ("B", 5, True), ("n", 4, True), ("iters", 8, True),
    ("cost", 17, True), ("max viol", 9, True), ("total s", 9, True), ("ms/inst", 9, True),
    ("vs IPOPT", 9, True), ("status", 0, False),
)


def _line(cells) -> str:
    parts = []
    for (_, width, right), text in zip(COLUMNS, cells):
        parts.append(text.rjust(width) if right else text.ljust(width))
    return "  ".join(parts).rstrip()


def header() -> str:
    titles = _line([title for title, _, _ in COLUMNS])
    return titles + "\n" + "-" * len(titles)


def _num(value: Optional[float], fmt: str) -> str:
    if value is None:
        return "-"
    return format(value, fmt) if math.isfinite(value) else str(value)


def format_row(row: Row) -> str:
    lead = [row.problem, row.method, str(row.batch)]
    if row.error:
        return _line(lead) + "  ERROR " + row.error.splitlines()[0]
    # B = 1: the cost itself to 10 significant digits; else the median over instances
    cost = _num(row.costs[0], ".10g") if row.instances == 1 else _num(row.cost_median, ".6g")
    status = ", ".join(f"{k} {v}" for k, v in row.status.items())
    return _line(lead + [
        str(row.instances), f"{row.iterations_median:g}/{row.iterations_max}", cost,
        _num(row.max_violation, ".1e"), _num(row.seconds, ".3f"), _num(row.ms_per_instance, ".3f"),
        _num(row.vs_ipopt, ".1e"), status,
    ])


def legend() -> str:
    return ("iters: median/max over instances; cost: B = 1 the cost, else the median; n: instances solved "
            "(references: min(B, --reference-instances));\nms/inst: torchtraj total / B, references median "
            "solve call; vs IPOPT: max |J - J_ipopt| / |J_ipopt| over the instances IPOPT solved.")


def throughput(name: str, rows: list, largest: int, references: tuple) -> str:
    """The line comparing torchtraj's time per instance at the batch size ``largest`` with FATROP's (``references``:
    the reference solvers' method names)."""
    ours = next((r for r in rows if r.batch == largest and r.method not in references), None)
    fatrop = next((r for r in rows if r.batch == largest and r.method == "fatrop"), None)
    if ours is None or ours.error:
        return f"throughput {name}: no torchtraj result at B={largest}"
    text = f"throughput {name}: {ours.method} {ours.ms_per_instance:.3f} ms/instance at B={largest}"
    if ours.repeat > 1:
        text += f" (the median of {ours.repeat} timed solves)"
    if ours.compile_seconds is not None:
        text += f" (compiled kernels; the untimed run before, which compiled them, took {ours.compile_seconds:.1f} s)"
    if ours.record_seconds is not None:
        text += f" (recorded kernels; the untimed runs before, which recorded them, took {ours.record_seconds:.1f} s)"
    if fatrop is None or fatrop.error:
        return text + "; no FATROP result to compare"
    ratio = ours.ms_per_instance / fatrop.ms_per_instance
    each = f", each the median of {fatrop.repeat} solves" if fatrop.repeat > 1 else ""
    return (text + f" vs FATROP {fatrop.ms_per_instance:.3f} ms/instance (median of {fatrop.instances}{each}); "
            f"ratio {ours.method}/FATROP = {ratio:.3g} ({'<' if ratio < 1 else '>='}1: "
            f"{ours.method} {'faster' if ratio < 1 else 'not faster'} per instance)")
