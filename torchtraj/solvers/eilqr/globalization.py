r"""One globalised step of eILQR (Horizon §II-F): the full step, its second-order correction, then backtracking.

A full Newton step that the ℓ1 merit refuses near a solution (the Maratos effect: the linearised dynamics leave a
second-order defect that ``γ ‖C‖₁`` charges more than the step gains) would cut the step size for ever and lose the
quadratic convergence. Before backtracking, the step is corrected once (Nocedal & Wright 2006 §18.3, "second-order
correction"; IPOPT's form, Wächter & Biegler 2006 §2.4): the same factorised KKT system (one vector solve; a
refactorisation with the same ``ε`` where the inertia correction mixed factorisations) with the constraint values
``c(w) + c(w + p)`` instead of ``c(w)``, so that ``∇c (p̂ − p) = −c(w + p)`` removes the defect the full step left. The
corrected step is taken whole if it passes the Armijo test of ``p``; otherwise the step sizes ``α = β, β², …`` of ``p``
are tried in batched rounds (:func:`~torchtraj.solvers.eilqr.merit.line_search`).
"""

from __future__ import annotations

import dataclasses

import torch

from ...globalization.line_search import Accepted
from .initial_state import InitialRows
from .merit import armijo_bound, constraint_values, line_search, merit_at, slope, trial_steps
from .newton import direction, pick_direction, resolve


def globalized_step(problem, cons, params, model, it, x0, initial, d, eps, gamma, l1, pending, opts, weights):
    """The accepted step of the ``pending (B,)`` instances from the direction ``d`` (computed with ``eps (B,)``):
    ``(direction, Accepted, merit0 (B,))``, the direction replaced by its correction where that was taken."""
    merit0 = model.J + gamma * l1
    derivative = slope(model, d, gamma, l1)
    steps = trial_steps(opts, merit0)
    ls = line_search(problem, cons, params, it.X, it.U, x0, initial, d, merit0, derivative, gamma, pending,
                     steps[:1], opts, weights)
    refused = pending & ~ls.found
    if opts.globalization and opts.second_order_correction and bool(refused.any()):
        defects, h, hN, c0 = constraint_values(problem, cons, params, it.X + d.dX, it.U + d.dU, x0, initial)
        corrected = dataclasses.replace(
            model, defects=model.defects + defects, h=model.h if h is None else model.h + h,
            hN=model.hN if hN is None else model.hN + hN,
            initial=None if model.initial is None else InitialRows(e0=model.initial.e0 + c0, E0=model.initial.E0))
        # the same factorisation, one vector solve, where every instance's step came from one
        soc = resolve(d, corrected, it, x0) if d.factor is not None else direction(corrected, it, x0, eps)
        m = merit_at(problem, cons, params, it.X + soc.dX, it.U + soc.dU, x0, initial, gamma, weights)
        bound = armijo_bound(merit0, derivative, steps[:1], opts)[:, 0]
        taken = refused & soc.ok & torch.isfinite(m) & (m <= bound)
        d = pick_direction(taken, soc, d)
        ls = Accepted(found=ls.found | taken, alpha=torch.where(taken, 1.0, ls.alpha),
                      values=(torch.where(taken, m, ls.values[0]),))
    refused = pending & ~ls.found
    if steps.shape[0] > 1 and bool(refused.any()):
        rest = line_search(problem, cons, params, it.X, it.U, x0, initial, d, merit0, derivative, gamma, refused,
                           steps[1:], opts, weights)
        ls = Accepted(found=ls.found | rest.found, alpha=torch.where(ls.found, ls.alpha, rest.alpha),
                      values=(torch.where(ls.found, ls.values[0], rest.values[0]),))
    return d, ls, merit0
