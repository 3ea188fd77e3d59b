r"""The largest violation of a trajectory, as every method reports it (``Solution.max_violation``).

.. math::

    v(X, U) = \max\Big( \max_k \|f(x_k, u_k) - x_{k+1}\|_∞,\ \|\bar x_0 - x_0\|_∞,\
        \max_k \|h(z_k)\|_∞,\ \max_k \|\max(g(z_k), 0)\|_∞,\ \|h_N\|_∞,\ \|\max(g_N, 0)\|_∞ \Big)

The dynamics are constraints of the trajectory like any other (a multiple-shooting iterate, ALTRO's infeasible
start and its projection move the states apart from the rollout), so their defects count. ALTRO's states start at
``x̄_0`` by construction (rolled out from it, and projected with a zero initial defect), so it leaves the initial
defect out; the implicit layer's refined points are Newton steps on it, so it passes ``x̄_0``. The interior-point
method takes the same measure, :func:`violation_of`, of the values its expansion has already evaluated.

A solution's cost and violation (:func:`cost_and_violation`) are measured once a solve, a controller's every step,
so :func:`solution_measures` replays them from a recorded graph where the method's ``record`` option says so.
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor

from ..core.batching import map_stage
from ..core.compiled import kernel
from ..core.constraints import Constraints
from ..core.problem import Problem
from ..core.recorded import Recorded
from .model import total_cost


def violation_of(defects: Tensor, h: Tensor, g: Tensor, hN: Tensor, gN: Tensor,
                 initial: Optional[Tensor] = None) -> Tensor:
    """``v (B,)`` of evaluated values: defects ``(B, N, nx)``, equalities ``h (B, N, me)``, ``hN (B, meN)``,
    inequalities ``g (B, N, mi)``, ``gN (B, miN)`` (rows off at a knot hold a value ``≤ 0``), and the initial
    defect ``initial (B, nx)`` where it counts."""
    B = defects.shape[0]
    parts = [defects.new_zeros(B, 1), defects.abs().flatten(1), h.abs().flatten(1), g.clamp_min(0).flatten(1),
             hN.abs().flatten(1), gN.clamp_min(0).flatten(1)]
    if initial is not None:
        parts.append(initial.abs())
    return torch.cat(parts, -1).amax(-1)


def largest_violation(problem: Problem, X: Tensor, U: Tensor, params, x0: Optional[Tensor] = None,
                      constraints: Optional[Constraints] = None) -> Tensor:
    """``v (B,)`` at ``X (B, N+1, nx)``, ``U (B, N, nu)``; the initial defect counts where ``x0 (B, nx)`` is given.

    ``constraints``: the problem's (:class:`~torchtraj.core.constraints.Constraints`), made here if not given."""
    constraints = Constraints.of(problem) if constraints is None else constraints
    defects = map_stage(problem.dynamics, X[:, :-1], U, params) - X[:, 1:]
    values = constraints.evaluate(X, U, params)
    return violation_of(defects, values.eq, values.ineq, values.eqN, values.ineqN,
                        None if x0 is None else x0 - X[:, 0])


def cost_and_violation(problem: Problem, constraints: Constraints, X: Tensor, U: Tensor, params,
                       x0: Optional[Tensor] = None) -> tuple:
    """The objective ``(B,)`` and :func:`largest_violation` ``(B,)`` at ``(X, U)``, the initial defect counted where
    ``x0 (B, nx)`` is given: what a solution reports (``Solution.cost``, ``Solution.max_violation``)."""
    return total_cost(problem, X, U, params), largest_violation(problem, X, U, params, x0, constraints)


# one record per signature, shared by every solve in the process (a controller measures its answer every step)
_RECORDED_COST_AND_VIOLATION = Recorded(cost_and_violation)


def solution_measures(compile: bool, record: Optional[bool]) -> Callable:
    """:func:`cost_and_violation` compiled (a method's ``compile`` option), else replayed from its record as the
    method's ``record`` option says (:mod:`~torchtraj.core.recorded`: the eager bits), else eager."""
    if compile:
        return kernel(cost_and_violation, True)
    return _RECORDED_COST_AND_VIOLATION.option(record)
