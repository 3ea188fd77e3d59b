"""Where the time of a solve goes: cumulative profile times of the solver's parts.

A method's parts (:func:`parts_of`) are disjoint (none calls another), so their shares and "other" add up to the
whole. ALTRO and AL-iLQR are split by :data:`PARTS`; iLQR by those of its parts it has; the other methods by their
expansion and the Riccati core that every method shares. The split is taken from a separate, profiled run: cProfile
slows Python-heavy code, so its total is not a timing to quote.
"""

from __future__ import annotations

import cProfile
import pstats
import time
import warnings
from typing import Callable

#: label: (file under torchtraj/, function name)
PARTS = {
    "expansion (torch.func derivatives)": ("solvers/altro/augmented_lagrangian.py", "expand"),
    "line search (batched rollouts)": ("iterations/ilqr.py", "_line_search"),
    "Riccati factorisation": ("riccati/factorization.py", "factorize"),
    "Riccati solve": ("riccati/factor.py", "solve"),
    "initial rollout": ("core/batching.py", "rollout"),
    "multiplier updates": ("solvers/altro/augmented_lagrangian.py", "updated_duals"),
    "projection": ("solvers/altro/projection.py", "project"),
}


#: each method's expansion (its model at an iterate), where it is not ALTRO's; none calls the Riccati core. A method
#: without a line here is split by the Riccati core alone.
EXPANSIONS = {
    "ilqr": ("iterations/ilqr.py", "expand"),
    "ipm": ("solvers/ipm/expansion.py", "expand"),
    "eilqr": ("solvers/eilqr/model.py", "expand"),
    "hm-ilqr": ("solvers/hm_ilqr/objective.py", "expand"),
}

#: the labels of :data:`PARTS` that iLQR has (ALTRO's augmented Lagrangian and projection it has not)
ILQR_PARTS = ("line search (batched rollouts)", "Riccati factorisation", "Riccati solve", "initial rollout")

#: the same for compiled kernels (``ILQROptions.compile``), whose insides cProfile cannot see
COMPILED_PARTS = {
    "iterations (compiled: expansion, Riccati, line search)": ("iterations/ilqr.py", "_iteration"),
    "AL violation and dual update": ("solvers/altro/stages.py", "_measures"),
    "initial rollout": ("core/batching.py", "rollout"),
    "initial AL objective": ("solvers/altro/augmented_lagrangian.py", "value"),
    "initial AL violation": ("solvers/altro/augmented_lagrangian.py", "violation"),
    "MPC multiplier update": ("solvers/altro/augmented_lagrangian.py", "updated_duals"),
    "final cost and violation": ("kkt/merit.py", "cost_and_violation"),
}


def parts_of(method: str, compiled: bool = False) -> dict:
    """The parts that split ``method``'s time: :data:`PARTS` for ALTRO and AL-iLQR (:data:`COMPILED_PARTS` with
    compiled kernels); for the others, eager, their expansion (:data:`EXPANSIONS`, where it has a line) and the
    Riccati core (iLQR also its line search and initial rollout), and compiled none: their kernels hold those parts,
    and cProfile cannot see into them."""
    if method in ("altro", "al-ilqr"):
        return COMPILED_PARTS if compiled else PARTS
    if compiled:
        return {}
    expansion = {"expansion (torch.func derivatives)": EXPANSIONS[method]} if method in EXPANSIONS else {}
    riccati = ILQR_PARTS if method == "ilqr" else ("Riccati factorisation", "Riccati solve")
    return {**expansion, **{label: PARTS[label] for label in riccati}}


def cumulative(stats: dict, file: str, name: str) -> float:
    """Cumulative seconds of ``torchtraj/<file>:<name>`` in ``pstats.Stats(...).stats``."""
    return sum(v[3] for k, v in stats.items() if k[0].endswith("torchtraj/" + file) and k[2] == name)


def split(run: Callable[[], object], parts: dict = PARTS) -> tuple[float, dict]:
    """Run ``run()`` under cProfile; return its profiled seconds and the share of each of ``parts``
    (:data:`PARTS` or :data:`COMPILED_PARTS`; "other" is the rest: Python bookkeeping, masks, host syncs)."""
    profiler = cProfile.Profile()
    tick = time.perf_counter()
    profiler.enable()
    run()
    profiler.disable()
    total = time.perf_counter() - tick
    stats = pstats.Stats(profiler).stats
    seconds = {label: cumulative(stats, file, name) for label, (file, name) in parts.items()}
    seconds["other"] = total - sum(seconds.values())
    return total, {k: v / total for k, v in seconds.items()}


def quiet_inductor() -> None:
    """Silence the deprecation warning torch 2.13's inductor raises from its own lowering code (not ours to fix),
    which would otherwise interleave with the tables of a compiled run."""
    warnings.filterwarnings("ignore", message=r"`torch\._prims_common\.check` is deprecated")


def format_split(parts: dict) -> str:
    return ", ".join(f"{label} {100 * share:.0f}%" for label, share in parts.items())
