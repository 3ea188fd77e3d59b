"""Pictures of a batched solve, for when a look says more than a table: how each instance converged, and its
trajectories.

- :func:`convergence`: each instance's per-iteration history (:class:`~torchtraj.core.solution.History`) against the
  iteration: its cost, its largest constraint violation, its stationarity residual (the KKT conditions' gradient
  part, as the method measures it) and its step size, the last three on log scales. An instance's curve ends at
  its own last iteration (the history repeats its final values after it), or at the history's last row where its
  method counts iterations that record no row (the interior point's restoration phase and crossover rounds); it
  is drawn blue where the instance converged and red where it did not, so the failures stand out in a large batch.
- :func:`trajectories`: every instance's states and controls against time, one panel per component, with the
  problem's bounds where it has them.

Both return a :class:`matplotlib.figure.Figure` (no ``pyplot``: nothing global is touched, and nothing is shown);
save it with ``fig.savefig("convergence.png")``, or display it in a notebook. Matplotlib is the optional extra
``plot`` (``pip install "torchtraj[plot]"``); without it the functions raise an ``ImportError`` that says so.
"""

from __future__ import annotations

from typing import Optional

import torch

from .core.problem import Problem
from .core.solution import Solution
from .core.status import Status

#: Colours of the instances that converged and of those that did not.
CONVERGED_COLOUR, FAILED_COLOUR = "tab:blue", "tab:red"
#: The values below this are drawn at it on the log scales (a residual of exactly 0 has no logarithm).
LOG_FLOOR = 1e-16


def _figure_class():
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise ImportError('torchtraj.plotting needs matplotlib: pip install "torchtraj[plot]"') from exc
    return Figure


def _instances(sol: Solution) -> list:
    """``(instance, rows, converged)`` for each instance of ``sol``: ``rows`` its iterations, at most the history's
    length."""
    iterations = sol.iterations.reshape(-1).clamp_max(len(sol.history)).tolist()
    converged = (sol.status.reshape(-1) == Status.CONVERGED).tolist()
    return list(zip(range(len(iterations)), iterations, converged))


def convergence(sol: Solution, title: Optional[str] = None):
    """The per-iteration history of every instance of ``sol`` (module docstring): a ``Figure`` of four panels, three
    where the method records no stationarity residual."""
    Figure = _figure_class()
    history = sol.history
    panels = [("cost", "objective [problem units]", history.cost, "linear"),
              ("largest constraint violation", "violation [problem units] (log)", history.max_violation, "log")]
    if "stationarity" in history.extra:
        panels.append(("stationarity residual", "residual [problem units] (log)", history.extra["stationarity"],
                       "log"))
    panels.append(("step size", "step size α [1] (log)", history.step_size, "log"))
    fig = Figure(figsize=(3.8 * len(panels), 3.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    instances = _instances(sol)
    for ax, (name, ylabel, values, scale) in zip(axes, panels):
        values = values.detach().to("cpu", torch.float64)
        for i, count, converged in instances:
            curve = values[i, :count]
            if scale == "log":
                curve = curve.abs().clamp_min(LOG_FLOOR)
            ax.plot(range(1, count + 1), curve.numpy(), color=_colour(converged), lw=1,
                    alpha=0.5 if len(instances) > 1 else 1.0)
        ax.set(xlabel="iteration [count]", ylabel=ylabel, title=name, yscale=scale)
        _legend(ax, instances)
    done = sum(converged for _, _, converged in instances)
    fig.suptitle(title or f"{sol.method}: {done} of {len(instances)} instance(s) converged")
    return fig


def trajectories(sol: Solution, problem: Optional[Problem] = None, title: Optional[str] = None):
    """Every instance's states (top row) and controls (bottom row) against time, one panel per component: a
    ``Figure``. With ``problem``, time is in its ``dt`` (knots where it has none) and its state and control bounds are
    drawn as dashed lines."""
    Figure = _figure_class()
    X, U = sol.X.detach().to("cpu", torch.float64), sol.U.detach().to("cpu", torch.float64)
    nx, nu, N = X.shape[-1], U.shape[-1], U.shape[-2]
    dt = problem.dt if problem is not None and problem.dt is not None else None
    t = (torch.arange(N + 1, dtype=torch.float64) * (dt or 1.0)).numpy()
    columns = max(nx, nu)
    fig = Figure(figsize=(min(3.6 * columns, 20.0), 6.0), layout="constrained")
    axes = fig.subplots(2, columns, squeeze=False)
    instances = _instances(sol)
    for row, (values, size, name, lower, upper) in enumerate((
            (X, nx, "x", _bound(problem, "x_lower"), _bound(problem, "x_upper")),
            (U, nu, "u", _bound(problem, "u_lower"), _bound(problem, "u_upper")))):
        for j in range(columns):
            ax = axes[row, j]
            if j >= size:  # a row with fewer components than the other
                ax.remove()
                continue
            for i, _, converged in instances:
                alpha = 0.4 if len(instances) > 1 else 1.0
                if row == 0:
                    ax.plot(t, values[i, :, j].numpy(), color=_colour(converged), alpha=alpha, lw=1)
                else:
                    ax.step(t[:-1], values[i, :, j].numpy(), where="post", color=_colour(converged), alpha=alpha,
                            lw=1)
            bounded = False
            for bound in (lower, upper):
                if bound is not None and torch.isfinite(bound[j]):
                    ax.axhline(float(bound[j]), color="0.4", ls="--", lw=1)
                    bounded = True
            ax.set(xlabel="time t [s]" if dt else "knot k [index]", ylabel=f"{name}[{j}] [problem units]",
                   title=f"{'state' if row == 0 else 'control'} {name}[{j}]")
            _legend(ax, instances, bounded)
    done = sum(converged for _, _, converged in instances)
    fig.suptitle(title or f"{sol.method}: {len(instances)} instance(s), {done} converged")
    return fig


def _colour(converged: bool) -> str:
    return CONVERGED_COLOUR if converged else FAILED_COLOUR


def _legend(ax, instances: list, bounded: bool = False) -> None:
    """A legend of the colours present (and of the bounds' dashes)."""
    from matplotlib.lines import Line2D

    present = sorted({converged for _, _, converged in instances}, reverse=True)
    handles = [Line2D([], [], color=_colour(c), label="converged" if c else "not converged") for c in present]
    if bounded:
        handles.append(Line2D([], [], color="0.4", ls="--", label="bound"))
    ax.legend(handles=handles, fontsize=7)


def _bound(problem: Optional[Problem], name: str) -> Optional[torch.Tensor]:
    """The problem's bound ``name`` as a float64 CPU vector, or None (none declared, or one per instance)."""
    value = None if problem is None else getattr(problem, name)
    return None if value is None or value.dim() != 1 else value.detach().to("cpu", torch.float64)
