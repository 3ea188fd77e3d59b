r"""The trial points of a CRLS round (:mod:`~torchtraj.solvers.hm_ilqr.crls`), each a kernel of its own (compiled
with ``HMILQROptions.compile``): the round's model of its step, the line search's batched segment rollouts with their
ratio test, the second-order correction's step, and the stationarity residual at the start point.

The ratio test (Tang et al. eq. 20) takes a step size ``α`` where the merit ``m = J + w D`` (objective and weighted
infeasibility, :mod:`~torchtraj.solvers.hm_ilqr.shooting`) changes as the model predicts,

.. math::

    ρ(α) = \frac{m(α) − m(0)}{ΔV(α)},\qquad ΔV(α) = α ΔV_1 + \tfrac{α^2}{2} ΔV_2 − (1 − (1 − α)^2)\, w D,
    \qquad ΔV(α) < 0,\quad ρ_{lower} < ρ(α) < ρ_{upper},

or where both changes lie below ``ROUNDING`` rounding errors of ``m`` (the crls module's "Round-off"); the trial
points are the segments rolled out from the nodes moved by ``α δx`` with the step's feedback and ``α`` times its
feedforward.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from ...core.batching import map_stage
from ...riccati.range_space import feedforward_of
from .multipliers import stepped_multipliers, with_multipliers
from .objective import HybridObjective
from .shooting import expected_change, merit_weight, model_change, rollout_segments, stationarity

#: Changes of the merit below this many rounding errors of its value are not resolved (Wächter & Biegler 2006,
#: §3.9: IPOPT relaxes its Armijo test by ``10 ε_mach |φ|``).
ROUNDING = 10.0


def round_model(lqr, rhs, factor, sol, J: Tensor, D: Tensor, weight_floor, one: Tensor, opts) -> tuple:
    """What a round reads of the step ``sol`` of ``factor``: the model's changes ``ΔV_1``, ``ΔV_2``, the defect
    weight (never below ``weight_floor``, an earlier iteration's: no cycling between merits), the merit ``J + w D``
    and its rounding (:mod:`~torchtraj.solvers.hm_ilqr.crls`, "Round-off"), whether the factorisation and the model
    are usable, the model's decrease at ``α = 1`` (``one``) and the gains, each ``(B, ...)``."""
    dV1, dV2 = model_change(lqr, rhs, sol.dx, sol.du)
    weight = merit_weight(dV1, dV2, D, opts.defect_weight)
    if weight_floor is not None:
        weight = torch.maximum(weight, weight_floor)
    ok = factor.ok & torch.isfinite(dV1) & torch.isfinite(dV2)
    full = -expected_change(one, dV1, dV2, D, weight)[:, 0]
    merit = J + weight * D
    return dV1, dV2, weight, merit, ROUNDING * torch.finfo(J.dtype).eps * merit.abs(), ok, full, factor.K


def ratio_test(problem, objective: HybridObjective, params, segments, X: Tensor, U: Tensor, factor, sol,
               alphas: Tensor, dV1: Tensor, dV2: Tensor, D: Tensor, weight: Tensor, merit: Tensor, rounding: Tensor,
               curved, opts):
    """The trial points of the step sizes ``alphas (l,)`` along ``sol`` (:func:`candidates`) and the ratio test of
    their merit's change against the model's (eq. 20): ``(accept (B, l), (X, U, J, D))``."""
    Xc, Uc, Jc, Dc = candidates(problem, objective, params, segments, X, U, sol.dx, feedforward_of(factor, sol),
                                factor.K, alphas)
    expected = expected_change(alphas, dV1, dV2, D, weight)
    change = Jc + weight.unsqueeze(1) * Dc - merit.unsqueeze(1)
    ratio = change / expected
    bounded = (Xc.abs().flatten(2).amax(-1) < opts.max_state) & (Jc < opts.max_cost)
    # a change the merit cannot resolve (the crls module's "Round-off") is accepted as the model says
    unresolved = rounding.unsqueeze(1)
    below = (-expected <= unresolved) & (change <= unresolved)
    accept = (torch.isfinite(Jc) & torch.isfinite(Dc) & bounded & (expected < 0)
              & (((ratio > opts.line_search_lower) & (ratio < opts.line_search_upper)) | below))
    if curved is not None:  # a Newton model's step is shortened only so far, then regularised
        accept = accept & (~curved.unsqueeze(1) | (alphas >= opts.curvature_step_min).unsqueeze(0))
    return accept, (Xc, Uc, Jc, Dc)


def candidates(problem, objective: HybridObjective, params, segments, X: Tensor, U: Tensor, dx: Tensor,
               feedforward: Tensor, K: Tensor, alphas: Tensor) -> tuple:
    """The trial points of the step sizes ``alphas (l,)``, ``(X, U, J, D)`` each ``(B, l, ...)``: the segments rolled
    out from the nodes moved by ``α dx`` with the feedback ``K`` and the feedforward ``α k``, their objective and
    their defects with the held rows' residuals."""
    a = alphas.reshape(1, -1, 1, 1)
    starts = segments.starts
    nodes = X[:, starts].unsqueeze(1) + a * dx[:, starts].unsqueeze(1)
    nodes[:, :, 0] = X[:, 0].unsqueeze(1)
    Xc, Uc, Dc = rollout_segments(problem.dynamics, params, nodes, U, segments, X, K, a * feedforward.unsqueeze(1),
                                  objective.record)
    return Xc, Uc, objective.value(Xc, Uc, params), Dc + objective.equality_residual(Xc, Uc, params)


def corrected_step(problem, objective: HybridObjective, params, segments, rhs, factor, Xc: Tensor, Uc: Tensor):
    """The second-order correction's step (:mod:`~torchtraj.solvers.hm_ilqr.crls`): ``factor``'s solve for the
    right-hand side ``rhs`` with the trial point ``(Xc, Uc)``'s own defects at the nodes and held rows, ``C(w + p)``,
    added to ``C(w)``."""
    k = segments.starts[1:] - 1
    d = torch.zeros_like(rhs.c)
    if k.numel():
        d[:, k] = map_stage(problem.dynamics, Xc[:, k], Uc[:, k], params) - Xc[:, k + 1]
    corrected = dataclasses.replace(rhs, c=rhs.c + d)
    held = objective.params.rlb.to(Xc.dtype)
    if objective.me:
        corrected.e = rhs.e + objective.stage_eq(Xc, Uc, params) * held.reshape(-1, 1, 1)
    if objective.meN:
        corrected.eN = rhs.eN + objective.terminal_eq(Xc, params) * held.reshape(-1, 1)
    return factor.solve(corrected)


def start_residual(lqr, rhs, rows, sol, rlb: Tensor) -> Tensor:
    """The stationarity residual ``(B,)`` at the start point, with the inequality rows' multipliers ``z⁺`` of the
    step ``sol`` and its held rows' ``ν`` (:mod:`~torchtraj.solvers.hm_ilqr.multipliers`)."""
    z, zN = stepped_multipliers(rows, sol.dx, sol.du, rlb)
    return stationarity(lqr, with_multipliers(rhs, rows, lqr.A.shape[-1], z, zN), sol.nu, sol.nuN)
