r"""The checked, batched inputs of one solve: what every solver receives.

``tt.solve`` builds one :class:`Batch` from the user's arguments. Every tensor argument may omit the batch
dimension; the batch size B is the common leading dimension of ``x0``, ``U0``, ``X0`` and the batched parameters
(1 if none has one), and every input is broadcast to it:

.. math::

    x_0 \in \mathbb{R}^{B \times n_x}, \quad U_0 \in \mathbb{R}^{B \times N \times n_u}, \quad
    X_0 \in \mathbb{R}^{B \times (N+1) \times n_x}, \quad p = \{\text{name}: (B, \dots)\}.

Tensors are moved to the problem's dtype and device, so that a solver never checks a shape or a dtype.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from .probe import accepts_one_row
from .problem import Problem


def batched(value, name: str, shape: tuple, problem: Problem) -> Optional[Tensor]:
    """``value`` as a tensor of shape ``(B, *shape)`` (B = 1 when it had no batch dimension); ``None`` stays."""
    if value is None:
        return None
    t = torch.as_tensor(value, dtype=problem.dtype, device=problem.device)
    if tuple(t.shape) == shape:
        return t.unsqueeze(0)
    if t.dim() == len(shape) + 1 and tuple(t.shape[1:]) == shape:
        return t
    raise ValueError(f"{name} must have shape {shape} or (B, *{shape}), got {tuple(t.shape)}")


def batch_size(named: dict) -> int:
    """The common leading dimension of ``{name: (B or 1, ...)}`` (entries of 1 broadcast), or 1."""
    sizes = {name: int(t.shape[0]) for name, t in named.items() if t is not None and t.shape[0] != 1}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"batch sizes disagree: {sizes}")
    return next(iter(sizes.values()), 1)


def check_parameter_batch(problem: Problem, B: int) -> None:
    """Refuse a parameter whose batch dimension was not said and cannot be told: one given to the constructor (so
    taken as one instance's value, its shape not declared in ``param_shapes``), of two or more dimensions, whose
    leading dimension is the batch size, and which the problem's functions accept as well with one row
    (:func:`~torchtraj.core.probe.accepts_one_row`). It is then likely one value per instance passed as if it were
    one instance's, and every instance would see all of them. A matrix the functions use as one (``e @ Q @ e``)
    fails with one row and passes; a vector parameter is taken as one instance's (its length may be anything)."""
    if B <= 1:
        return
    for k in sorted(problem._inferred_shapes):
        shape = tuple(problem.param_shapes[k])
        if len(shape) < 2 or shape[0] != B or tuple(problem.params[k].shape) != shape:
            continue
        if accepts_one_row(problem, k):
            raise ValueError(
                f"parameter {k!r} was given to the Problem constructor with shape {shape}, whose leading dimension is "
                f"the batch size {B}, and the problem's functions accept one row of it as well: its batch dimension "
                f"must be said. The constructor takes one instance's parameters, so every instance would see all "
                f"{B} rows. For one value per instance, build the problem with one instance's value and pass the "
                f"batch with problem.with_params({k}=values) (or declare param_shapes={{{k!r}: {shape[1:]}}}); if "
                f"{shape} is one instance's value, declare it: param_shapes={{{k!r}: {shape}}}")


@dataclass
class Batch:
    """One solve's inputs, broadcast to the batch (module docstring).

    Attributes:
        x0: initial states ``(B, nx)``.
        U0: initial controls ``(B, N, nu)``.
        X0: state guess ``(B, N+1, nx)``, or ``None``.
        params: the problem's parameters batched to B (:meth:`~torchtraj.Problem.batched_params`).
        duals: a warm start of the multipliers (``tt.solve``'s ``duals``), or ``None``.
        B: the batch size.
    """

    x0: Tensor
    U0: Tensor
    X0: Optional[Tensor]
    params: dict
    duals: Optional[dict]
    B: int

    @classmethod
    def build(cls, problem: Problem, x0=None, U0=None, X0=None, duals: Optional[dict] = None) -> "Batch":
        """Check and broadcast the user's inputs; ``x0`` and ``U0`` default to ``problem.x0`` and ``problem.u_init``."""
        N, nx, nu = problem.N, problem.nx, problem.nu
        x0 = batched(problem.x0 if x0 is None else x0, "x0", (nx,), problem)
        U0 = batched(problem.u_init if U0 is None else U0, "U0", (N, nu), problem)
        X0 = batched(X0, "X0", (N + 1, nx), problem)
        named = {"x0": x0, "U0": U0, "X0": X0}
        empty = [name for name, t in named.items() if t is not None and t.shape[0] == 0]
        if empty:
            raise ValueError(f"{' and '.join(empty)} {'hold' if len(empty) > 1 else 'holds'} an empty batch (B = 0): "
                             f"there is no instance to solve")
        B = batch_size({**named, "params": torch.empty(problem.param_batch_size())})
        check_parameter_batch(problem, B)
        x0, U0 = x0.expand(B, nx), U0.expand(B, N, nu)
        X0 = None if X0 is None else X0.expand(B, N + 1, nx)
        return cls(x0=x0, U0=U0, X0=X0, params=problem.batched_params(B), duals=duals, B=B)

    def for_solver(self, detach: bool = False) -> "Batch":
        """The inputs as a solver takes them: contiguous (the broadcast views made whole), each at the start of its
        storage (a caller's slice, as a distributed rank's shard, copied: a compiled kernel guards on a nonzero
        storage offset, and the rows that a solve gathers start at zero, so the kernels would compile once for each)
        and, with ``detach``, cut from the caller's graph (a differentiable solve takes its gradients at the
        solution's KKT point, not through the iterations)."""
        def from_start(t: Tensor) -> Tensor:  # its layout kept (a parameter every instance shares: stride 0)
            t = t.detach() if detach else t
            return t if t.storage_offset() == 0 else t.clone()

        def own(t: Optional[Tensor]) -> Optional[Tensor]:
            return None if t is None else from_start(t).contiguous()

        params = {k: from_start(v) if isinstance(v, Tensor) else v for k, v in self.params.items()}
        return dataclasses.replace(self, x0=own(self.x0), U0=own(self.U0), X0=own(self.X0), params=params)
