"""The one result type every solver returns."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Optional

import torch
from torch import Tensor

from .describe import solution_repr
from .status import Status


@dataclass
class History:
    """Per-iteration record of a batched solve; every field is ``(B, T)`` for T iterations.

    Entries after an instance stopped repeat its final values (its status says why it stopped). A row is one
    iteration of the method's main loop; the interior point's ``Solution.iterations`` also counts the iterations of
    its restoration phase (as IPOPT counts them) and its crossover rounds (each solves a Newton system), which add
    no row, so an instance's count may exceed T (:func:`torchtraj.plotting.convergence` draws the rows). Besides
    the four fields every method records, ``extra["stationarity"]`` holds the KKT conditions' stationarity residual
    at each iterate as the method measures it (the Lagrangian's gradient, unscaled except for the IPM's IPOPT
    scalings, of the multipliers and of the objective);
    ``max_violation`` is their feasibility residual, and the IPM's ``kkt_error`` their largest residual.
    """

    cost: Tensor
    max_violation: Tensor
    step_size: Tensor
    regularization: Tensor
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_rows(cls, rows: list) -> "History":
        """Stack a list of per-iteration dicts of ``(B,)`` tensors."""
        if not rows:
            empty = torch.zeros(0, 0)
            return cls(empty, empty, empty, empty)
        keys = rows[0].keys()
        stacked = {k: torch.stack([r[k] for r in rows], dim=1) for k in keys}
        base = {k: stacked.pop(k) for k in ("cost", "max_violation", "step_size", "regularization")}
        return cls(**base, extra=stacked)

    def __len__(self) -> int:
        return int(self.cost.shape[-1])


@dataclass
class Solution:
    """Result of ``tt.solve`` for a batch of B instances.

    Attributes:
        X: states ``(B, N+1, nx)``.
        U: controls ``(B, N, nu)``.
        K: feedback gains ``(B, N, nu, nx)`` of the last backward pass (``u = U + K (x - X)``).
        cost: objective ``(B,)`` at ``(X, U)``.
        max_violation: largest constraint violation ``(B,)`` (dynamics defects included).
        status: ``(B,)`` integer codes of :class:`~torchtraj.Status`.
        iterations: ``(B,)`` iterations each instance took.
        history: per-iteration :class:`History`.
        costate: multipliers of the dynamics ``(B, N+1, nx)`` where the method computes them.
        multipliers: multipliers of each constraint block, keyed by block name.
        penalties: final penalty weights of each block (augmented-Lagrangian methods).
        method: the method's name.
        kkt: the KKT residuals ``{name: (B,)}`` at the solution (stationarity, feasibility, complementarity,
            dual sign; :mod:`torchtraj.kkt.certificate`), which decide whether a status is ``CONVERGED``.
    """

    X: Tensor
    U: Tensor
    K: Tensor
    cost: Tensor
    max_violation: Tensor
    status: Tensor
    iterations: Tensor
    history: History
    costate: Optional[Tensor] = None
    multipliers: dict = field(default_factory=dict)
    penalties: dict = field(default_factory=dict)
    method: str = ""
    kkt: dict = field(default_factory=dict)

    @property
    def converged(self) -> Tensor:
        """Boolean mask ``(B,)`` of the instances that converged."""
        return self.status == Status.CONVERGED

    @property
    def batch_size(self) -> int:
        return int(self.X.shape[0])

    def __repr__(self) -> str:
        return solution_repr(self)

    def summary(self) -> str:
        """A few lines a person can read: status counts, cost and violation ranges."""
        counts = ", ".join(f"{k}: {v}" for k, v in Status.counts(self.status).items())
        finite = torch.isfinite(self.cost)
        cost = self.cost.detach()[finite]  # a differentiable solve's cost requires grad: read numbers only
        lines = [
            f"{self.method} on {self.batch_size} instance(s): {counts}",
            f"  iterations {int(self.iterations.min())}..{int(self.iterations.max())}",
        ]
        outer = self.history.extra.get("outer_limit")
        limited = self.status == Status.MAX_ITERATIONS
        if outer is not None and outer.numel() and bool(limited.any()):
            by_outer = int((limited & (outer[:, -1] > 0)).sum())
            lines.append(f"  max_iterations: {by_outer} after the outer loop's limit (iterations_outer dual updates), "
                         f"{int(limited.sum()) - by_outer} after the iteration budget or an unconverged projection")
        if cost.numel():
            lines.append(f"  cost {float(cost.min()):.8g}..{float(cost.max()):.8g}")
            lines.append(f"  max violation {float(self.max_violation.detach()[finite].max()):.3g}")
        return "\n".join(lines)


def without_inference_tensors(value: Any) -> Any:
    """``value`` (a :class:`Solution`, :class:`History`, a dict, list or tuple of them, a tensor) with every tensor
    made under ``torch.inference_mode`` replaced by a copy made outside it, the rest as it is: a copy can be changed
    in place and saved for backward by autograd, which an inference tensor cannot (``tt.solve`` runs its
    non-differentiable solves in inference mode and returns such copies)."""
    if isinstance(value, torch.Tensor):
        return value.clone() if value.is_inference() else value
    if isinstance(value, dict):
        return {k: without_inference_tensors(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(without_inference_tensors(v) for v in value)
    if isinstance(value, (Solution, History)):
        return dataclasses.replace(value, **{f.name: without_inference_tensors(getattr(value, f.name))
                                             for f in dataclasses.fields(value)})
    return value
