"""``python -m torchtraj.bench --defaults``: each method with its default options on the problem set, against IPOPT.

The question it answers is what a user gets from ``tt.solve(problems.get(name), x0, method=m)`` and nothing else:
the status (``CONVERGED`` only at a KKT point, :mod:`torchtraj.kkt.certificate`), and whether that point is IPOPT's
optimum from the same start. Where the costs differ by more than ``1e-6`` relative, IPOPT is started at
torchtraj's point (warm start: small barrier parameter, no push off the bounds); if it stays there (same cost to
``1e-6``), the point is another local optimum that IPOPT confirms as a KKT point (``kept``), else it is ``off``.

Each row: one problem, one method, no ``X0`` (the problem's own guesses); ``B = 1`` from the problem's ``x0``, and
with ``--batch B``
``sample_x0(name, B, seed)`` in one batch, its first ``--reference-instances`` compared with IPOPT instance by
instance.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from .. import problems, solvers
from ..core.status import Status
from ..solve import solve

#: Relative cost agreement that counts as the same optimum.
SAME = 1e-6


@dataclass
class DefaultsRow:
    problem: str
    method: str
    batch: int
    converged: int = 0
    optimum: int = 0  # converged at IPOPT's optimum from the same start
    kept: int = 0  # converged at another point that IPOPT warm-started keeps
    compared: int = 0
    statuses: dict = field(default_factory=dict)
    iterations: str = ""
    worst_relative: float = float("nan")
    violation: float = float("nan")
    stationarity: float = float("nan")
    seconds: float = float("nan")
    note: str = ""


def _verdict(reference, x0, X, U, cost: float, ipopt_cost: float) -> str:
    if abs(cost - ipopt_cost) <= SAME * max(1.0, abs(ipopt_cost)):
        return "optimum"
    warm = reference.solve(x0, U0=U, X0=X, warm_start=True)
    return "kept" if warm.ok and abs(warm.cost - cost) <= SAME * max(1.0, abs(cost)) else "off"


def run_row(name: str, method: str, batch: int, seed: int, compare: int, reference) -> DefaultsRow:
    problem = problems.get(name)
    x0 = problem.x0.unsqueeze(0) if batch == 1 else problems.sample_x0(name, batch, seed=seed)
    row = DefaultsRow(name, method, batch)
    start = time.perf_counter()
    sol = solve(problem, x0, method=method)
    row.seconds = time.perf_counter() - start
    row.statuses = Status.counts(sol.status)
    converged = sol.status == Status.CONVERGED
    row.converged = int(converged.sum())
    row.iterations = f"{int(sol.iterations.median())}/{int(sol.iterations.max())}"
    row.violation = float(sol.max_violation[converged].max()) if row.converged else float("nan")
    row.stationarity = float(sol.kkt["stationarity"][converged].max()) if row.converged else float("nan")
    if reference is None:
        row.note = "no IPOPT (casadi missing)"
        return row
    worst = 0.0
    for i in range(min(batch, compare)):
        if not bool(converged[i]):
            continue
        x = x0[i].numpy()
        ipopt = reference.solve(x)
        cost = float(sol.cost[i])
        row.compared += 1
        worst = max(worst, abs(cost - ipopt.cost) / max(1.0, abs(ipopt.cost)))
        verdict = _verdict(reference, x, sol.X[i].numpy(), sol.U[i].numpy(), cost, ipopt.cost)
        row.optimum += verdict == "optimum"
        row.kept += verdict == "kept"
    row.worst_relative = worst
    return row


def run(methods: list, names: list, batches: list, seed: int, compare: int, say: Callable[[str], None]) -> list:
    try:
        from .reference import ReferenceSolver
        references = {name: ReferenceSolver(name, "ipopt") for name in names}
    except ImportError:
        references = {name: None for name in names}
    say(f"torchtraj bench --defaults: tt.solve(problems.get(name), x0, method=m), default options, float64, "
        f"torch {torch.__version__}")
    say("converged: CONVERGED (a KKT point to the certificate's tolerances); at IPOPT / kept: of the converged "
        f"instances compared with IPOPT from the same start, at its optimum (cost within {SAME:g} relative) / at "
        "another point that IPOPT warm-started keeps; off: neither")
    header = (f"{'problem':22s} {'method':8s} {'B':>4s} {'converged':>10s} {'at IPOPT':>9s} {'kept':>5s} {'off':>4s} "
              f"{'iters':>8s} {'worst rel':>9s} {'max viol':>9s} {'max stat':>9s} {'s':>7s}  statuses")
    say(header)
    say("-" * len(header))
    rows = []
    for name in names:
        for method in methods:
            solver = solvers.get(method)
            if problems.get(name).has_constraints and not solver.handles_constraints:
                continue
            for batch in batches:
                row = run_row(name, method, batch, seed, compare, references[name])
                rows.append(row)
                off = row.compared - row.optimum - row.kept
                say(f"{name:22s} {method:8s} {batch:4d} {row.converged:>5d}/{batch:<4d} {row.optimum:>9d} "
                    f"{row.kept:>5d} {off:>4d} {row.iterations:>8s} {row.worst_relative:9.1e} {row.violation:9.1e} "
                    f"{row.stationarity:9.1e} {row.seconds:7.1f}  {row.statuses} {row.note}")
    return rows
