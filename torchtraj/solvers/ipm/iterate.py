"""The interior-point method's primal-dual iterate and its model (values and derivatives at the iterate)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from torch import Tensor


@dataclass
class Iterate:
    """Primal-dual point of the batch: states, controls, slacks ``s`` and multipliers ``z`` of the stage
    ``(B, N, mi)`` and terminal ``(B, miN)`` inequalities, costates ``lam (B, N+1, nx)``, equality
    multipliers ``nu (B, N, me)``, ``nuN (B, meN)``."""

    X: Tensor
    U: Tensor
    s: Tensor
    sN: Tensor
    z: Tensor
    zN: Tensor
    y: Tensor
    yN: Tensor
    lam: Tensor
    nu: Tensor
    nuN: Tensor


@dataclass
class Model:
    """Values and derivatives at an iterate (one expansion), and the measures of its optimality."""

    J: Tensor  # (B,) objective
    Lz: Tensor  # (B, N, nz) gradient of the stage Lagrangians (without -λ_k x_k)
    Lzz: Tensor
    LNx: Tensor
    LNxx: Tensor
    f: Tensor  # (B, N, nx) dynamics values; fz their Jacobians
    fz: Tensor
    g: Tensor  # (B, N, mi), Gz (B, N, mi, nz); masked rows are zero
    Gz: Tensor
    h: Tensor
    Hz: Tensor
    gN: Tensor
    GN: Tensor
    hN: Tensor
    HN: Tensor
    theta: Tensor  # (B,) ‖c‖₁
    violation: Tensor  # (B,) largest violation of the problem's constraints and the dynamics
    dual_error: Tensor  # (B,) scaled largest Lagrangian gradient entry
    primal_error: Tensor  # (B,) largest residual of the barrier problem's constraints
    complementarity_error: Tensor  # (B,) scaled largest ``s z`` (the complementarity error at μ = 0)
    finite: Tensor  # (B,)
    knots: Tensor  # (N, mi): 1 where a stage inequality row applies


@dataclass
class Hooks:
    """What a caller of the iteration (:func:`~torchtraj.solvers.ipm.solver.run`) may set per instance; the
    restoration phase (:mod:`~torchtraj.solvers.ipm.restoration`) solves its own problem with them.

    ``barrier (B,)``: initial ``μ`` (else ``IPOptions.barrier_initial``); ``budget (B,)``: iterations left (else
    ``IPOptions.iterations``); ``start(it) -> Iterate``: changes the initial iterate; ``estimate (B,)``: with a
    ``start``, the instances whose multipliers still take the least-squares estimate at the first iterate (where
    ``IPOptions.least_squares_multipliers``; ``None``: none; without a ``start``, all do); ``leave(params, it,
    model) -> (B,)``: the instances that may stop now, reported ``CONVERGED``."""

    barrier: Optional[Tensor] = None
    budget: Optional[Tensor] = None
    start: Optional[Callable] = None
    estimate: Optional[Tensor] = None
    leave: Optional[Callable] = None
