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
    if row.compiling_seconds == row.compiling_seconds:  # not NaN: compiled kernels
        status += f"; untimed compiling run {row.compiling_seconds:.1f} s"
    return _line(lead + [
        str(row.instances), f"{row.iterations_median:g}/{row.iterations_max}", cost,
        _num(row.max_violation, ".1e"), _num(row.seconds, ".3f"), _num(row.ms_per_instance, ".3f"),
        _num(row.vs_ipopt, ".1e"), status,
    ])


def legend() -> str:
    return ("iters: median/max over instances; cost: B = 1 the cost, else the median; n: instances solved "
            "(references: min(B, --reference-instances));\nms/inst: torchtraj total / B, references median "
            "solve call; vs IPOPT: max |J - J_ipopt| / |J_ipopt| over the instances IPOPT solved.")
