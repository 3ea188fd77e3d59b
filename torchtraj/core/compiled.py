"""Opt-in ``torch.compile`` of the solvers' per-iteration kernels (``ILQROptions.compile``).

In eager mode a solver iteration is a few thousand small PyTorch operations — a rollout is N dynamics calls,
the Riccati sweep N small factorisations — and at small batches their fixed per-operation cost, not the
arithmetic, is the time: a pendulum MPC step (N = 30, 3 iterations) takes 63-74 ms on two CPU cores at B = 1.
Compiled by inductor into fused loops, it takes 3.5 ms (``python -m torchtraj.bench --mpc --compile``). The kernels:

* one iLQR iteration (:func:`torchtraj.solvers.ilqr.ilqr_step`: the ``torch.func`` expansion, the Riccati sweep of
  :mod:`torchtraj.riccati`, the line search's batched rollouts and the step acceptance) — one graph while the
  line search takes a single round of step sizes (``B ≤ 8192 / line_search_steps``), else one per round;
* the initial rollout, objective and violation, and the final gains and costates (iLQR) or cost and violation
  (ALTRO);
* per ALTRO iteration, the violation, the multiplier update and the objective under the new multipliers
  (:func:`torchtraj.solvers.altro.stages._measures`), and the MPC policy's own multiplier update.

The loops over iterations, the masks and the host synchronisations stay in Python, so the solver's logic is the
same code in both modes and its answers agree to rounding (``tests/test_compiled.py``).

Costs: the first call of each kernel for a new problem, batch size, horizon or dtype traces and compiles it (tens
of seconds; minutes for a whole ALTRO step on two cores), which pays off only for repeated solves with the same
shapes — an MPC policy, a training loop. Compiled code is specialised to shapes (``dynamic=False``); each kernel
keeps up to :data:`RECOMPILE_LIMIT` specialisations (problems × shapes × dtypes) before falling back to eager:
the first compiled kernel raises ``torch._dynamo.config.recompile_limit`` to it (a process-wide setting).
A C++ compiler is needed on CPU (inductor's requirement).
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

#: Contractions up to this length are written as broadcast products and sums when traced (:func:`matmul`).
FUSED_CONTRACTION = 8

#: Specialisations kept per kernel (Dynamo's default of 8 is reached by three MPC tasks in one process).
RECOMPILE_LIMIT = 64

_KERNELS: dict = {}


def kernel(fn: Callable, enabled: bool) -> Callable:
    """``fn`` itself, or (``enabled``) its compiled version, built once per function and shared by every call.

    ``fn`` must be a module-level function or an unbound method (``type(obj).method``, called with ``obj`` first),
    so that one compiled wrapper, and Dynamo's cache of its specialisations, serves every solve.
    """
    if not enabled:
        return fn
    compiled = _KERNELS.get(fn)
    if compiled is None:
        compiled = _KERNELS[fn] = _compile(fn)
    return compiled


def _compile(fn: Callable) -> Callable:
    # a process-wide setting (a patch around each call would cost 40 µs a call), raised only, never lowered
    config = torch._dynamo.config
    config.recompile_limit = max(config.recompile_limit, RECOMPILE_LIMIT)
    return torch.compile(fn, dynamic=False, options={"cpp_wrapper": True})


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b``. Traced by ``torch.compile`` with a short contraction (the stage matrices of small systems), a
    broadcast product and a sum, which inductor fuses into its loops: as matmuls, the products of a Riccati sweep
    and a closed-loop rollout are hundreds of library calls per kernel, each with its own fixed cost."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    if a.dim() == 3 and b.dim() == 3 and a.shape[0] == b.shape[0]:
        return torch.bmm(a, b)  # skips matmul's broadcasting: 1.3 µs against 3.7 µs a call for one 3 × 3 product
    return a @ b


def addmatmul(c: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``c + a @ b`` for batches of matrices ``(B, m, k)``, ``(B, k, n)``: one fused library call eager
    (``torch.baddbmm``), a broadcast product and sum when traced with a short contraction, as :func:`matmul`."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        return c + (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    return torch.baddbmm(c, a, b)


def matvec(a: Tensor, v: Tensor) -> Tensor:
    """``a @ v`` for a batch of matrices ``a (..., m, n)`` and vectors ``v (..., n)``, as :func:`matmul`."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        return (a * v.unsqueeze(-2)).sum(-1)
    return matmul(a, v.unsqueeze(-1)).squeeze(-1)
