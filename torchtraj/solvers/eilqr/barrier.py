r"""The inequalities as soft barriers on the cost, the way Horizon's eILQR poses them (Laurenzi et al. §III:
"unilateral contact forces, friction cones, and joint limits are modeled with soft barriers").

eILQR is a Newton method on the KKT conditions of an *equality*-constrained problem. Every inequality row
``g_i(x, u) ≤ 0`` of a problem (path and terminal inequalities, control and state bounds, in the layout of
:class:`~torchtraj.core.constraints.Constraints`) leaves the constraints and enters the cost as

.. math::

    w\,β(−g_i),\qquad β(t) = \begin{cases} −\log t & t ≥ δ \\
        \tfrac12 \big((t − 2δ)/δ\big)^2 − \tfrac12 − \log δ & t < δ \end{cases}

the relaxed logarithmic barrier (Hauser & Saccon 2006; Feller & Ebenbauer 2017) of weight ``w``
(``barrier_weight``) and relaxation ``δ`` (``barrier_relaxation``). The quadratic extension matches ``−log t`` in
value, slope and curvature at ``t = δ`` (C²), so the barrier is finite at an infeasible guess and its Newton steps
are defined everywhere. At a solution, an active row sits at ``t ≈ w / z*`` from its bound (``z*`` the hard
problem's multiplier) and costs about ``w`` above the hard-constrained optimum; inactive rows pull the solution by
``w / t``. The gap to the hard optimum shrinks with ``w`` (``tests/test_eilqr.py`` measures it), and the row's
implied multiplier ``w β'(−g) ≥ 0`` is reported in ``Solution.multipliers`` under the block's name.

The state rows are switched off at knot 0 in the hard problem (``x_0`` is given); here they apply at every knot,
which adds a constant where ``x_0`` is fixed and keeps a free ``x_0`` (``free_initial_state``) inside its bounds.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state
from ...core.constraints import Constraints
from ...core.problem import Problem


def _delta(t: Tensor, delta) -> Tensor:
    return torch.as_tensor(delta, dtype=t.dtype, device=t.device)


def relaxed_log(t: Tensor, delta) -> Tensor:
    """``β(t)`` elementwise (module docstring); ``delta`` a float or a tensor broadcast against ``t``."""
    delta = _delta(t, delta)
    safe = torch.maximum(t, delta)  # the log's branch never sees t < δ, so its gradient stays finite there
    quadratic = 0.5 * ((t - 2.0 * delta) / delta) ** 2 - 0.5 - torch.log(delta)
    return torch.where(t >= delta, -torch.log(safe), quadratic)


def relaxed_log_slope(t: Tensor, delta) -> Tensor:
    """``β'(t)`` elementwise: ``−1/t`` for ``t ≥ δ``, ``(t − 2δ)/δ²`` below."""
    delta = _delta(t, delta)
    return torch.where(t >= delta, -1.0 / torch.maximum(t, delta), (t - 2.0 * delta) / delta ** 2)


def relaxed_log_curvature(t: Tensor, delta) -> Tensor:
    """``β''(t)`` elementwise: ``1/t²`` for ``t ≥ δ``, ``1/δ²`` below."""
    delta = _delta(t, delta)
    return torch.where(t >= delta, 1.0 / torch.maximum(t, delta) ** 2, 1.0 / delta ** 2)


def soft_problem(problem: Problem, weight: float, delta: float) -> Problem:
    """``problem`` with every inequality row and bound moved into the costs as ``w β(−g)``; its equalities stay.

    The result is a :class:`~torchtraj.Problem` like any other (same parameters, so a differentiable solve's
    gradients reach them), with no inequality and no bound: the problem whose KKT point eILQR returns."""
    cache = problem.__dict__.setdefault("_soft_problems", {})  # one probe call per problem and barrier
    if (weight, delta) not in cache:
        cache[(weight, delta)] = _soft_problem(problem, weight, delta)
    return cache[(weight, delta)]


def _soft_problem(problem: Problem, weight: float, delta: float) -> Problem:
    cons = Constraints.of(problem)
    if cons.mi + cons.miN == 0:
        return problem
    stage_ineq, terminal_ineq = cons.stage_ineq, cons.terminal_ineq
    stage_cost, terminal_cost = problem.stage_cost, problem.terminal_cost
    mi, miN = cons.mi, cons.miN

    def soft_stage_cost(x, u, p):
        out = stage_cost(x, u, p)
        return out + weight * relaxed_log(-stage_ineq(x, u, p), delta).sum() if mi else out

    def soft_terminal_cost(x, p):
        out = terminal_cost(x, p)
        return out + weight * relaxed_log(-terminal_ineq(x, p), delta).sum() if miN else out

    return problem.replace(stage_cost=soft_stage_cost, terminal_cost=soft_terminal_cost, stage_ineq=None,
                           state_ineq=None, terminal_ineq=None, u_lower=None, u_upper=None, x_lower=None,
                           x_upper=None, linear_quadratic=False, name=f"{problem.name} (soft barrier)")


def implied_multipliers(problem: Problem, X: Tensor, U: Tensor, params, weight: float, delta: float) -> tuple:
    """The inequality rows' multipliers that the barrier implies, ``z = −w β'(−g) ≥ 0``: stage ``(B, N, mi)``
    (zero on rows off at a knot, as the hard problem lays them out) and terminal ``(B, miN)``."""
    cons = Constraints.of(problem)
    B, N = U.shape[0], U.shape[1]
    z = X.new_zeros(B, N, cons.mi)
    zN = X.new_zeros(B, cons.miN)
    if cons.mi:
        g = map_stage(cons.stage_ineq, X[:, :-1], U, params)
        z = -weight * relaxed_log_slope(-g, delta) * cons.ineq_knot_mask
    if cons.miN:
        zN = -weight * relaxed_log_slope(-map_state(cons.terminal_ineq, X[:, -1], params), delta)
    return z, zN
