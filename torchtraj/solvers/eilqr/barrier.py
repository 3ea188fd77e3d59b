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
``w / t``. The gap to the hard optimum shrinks with ``w`` (``tests/test_eilqr.py`` measures it). The rows'
multipliers, reported in ``Solution.multipliers`` under the blocks' names, are the primal-dual iterates ``z`` of
:mod:`~torchtraj.solvers.eilqr.continuation`, equal to the implied ``−w β'(−g) ≥ 0`` at a converged point to the
complementarity tolerance. By default (an extension beyond the paper, the same module) the weight falls between
Newton stages to a tolerance-sized one, so that the point is the hard-constrained optimum.

The state rows are switched off at knot 0 in the hard problem (``x_0`` is given); in :func:`soft_problem` (the problem
a fixed weight's point is a KKT point of) they apply at every knot, which adds a constant where ``x_0`` is fixed; the
solver's barrier follows the hard problem's layout (from knot 1).
"""

from __future__ import annotations

import torch
from torch import Tensor

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
    # one probe call per problem and barrier
    return problem.derived("_soft_problems", (weight, delta), lambda: _soft_problem(problem, weight, delta))


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

    soft = problem.replace(stage_cost=soft_stage_cost, terminal_cost=soft_terminal_cost, stage_ineq=None,
                           state_ineq=None, terminal_ineq=None, u_lower=None, u_upper=None, x_lower=None,
                           x_upper=None, linear_quadratic=False, name=f"{problem.name} (soft barrier)")
    # the rows its costs read, held by the problem itself: a recorded kernel of its functions (the certificate's
    # residuals at every control step) holds their tensors by reference, as those of any problem it is given
    # (torchtraj.core.recorded: tensors of an argument whose tensors cannot be replaced)
    soft.__dict__["_softened_rows"] = cons
    return soft
