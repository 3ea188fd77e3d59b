"""``python -m torchtraj.bench --grad``: forward and backward times of differentiable solves.

Two problems, each on the same instances for every solver in the same run:

* ``linear_box`` (:mod:`~torchtraj.bench.grad_linear`): the protocol of the differentiable-MPC literature
  (Amos et al. 2018, §5.1), a random stable linear system with box-constrained controls, horizon 30,
  batches 16 / 64 / 256, run by torchtraj and by mpc.pytorch (the optional extra ``mpc``);
* the pendulum of the benchmark problem set with an active state constraint ``|ω| ≤ ω_max``
  (:mod:`~torchtraj.bench.grad_pendulum`), which mpc.pytorch cannot express, its gradients checked
  instance by instance.

Each timed solve comes after an untimed one of the same solver on the same instances (the steady state of
repeated solves, as in a training loop: the first solve at a new batch size also pays for its new buffers,
about 0.2 s more for torchtraj at B = 256 on one CPU core). A row reports:

* forward: wall time of the solve;
* backward: wall time of ``loss.backward()``;
* grad vs FD: the largest relative difference between the gradient along a random direction and the central
  difference of re-solves, ``ε = 1e-6``;
* vs torchtraj: ``max |U − U_torchtraj|`` (both solve the same QP).

This module holds the rows, their report and :func:`run`, and gives the names of the two problems' modules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional

import torch

from .. import problems
from ..solve import default_method as solve_default_method
from ..solve import solve
from .grad_linear import (
    FD_STEP,
    HORIZON,
    NU,
    NX,
    U_MAX,
    _instances,  # noqa: F401  (the tests draw the protocol's instances through this module)
    _timed,
    linear_system,
    lq_problem,
    mpc_available,
    mpc_pytorch_lq,
    torchtraj_lq,
)
from .grad_pendulum import (
    ByInstance,
    InstanceFD,
    Resolved,
    constrained_pendulum,
    directional,
    fd_by_instance,
    not_minimal,
    resolved,
    solve_by_instance,
    torchtraj_pendulum,
)
from .runs import compiled as is_compiled

__all__ = [
    "FD_STEP", "HORIZON", "NU", "NX", "U_MAX", "linear_system", "lq_problem", "mpc_available", "mpc_pytorch_lq",
    "torchtraj_lq", "ByInstance", "InstanceFD", "Resolved", "constrained_pendulum", "directional", "fd_by_instance",
    "not_minimal", "resolved", "solve_by_instance", "torchtraj_pendulum", "GradRow", "COLUMNS", "format_row",
    "header", "default_method", "run",
]


@dataclass
class GradRow:
    """One line of the report: times in seconds, ``grad vs FD`` and ``vs torchtraj`` NaN where not measured."""

    problem: str
    solver: str
    batch: int
    forward_s: float = float("nan")
    backward_s: float = float("nan")
    grad_vs_fd: float = float("nan")
    vs_torchtraj: float = float("nan")
    converged: str = ""
    note: str = ""

    @property
    def total_s(self) -> float:
        return self.forward_s + self.backward_s


# --------------------------------------------------------------------------------- the report
COLUMNS = (("problem", 18, False), ("solver", 23, False), ("B", 5, True), ("forward s", 10, True),
           ("backward s", 11, True), ("total s", 9, True), ("grad vs FD", 11, True),
           ("|U - U_tt|", 11, True), ("converged", 10, True), ("note", 0, False))


def _fmt(value: float, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def format_row(row: GradRow) -> str:
    cells = [row.problem, row.solver, str(row.batch), _fmt(row.forward_s, ".3f"), _fmt(row.backward_s, ".3f"),
             _fmt(row.total_s, ".3f"), _fmt(row.grad_vs_fd, ".1e"), _fmt(row.vs_torchtraj, ".1e"),
             row.converged, row.note]
    parts = [c.rjust(w) if right else c.ljust(w) for (_, w, right), c in zip(COLUMNS, cells)]
    return "  ".join(parts).rstrip()


def header() -> str:
    titles = "  ".join(t.rjust(w) if right else t.ljust(w) for t, w, right in COLUMNS).rstrip()
    return titles + "\n" + "-" * len(titles)


def default_method() -> str:
    """The method of ``--grad`` when none is named: the one ``tt.solve`` picks for its problems, which are
    constrained (:func:`~torchtraj.solve.default_method`; the IPM)."""
    return solve_default_method(lq_problem(linear_system(0)))


def run(batches, seed: int, method: str, say: Callable, dtype=torch.float64, device="cpu",
        pendulum_batches: Optional[list] = None, options=None, with_mpc: bool = True,
        gradients: str = "implicit", lq_options=None) -> list:
    """Run the protocol, print one line per row through ``say``, return the rows. ``lq_options`` (default
    ``options``) are those of the linear_box rows: a convex problem, for which the IPM's Mehrotra mode is made."""
    system = linear_system(seed, dtype, device)
    problem = lq_problem(system)
    have_mpc, why = mpc_available() if with_mpc else (False, "mpc.pytorch off (--no-reference)")
    say(f"gradient benchmark: torchtraj method {method}, {gradients} gradients, {dtype} on {device}, "
        f"{torch.get_num_threads()} threads; {why}")
    say(f"linear_box: nx={NX}, nu={NU}, N={HORIZON}, |u|<={U_MAX}; FD step {FD_STEP:g} (central, one random "
        "direction per input); times after an untimed run of the same solver at the same batch size, wall clock of "
        "the whole batch")
    say()
    say(header())
    rows = []
    speedups = []
    compiled = is_compiled(method, options)
    graphs = getattr(options, "cuda_graphs", False) and torch.device(device).type == "cuda"
    label = f"torchtraj/{method}" + ("+compile" if compiled else "") + ("+graphs" if graphs else "") \
        + ("+unrolled" if gradients == "unrolled" else "")
    lq_label = label + ("+mehrotra" if getattr(lq_options, "barrier_strategy", None) == "mehrotra" else "")
    lq_options = lq_options or options
    for batch in batches:
        x0, Xbar, Ubar, dirs = _instances(batch, seed, system)
        ours = GradRow("linear_box", lq_label, batch)
        U_ours = None
        try:
            # untimed at this batch size: first buffers of a new size (and compiled kernels) are built once
            _, seconds = _timed(lambda: torchtraj_lq(problem, x0, Xbar, Ubar, dirs, method, lq_options, fd=False,
                                                     gradients=gradients),
                                device)
            warm_up = f"; untimed compiling run {seconds:.0f} s" if compiled else ""
            fields, U_ours = torchtraj_lq(problem, x0, Xbar, Ubar, dirs, method, lq_options, gradients=gradients)
            for k, v in fields.items():
                setattr(ours, k, v)
            saturated = float((U_ours.abs() > U_MAX - 1e-6).to(torch.float64).mean())
            ours.note = f"{100 * saturated:.0f}% of controls at a bound" + warm_up
        except Exception as exc:  # a row never stops the run
            ours.note = f"{type(exc).__name__}: {exc}"
        say(format_row(ours))
        rows.append(ours)
        theirs = GradRow("linear_box", "mpc.pytorch", batch)
        if have_mpc:
            try:
                mpc_pytorch_lq(problem, x0, Xbar, Ubar, dirs, fd=False)  # untimed at this batch size, as ours
                fields, U_theirs = mpc_pytorch_lq(problem, x0, Xbar, Ubar, dirs)
                for k, v in fields.items():
                    setattr(theirs, k, v)
                if U_ours is not None:
                    theirs.vs_torchtraj = float((U_theirs - U_ours).abs().max())
                    speedups.append((batch, theirs.total_s / ours.total_s))
            except Exception as exc:
                theirs.note = f"{type(exc).__name__}: {exc}"
        else:
            theirs.note = why
        say(format_row(theirs))
        rows.append(theirs)
    for batch, ratio in speedups:
        say(f"speed-up B={batch}: mpc.pytorch total / torchtraj total = {ratio:.3g}")
    if pendulum_batches:
        say()
        pend = constrained_pendulum(dtype, device)
        for batch in pendulum_batches:
            row = GradRow(pend.name, label, batch)
            try:
                # untimed at this batch size (and compiling)
                x0 = problems.sample_x0("pendulum", batch, seed).to(dtype=dtype, device=device)
                _, seconds = _timed(lambda: solve(pend, x0, method=method, options=options), device)
                warm_up = f"; untimed compiling run {seconds:.0f} s" if compiled else ""
                for k, v in torchtraj_pendulum(pend, batch, seed, method, options, gradients=gradients).items():
                    setattr(row, k, v)
                row.note += warm_up
            except Exception as exc:
                row.note = f"{type(exc).__name__}: {exc}"
            say(format_row(row))
            rows.append(row)
            say(format_row(GradRow(pend.name, "mpc.pytorch", batch, note="cannot express state constraints")))
    return rows
