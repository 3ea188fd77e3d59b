"""Short text descriptions of a :class:`~torchtraj.Problem` and a :class:`~torchtraj.Solution`.

A dataclass's generated ``repr`` prints every tensor in full (a problem's ``u_init`` alone is ``N × nu`` numbers);
what a person looks for at a prompt are the sizes, the dtype, which constraints are present and what shape each
parameter has, and, for a solution, how many instances converged and the ranges of cost and violation.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .status import Status

_CONSTRAINT_FUNCTIONS = ("stage_eq", "stage_ineq", "state_ineq", "terminal_eq", "terminal_ineq")


def _shape(t: Tensor) -> str:
    return str(tuple(t.shape))


def _bounded(problem, lower: str, upper: str) -> bool:
    return any(b is not None and bool(torch.isfinite(b).any()) for b in (getattr(problem, lower),
                                                                         getattr(problem, upper)))


def problem_repr(problem) -> str:
    """``Problem('pendulum', nx=2, nu=1, N=50, dt=0.06, float64, constraints=[u bounds], params={m: ()})``."""
    constraints = [name for name in _CONSTRAINT_FUNCTIONS if getattr(problem, name) is not None]
    if _bounded(problem, "u_lower", "u_upper"):
        constraints.insert(0, "u bounds")
    if _bounded(problem, "x_lower", "x_upper"):
        constraints.insert(0, "x bounds")
    params = ", ".join(f"{k}: {_shape(v)}" for k, v in problem.params.items())
    dtype = str(problem.dtype).removeprefix("torch.")
    parts = [repr(problem.name), f"nx={problem.nx}", f"nu={problem.nu}", f"N={problem.N}"]
    if problem.dt is not None:
        parts.append(f"dt={problem.dt:g}")
    parts.append(dtype if problem.device.type == "cpu" else f"{dtype} on {problem.device}")
    parts.append(f"constraints=[{', '.join(constraints)}]")
    parts.append("params={" + params + "}")
    if problem.linear_quadratic:
        parts.append("linear_quadratic")
    return "Problem(" + ", ".join(parts) + ")"


def solution_repr(solution) -> str:
    """``Solution('altro', B=4, converged: 3, max_iterations: 1, cost 1.2..3.4, max violation 2e-09)``."""
    counts = ", ".join(f"{k}: {v}" for k, v in Status.counts(solution.status).items())
    parts = [repr(solution.method), f"B={solution.batch_size}", counts]
    cost = solution.cost.detach()
    finite = torch.isfinite(cost)
    if bool(finite.any()):
        parts.append(f"cost {float(cost[finite].min()):.6g}..{float(cost[finite].max()):.6g}")
        parts.append(f"max violation {float(solution.max_violation.detach()[finite].max()):.3g}")
    return "Solution(" + ", ".join(parts) + ")"
