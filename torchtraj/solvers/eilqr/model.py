r"""The iterate of eILQR and its KKT model: the Lagrangian's derivatives and the residuals of Horizon eqs. (3)-(4).

The iterate is a multiple-shooting point ``w = (X, U)`` with the multipliers of the dynamics ``λ`` (costates,
``λ_{k+1}`` of ``f(x_k, u_k) − x_{k+1} = 0``), of the stage and terminal equalities ``ν``, ``ν_N`` and, with a free
initial state, of its rows ``μ_0`` (:mod:`~torchtraj.solvers.eilqr.initial_state`), and of the inequality rows
``z`` (an extension beyond the paper: :mod:`~torchtraj.solvers.eilqr.continuation`). With the Lagrangian
(Horizon eq. 2, with the inequality rows ``g ≤ 0`` of :class:`~torchtraj.core.constraints.Constraints`)

.. math::

    L = \sum_k \big[\ell_k + ν_k^T h_k + z_k^T g_k + λ_{k+1}^T (f(x_k, u_k) − x_{k+1})\big] + \ell_N + ν_N^T h_N
        + z_N^T g_N \ (+\ μ_0^T h_0(x_0)),

the KKT conditions (eqs. 3a-3d, 4a-4b) are ``∂L/∂x_k = 0`` (k ≥ 1; also k = 0 with a free ``x_0``),
``∂L/∂u_k = 0``, the defects ``f(x_k, u_k) − x_{k+1} = 0``, ``h = 0``, ``h_N = 0`` and the initial rows
(``x̄_0 − x_0 = 0``, or ``h_0 = 0`` on a free ``x_0``), with the barrier's complementarity
``z (−g) = w`` for the inequalities. :func:`expand` takes every derivative an iteration needs at
once with ``torch.func`` (:func:`~torchtraj.core.derivatives.problem_lagrangian_expansion`): the Lagrangian's
Hessian with the barrier's primal-dual curvature is the Newton matrix, and the *cost* gradient with the
barrier's (:func:`with_weight`) its right-hand side, so that the Riccati core's
multipliers are the new estimates ``λ⁺``, ``ν⁺`` themselves (:func:`~torchtraj.kkt.newton.newton_rhs`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state
from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...core.one_pass import problem_kkt_expansion
from ...core.problem import Problem
from ...riccati import all_finite
from .continuation import Rows, Weights, barrier_multipliers, barrier_value, curvatures, safeguarded
from .initial_state import InitialRows


@dataclass
class Iterate:
    """``X (B, N+1, nx)``, ``U (B, N, nu)``, costates ``lam (B, N+1, nx)`` (``lam[:, 0]`` the initial condition's),
    equality multipliers ``nu (B, N, me)``, ``nuN (B, meN)`` and the free initial state's ``mu0 (B, m0)``."""

    X: Tensor
    U: Tensor
    lam: Tensor
    nu: Tensor
    nuN: Tensor
    mu0: Tensor
    z: Tensor
    zN: Tensor


@dataclass
class Model:
    """The iterate's values and derivatives: cost ``J (B,)``; cost gradients ``lz (B, N, nz)``, ``lNx (B, nx)``;
    Lagrangian Hessians ``Lzz (B, N, nz, nz)``, ``LNxx (B, nx, nx)``; dynamics ``f (B, N, nx)``, ``fz``;
    equalities ``h (B, N, me)``, ``Hz``, ``hN (B, meN)``, ``HN``; the initial rows ``initial`` (values ``e0 (B, m0)``
    and Jacobian ``E0 (B, m0, nx)``, or the fixed start's defect ``x̄_0 − x_0``); the residuals ``dual (B,)``,
    ``primal (B,)`` (``∞``-norms) and ``error = max(dual, primal, complementarity)``; ``finite (B,)``. The barrier
    (:mod:`~torchtraj.solvers.eilqr.continuation`): the rows ``rows``, the safeguarded multipliers ``z``, ``zN``, the
    barrier's ``zw = w s(t)``, ``zwN``, the curvatures ``sigma``, ``sigmaN``, ``complementarity (B,)``, the
    problem's own ``cost (B,)`` (``J`` adds the barrier) and ``base``: the weight-free ``(lz, lNx, Lzz, LNxx)``."""

    J: Tensor
    lz: Tensor
    lNx: Tensor
    Lzz: Tensor
    LNxx: Tensor
    f: Tensor
    fz: Tensor
    h: Tensor
    Hz: Tensor
    hN: Tensor
    HN: Tensor
    initial: InitialRows
    defects: Tensor
    dual: Tensor
    primal: Tensor
    error: Tensor
    finite: Tensor
    rows: Rows = None
    z: Tensor = None
    zN: Tensor = None
    zw: Tensor = None
    zwN: Tensor = None
    sigma: Tensor = None
    sigmaN: Tensor = None
    complementarity: Tensor = None
    cost: Tensor = None
    base: tuple = None
    #: ``max |z − w s(t)|`` ``(B,)``: how far the multipliers are from the barrier's own, the soft problem's
    #: stationarity residual besides ``dual`` (its Lagrangian's gradient takes ``w s(t)``, not ``z``)
    barrier_gap: Tensor = None


def _amax(*parts: Tensor) -> Tensor:
    """``max |parts|`` per instance, ``(B,)`` (zero where all are empty)."""
    B = parts[0].shape[0]
    return torch.cat([p.reshape(B, -1).abs() for p in parts] + [parts[0].new_zeros(B, 1)], -1).amax(-1)


def _slacks(cons: Constraints, X: Tensor, U: Tensor, params) -> tuple:
    """The inequality rows' slacks ``t = −g`` at the stages ``(B, N, mi)`` and the end ``(B, miN)``."""
    B, N = U.shape[0], U.shape[1]
    t = -map_stage(cons.stage_ineq, X[:, :-1], U, params) if cons.mi else X.new_zeros(B, N, 0)
    tN = -map_state(cons.terminal_ineq, X[:, -1], params) if cons.miN else X.new_zeros(B, 0)
    return t, tN


def _barrier_point(cons: Constraints, params, it: Iterate, weights: Weights) -> tuple:
    """``(t, tN, mask, z, zN)`` at ``it``: the rows' slacks, the stage rows' knot mask and the safeguarded barrier
    multipliers, from the rows' values alone."""
    X, U = it.X, it.U
    t, tN = _slacks(cons, X, U, params)
    mask = cons.ineq_knot_mask if cons.mi else X.new_zeros(U.shape[1], 0)
    zw, zwN = barrier_multipliers(Rows(t=t, G=None, tN=tN, GN=None, mask=mask), weights)
    return t, tN, mask, safeguarded(it.z, zw) * mask, safeguarded(it.zN, zwN)


def last_multipliers(cons: Constraints, params, it: Iterate, weights: Weights) -> tuple:
    """``(z, zN)``: the barrier multipliers :func:`expand` would give ``it``, from the rows' values alone (the last
    iterate of a solve whose iterations ran out, untested: ``EILQROptions.test_last_iterate`` off)."""
    return _barrier_point(cons, params, it, weights)[3:]


def expand(problem: Problem, cons: Constraints, params, it: Iterate, x0: Tensor, rows, weights: Weights,
           record: Optional[bool] = False) -> Model:
    """Everything an iteration needs at ``it`` (module docstring): ``cons`` the problem's constraints, ``x0 (B, nx)``
    the given initial states, ``rows`` the free initial state's
    :class:`~torchtraj.solvers.eilqr.initial_state.InitialState` or ``None``, ``weights`` the barrier's; ``record``:
    the one-pass expansion replayed from its recorded graph (``EILQROptions.record``)."""
    X, U = it.X, it.U
    nx = X.shape[-1]
    # the barrier's multipliers come from the rows' values, the Lagrangian's Hessian from the multipliers: the values
    # first, then everything else in one pass (the rows' Jacobians with it)
    t, tN, mask, z, zN = _barrier_point(cons, params, it, weights)
    e = problem_kkt_expansion(problem, cons, X, U, params, it.lam, it.nu, z, it.nuN, zN, record=record)
    ineq = Rows(t=t, G=e.Gz, tN=tN, GN=e.GN, mask=mask)
    f, fz, h, Hz, hN, HN = e.f, e.fz, e.h, e.Hz, e.hN, e.HN
    # the cost gradient: the Lagrangian's less its multiplier terms (the right-hand side whose solve gives λ⁺, ν⁺;
    # the barrier's gradient is added by with_weight)
    lz = (e.Lz - _mv(fz.transpose(-1, -2), it.lam[:, 1:]) - _mv(Hz.transpose(-1, -2), it.nu)
          - _mv(ineq.G.transpose(-1, -2), z))
    lNx = e.LNx - _mv(HN.transpose(-1, -2), it.nuN) - _mv(ineq.GN.transpose(-1, -2), zN)
    initial = rows.evaluate(X[:, 0], params, jacobian=True) if rows is not None else None
    Lzz = e.Lzz
    curvature = rows.curvature(X[:, 0], it.mu0, params) if rows is not None else None
    if curvature is not None:  # a free x_0's rows h_0 are part of the Lagrangian (μ_0ᵀ h_0)
        Lzz = Lzz.clone()
        Lzz[:, 0, :nx, :nx] += curvature
    defects = f - X[:, 1:]
    grad_x = e.Lz[:, 1:, :nx] - it.lam[:, 1:-1]
    grad_N = e.LNx - it.lam[:, -1]
    parts = [grad_x, e.Lz[..., nx:], grad_N]
    if initial is not None:  # x_0 is a variable: its stationarity counts, with the initial rows' multipliers
        parts.append(e.Lz[:, 0, :nx] + _mv(initial.E0.transpose(-1, -2), it.mu0))
        start = initial.e0
    else:
        start = x0 - X[:, 0]
    dual = _amax(*parts)
    primal = _amax(defects, h, hN, start)
    cost = e.cost
    finite = all_finite([e.Lz, e.Lzz, e.LNxx, fz, Hz, HN, cost.unsqueeze(1),
                         primal.unsqueeze(1), ineq.G.flatten(1), ineq.GN.flatten(1), ineq.t.flatten(1)])
    model = Model(J=cost, lz=lz, lNx=lNx, Lzz=Lzz, LNxx=e.LNxx, f=f, fz=fz, h=h, Hz=Hz, hN=hN, HN=HN,
                  initial=initial, defects=defects, dual=dual, primal=primal, error=torch.maximum(dual, primal),
                  finite=finite, rows=ineq, z=z, zN=zN, cost=cost, base=(lz, lNx, Lzz, e.LNxx))
    return with_weight(model, weights)


def with_weight(model: Model, weights: Weights) -> Model:
    """``model`` with the barrier of ``weights``: its gradient ``Gᵀ w s(t)`` in the cost gradient, its primal-dual
    curvature ``Gᵀ diag(σ) G`` in the Hessian, its value in ``J``, the complementarity ``|t (z − w s(t))|`` in the
    error (the rest does not depend on the weight: a decrease of ``w`` needs no new expansion)."""
    ineq, (lz, lNx, Lzz, LNxx) = model.rows, model.base
    zw, zwN = barrier_multipliers(ineq, weights)
    sigma, sigmaN = curvatures(ineq, model.z, model.zN, weights)
    lz = lz + _mv(ineq.G.transpose(-1, -2), zw)
    lNx = lNx + _mv(ineq.GN.transpose(-1, -2), zwN)
    Lzz = Lzz + torch.einsum("bnki,bnk,bnkj->bnij", ineq.G, sigma, ineq.G)
    LNxx = LNxx + torch.einsum("bki,bk,bkj->bij", ineq.GN, sigmaN, ineq.GN)
    complementarity = _amax(ineq.t * (model.z - zw), ineq.tN * (model.zN - zwN))
    error = torch.maximum(torch.maximum(model.dual, model.primal), complementarity)
    J = model.cost + barrier_value(ineq, weights)
    return dataclasses.replace(model, J=J, lz=lz, lNx=lNx, Lzz=Lzz, LNxx=LNxx, zw=zw, zwN=zwN, sigma=sigma,
                               sigmaN=sigmaN, complementarity=complementarity, error=error,
                               barrier_gap=_amax(model.z - zw, model.zN - zwN))
