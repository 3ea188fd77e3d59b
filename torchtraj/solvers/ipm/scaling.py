r"""Automatic scaling of the objective (Wächter & Biegler 2006 §3.8), per instance.

IPOPT does not iterate on the problem as given: by default (``nlp_scaling_method = gradient-based``) it solves

.. math::  \min_w\; s_f\, J(w) \quad\text{s.t. the same constraints},\qquad
           s_f = \max\big(s_{min},\ \min(1,\ g_{max} / ‖∇J(w_0)‖_∞)\big),

with ``g_max = 100`` (``nlp_scaling_max_gradient``), ``s_min = 1e-8`` (``nlp_scaling_min_value``) and the
gradient taken at the starting point ``w_0 = (X, U)`` (every knot's state and control, ``x_0`` included, as in the
multiple-shooting NLP where ``x_0`` is a variable fixed by a row). Every constant of the iteration that weighs the
objective against something else is absolute, so the factor changes the path: the inertia correction's ``δ_w``
(against ``∇²J``), the filter's margin ``φ − γ_φ θ`` and Armijo test, the switching condition
``α (−∇φᵀΔ)^{s_φ} > δ θ^{s_θ}`` (``s_φ = 2.3``), and the error's multiplier scaling ``s_d``. The tolerance
applies to the scaled problem, as in IPOPT, so the stationarity of the problem as given is at most ``tol / s_f``:
``tt.solve``'s certificate (1e-6 on the problem as given) holds at the default ``tol = 1e-8`` for ``s_f ≥ 0.01``
(quadrotor2d, the smallest of the problem set: 0.026); for a cost gradient above 1e4 at the start, a smaller
``IPOptions.tolerance`` or ``scaling="none"`` keeps it. The history's errors are the scaled problem's; its cost
and barrier are the problem's (:func:`unscale`).

Why it is here: start 59 of ``sample_x0("cartpole_unconstrained", 64, seed=0)`` (``‖∇J(w_0)‖_∞ = 309``, from
the terminal weight ``Q_f = 100``: ``s_f = 0.3238``, IPOPT's factor to 16 digits) took another path from the first
step without it (``δ_w = 1`` where IPOPT's scaled system takes ``10^{-2}``) and ran into a fixed point of the full
Newton step and its second-order correction: the full step lands where ``c(w + Δw) = −c(w)`` (``θ`` not reduced,
so the correction is tried), the correction's right-hand side ``c(w) + c(w + Δw)`` vanishes, and its step only
trades feasibility for objective, each accepted by the filter's ``φ``-branch while ``J`` fell by more than
``γ_φ θ``; the iterate settled at ``‖c‖_∞ = 0.2`` with the Lagrangian stationary to 1e-14 and ended
``MAX_ITERATIONS``. With ``s_f`` the iterates are IPOPT's: the same ``δ_w`` and step sizes, the objective within
1e-11 relative at each of the 16 iterates, and IPOPT's optimum (``tests/test_ipm_scaling.py``).

The scaled problem is the problem with its costs multiplied by a per-instance parameter
(:func:`scaled_problem`; the costs' copy is made once per problem, :func:`scaled_costs`); a batch whose every
``s_f`` is 1 iterates on the problem as given. The scaled problem's multipliers are ``s_f`` times the problem's,
and the solution is reported unscaled (:func:`unscale`).

IPOPT also scales each constraint row ``c_j`` by ``min(1, g_max / ‖∇c_j(w_0)‖_∞)``: not done here. The Newton
step does not change under a row scaling (its multiplier takes the factor), only ``θ`` and the errors do, and on
the problem set no row needs it: at the problem set's starts the largest Jacobian entry of a dynamics row is 1.17,
of a path row 73 (quadrotor2d's circle), of a terminal row 1.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...core.batch import Batch
from ...core.compiled import kernel
from ...core.derivatives import stage_gradient, terminal_gradient
from ...core.problem import Problem
from ...core.recorded import Recorded
from ...core.solution import History
from .kernels import compiled_kernels
from .options import IPOptions

#: The parameter that carries ``s_f (B,)`` into the scaled problem's costs.
SCALE = "_objective_scale"


def objective_scale(problem: Problem, X: Tensor, U: Tensor, params, opts: IPOptions) -> Tensor:
    """``s_f (B,)`` (module docstring) at the start ``X (B, N+1, nx)``, ``U (B, N, nu)``; 1 where the gradient is
    not finite (the iteration reports such a start) and everywhere with ``IPOptions.scaling == "none"``. The
    gradient's norm replays from its record where ``IPOptions.record`` says so (a controller scales every step), or
    is one kernel call where the solve's kernels are compiled."""
    if opts.scaling == "none":
        return X.new_ones(X.shape[0])
    if compiled_kernels(opts, X.device):
        largest = kernel(_largest_gradient, True)(problem, X, U, params)
    else:
        largest = _RECORDED_LARGEST_GRADIENT.option(opts.record)(problem, X, U, params)
    scale = torch.clamp(opts.scaling_max_gradient / largest, min=opts.scaling_min_value, max=1.0)
    return torch.where(torch.isfinite(largest), scale, 1.0)


def _largest_gradient(problem: Problem, X: Tensor, U: Tensor, params) -> Tensor:
    """``‖∇J(X, U)‖_∞ (B,)``."""
    _, stage = stage_gradient(problem.stage_cost, X[:, :-1], U, params)
    _, terminal = terminal_gradient(problem.terminal_cost, X[:, -1], params)
    B = X.shape[0]
    return torch.cat([stage.reshape(B, -1).abs(), terminal.reshape(B, -1).abs()], -1).amax(-1)


# one record per signature, shared by every solve in the process
_RECORDED_LARGEST_GRADIENT = Recorded(_largest_gradient)


def scaled_problem(problem: Problem, batch: Batch, opts: IPOptions) -> tuple:
    """The problem the iteration solves and its batch, from ``batch`` with its start ``X0`` given: where some
    instance's ``s_f`` is below 1, :func:`scaled_costs` with ``s_f (B,)`` among the parameters; else the problem and
    batch as given (they iterate bit for bit as before). Returns ``(problem, batch, s_f (B,) or None)``; asks the
    host once per solve."""
    scale = objective_scale(problem, batch.X0, batch.U0, batch.params, opts)
    if not bool((scale != 1.0).any()):
        return problem, batch, None
    return scaled_costs(problem), dataclasses.replace(batch, params={**batch.params, SCALE: scale}), scale


def scaled_costs(problem: Problem) -> Problem:
    """``problem`` with its costs multiplied by the parameter ``SCALE`` (one value per instance), made once per
    problem."""
    stage_cost, terminal_cost = problem.stage_cost, problem.terminal_cost
    return problem.derived("_objective_scaled", None, lambda: problem.replace(
        stage_cost=lambda x, u, p: p[SCALE] * stage_cost(x, u, p),
        terminal_cost=lambda x, p: p[SCALE] * terminal_cost(x, p),
        params={**problem.params, SCALE: torch.ones((), dtype=problem.dtype, device=problem.device)},
        param_shapes={**problem.param_shapes, SCALE: ()},
        name=f"{problem.name}_scaled",
    ))


def unscale(out, history: History, scale: Tensor):
    """The problem's cost and multipliers from the scaled problem's final values ``out``
    (:class:`~torchtraj.solvers.ipm.compaction.Final`) and history, ``scale (B,)`` = ``s_f``: the cost and every
    multiplier divided by ``s_f``; the history's cost and barrier likewise (``min s_f J − μ Σ log s`` is
    ``min J − (μ/s_f) Σ log s``: the barrier of the problem as given, in the multipliers' units, as a warm start
    takes it back, :mod:`~torchtraj.solvers.ipm.warm_start`); its errors stay the scaled problem's, as the
    convergence test measured them."""
    def per(value: Tensor) -> Tensor:
        return value / scale.reshape(-1, *[1] * (value.dim() - 1))

    out = dataclasses.replace(out, J=out.J / scale, lam=per(out.lam), z=per(out.z), zN=per(out.zN), nu=per(out.nu),
                              nuN=per(out.nuN))
    if history.cost.numel():
        extra = dict(history.extra)
        if "barrier" in extra:
            extra["barrier"] = extra["barrier"] / scale.unsqueeze(-1)
        history = dataclasses.replace(history, cost=history.cost / scale.unsqueeze(-1), extra=extra)
    return out, history
