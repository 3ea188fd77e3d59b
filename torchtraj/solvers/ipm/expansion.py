r"""The model at an iterate: the barrier problem's values, derivatives and optimality measures (FATROP §II-B).

The inequality rows ``g(w) ≤ 0`` of the problem (the stacked blocks of
:class:`~torchtraj.core.constraints.Constraints`: path and terminal inequalities and finite bounds) get slacks
``s ≥ 0``, and the barrier problem (FATROP eq. 3, with this library's sign of ``g``) is

.. math::

    \min_{w, s}\; J(w) - μ \sum_i \log s_i \quad \text{s.t.}\quad
    x_{k+1} = f(x_k, u_k),\; h(w) = 0,\; g(w) + s = 0,

``w = (X, U)`` with ``x_0`` fixed. :func:`expand` takes everything an iteration needs at an iterate in one pass of
``torch.func`` over the batch: the Lagrangian's gradient and Hessian (costates ``λ``, equality multipliers ``ν``,
multipliers ``y`` of ``g + s = 0``), the dynamics' values and Jacobians, the rows' values and Jacobians. Its
measures are IPOPT's (Wächter & Biegler 2006 eq. 5): the constraint violation ``θ = ‖c‖₁`` of the filter, and the
error of the barrier problem

.. math::  E_μ = \max\big(‖∇\mathcal L‖_∞ / s_d,\; ‖(\text{defects}, h, g + s)‖_∞,\; ‖S z − μ‖_∞ / s_c\big),

with the scalings ``s_d``, ``s_c`` of the multipliers' size; ``E_0 ≤ tol`` is convergence. ``‖∇\mathcal L‖_∞``
counts above its round-off, ``10 ε`` times its largest term ``‖∇_z (J + λ^T f + …)‖_∞``: the terms of a
stationarity residual cancel, and in float32 with multipliers in the hundreds what is left is noise of a few 1e-6,
above the default ``tol`` (IPOPT, in double precision, needs no such floor; in float64 it is ~1e-13).

A linear-quadratic problem (``Problem.linear_quadratic``) is expanded once, at its first iterate (where every
multiplier is zero, :class:`Base`): its Jacobians and Hessians are constants, taken once per instance and
broadcast over the stages, and at every later iterate its values alone are evaluated and its Lagrangian gradient
follows by products with them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state
from ...core.compiled import batched_options
from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...core.derivatives import (
    affine_stage_jacobian,
    multiplier_terms,
    quadratic_stage_hessian,
    stage_jacobian,
    terminal_hessian,
    terminal_jacobian,
)
from ...core.masks import RowPicker
from ...core.one_pass import problem_kkt_expansion, problem_values
from ...core.problem import Problem
from ...kkt.merit import violation_of
from ...kkt.model import total_cost
from ...riccati import all_finite
from .iterate import Iterate, Model
from .options import IPOptions


def flat_abs(*parts: Tensor) -> Tensor:
    """``|parts|`` flattened per instance and side by side, ``(B, n + 1)`` (a zero column: never empty)."""
    B = parts[0].shape[0]
    flat = [p.reshape(B, -1) for p in parts if p.shape[1:].numel()]  # empty blocks (no such rows) add no call
    return torch.cat(flat + [parts[0].new_zeros(B, 1)], -1).abs()


@dataclass
class ConstraintParts:
    """Values of the stage inequalities ``g (*, N, mi)`` (rows off at a knot are zero), stage equalities
    ``h (*, N, me)``, terminal inequalities ``gN (*, miN)`` and equalities ``hN (*, meN)``, and their Jacobians
    ``Gz (*, N, mi, nz)``, ``Hz``, ``GN (*, miN, nx)``, ``HN`` (``None`` where not asked for)."""

    g: Tensor
    Gz: Optional[Tensor]
    h: Tensor
    Hz: Optional[Tensor]
    gN: Tensor
    GN: Optional[Tensor]
    hN: Tensor
    HN: Optional[Tensor]


def constraint_parts(cons: Constraints, X: Tensor, U: Tensor, params, jacobians: bool,
                     affine: bool = False) -> ConstraintParts:
    """The rows' values (and Jacobians) at ``X (*, N+1, nx)``, ``U (*, N, nu)``; ``affine``: rows affine in
    ``(x, u)``, their stage Jacobians taken once per instance
    (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`)."""
    N, nx, nu = U.shape[-2], X.shape[-1], U.shape[-1]
    lead = X.shape[:-2]
    nz = nx + nu
    Xs, xN = X[..., :-1, :], X[..., -1, :]

    def stage(fn, m):
        if not m:
            return X.new_zeros(*lead, N, 0), X.new_zeros(*lead, N, 0, nz)
        if jacobians:
            return (affine_stage_jacobian if affine else stage_jacobian)(fn, Xs, U, params)
        return map_stage(fn, Xs, U, params), None

    def terminal(fn, m):
        if not m:
            return X.new_zeros(*lead, 0), X.new_zeros(*lead, 0, nx)
        if jacobians:
            return terminal_jacobian(fn, xN, params)
        return map_state(fn, xN, params), None

    g, Gz = stage(cons.stage_ineq, cons.mi)
    knots = cons.ineq_knot_mask
    g = g * knots
    Gz = None if Gz is None else Gz * knots.unsqueeze(-1)
    h, Hz = stage(cons.stage_eq, cons.me)
    gN, GN = terminal(cons.terminal_ineq, cons.miN)
    hN, HN = terminal(cons.terminal_eq, cons.meN)
    return ConstraintParts(g=g, Gz=Gz, h=h, Hz=Hz, gN=gN, GN=GN, hN=hN, HN=HN)


@dataclass
class Base:
    """The first expansion of a linear-quadratic problem (``Problem.linear_quadratic``): its point ``X``, ``U``
    and :class:`Model`, taken where every multiplier is zero, so that ``model.Lz`` is the cost gradient."""

    X: Tensor
    U: Tensor
    model: Model


@dataclass
class Expansion:
    """The derivatives of an iterate: the stage Lagrangians' gradient ``Lz (B, N, nz)`` (without ``−λ_k x_k``) and
    Hessian ``Lzz``, the terminal ones ``LNx``, ``LNxx``, the dynamics' values ``f (B, N, nx)`` and Jacobians
    ``fz``, the rows' :class:`ConstraintParts` and the objective ``J (B,)`` where the pass gave it."""

    Lz: Tensor
    Lzz: Tensor
    LNx: Tensor
    LNxx: Tensor
    f: Tensor
    fz: Tensor
    rows: ConstraintParts
    J: Optional[Tensor] = None  # the objective, where the pass gave it


def _general_expansion(problem: Problem, cons: Constraints, params, it: Iterate, record: Optional[bool]) -> Expansion:
    """One pass of ``torch.func`` over the batch and the stages
    (:func:`~torchtraj.core.one_pass.problem_kkt_expansion`; ``record``: replayed from its recorded graph)."""
    e = problem_kkt_expansion(problem, cons, it.X, it.U, params, it.lam, it.nu, it.y, it.nuN, it.yN, record=record)
    knots = cons.ineq_knot_mask
    rows = ConstraintParts(g=e.g * knots, Gz=e.Gz * knots.unsqueeze(-1), h=e.h, Hz=e.Hz, gN=e.gN, GN=e.GN, hN=e.hN,
                           HN=e.HN)
    return Expansion(Lz=e.Lz, Lzz=e.Lzz, LNx=e.LNx, LNxx=e.LNxx, f=e.f, fz=e.fz, rows=rows, J=e.cost)


def _linear_quadratic_expansion(problem: Problem, cons: Constraints, params, it: Iterate) -> Expansion:
    """The first expansion of a linear-quadratic problem: every Jacobian and Hessian taken once per instance and
    broadcast over the stages (:func:`~torchtraj.core.derivatives.affine_stage_jacobian`); the Lagrangian's Hessian is
    the costs' (affine rows have no curvature), its gradient the costs' and the multipliers' terms."""
    X, U = it.X, it.U
    f, fz = affine_stage_jacobian(problem.dynamics, X[:, :-1], U, params)
    _, lz, Lzz = quadratic_stage_hessian(problem.stage_cost, X[:, :-1], U, params)
    _, lNx, LNxx = terminal_hessian(problem.terminal_cost, X[:, -1], params)
    p = constraint_parts(cons, X, U, params, jacobians=True, affine=True)
    # stored whole, not as broadcast views: products with a gathered copy (compact_below) then round alike
    fz, Lzz, Gz, Hz = (t.contiguous() for t in (fz, Lzz, p.Gz, p.Hz))
    rows = ConstraintParts(g=p.g, Gz=Gz, h=p.h, Hz=Hz, gN=p.gN, GN=p.GN, hN=p.hN, HN=p.HN)
    stage, terminal = multiplier_terms(fz, Hz, Gz, p.HN, p.GN, it.lam[:, 1:], it.nu, it.y, it.nuN, it.yN)
    return Expansion(Lz=lz + stage, Lzz=Lzz, LNx=lNx + terminal, LNxx=LNxx, f=f, fz=fz, rows=rows)


def _linear_quadratic_values(problem: Problem, cons: Constraints, params, it: Iterate, base: Base) -> Expansion:
    """A linear-quadratic problem at a later iterate, from its first expansion: the values alone; the cost
    gradient moves with the constant cost Hessian, and the constant Jacobians carry the multipliers."""
    X, U, m = it.X, it.U, base.model
    dz = torch.cat([X[:, :-1] - base.X[:, :-1], U - base.U], -1)
    stage, terminal = multiplier_terms(m.fz, m.Hz, m.Gz, m.HN, m.GN, it.lam[:, 1:], it.nu, it.y, it.nuN, it.yN)
    Lz = m.Lz + _mv(m.Lzz, dz) + stage
    LNx = m.LNx + _mv(m.LNxx, X[:, -1] - base.X[:, -1]) + terminal
    f = map_stage(problem.dynamics, X[:, :-1], U, params)
    v = constraint_parts(cons, X, U, params, jacobians=False)
    rows = ConstraintParts(g=v.g, Gz=m.Gz, h=v.h, Hz=m.Hz, gN=v.gN, GN=m.GN, hN=v.hN, HN=m.HN)
    return Expansion(Lz=Lz, Lzz=m.Lzz, LNx=LNx, LNxx=m.LNxx, f=f, fz=m.fz, rows=rows)


# its loops run over the batch with the stages' few rows innermost, where Inductor's masked vectors of two or three
# elements cost more than scalar code: 20 ms a call against 31 ms at B = 1024 (docs/benchmarks.md); the kernels that
# hold the expansion take these options too (opening.opened, whole_iteration.whole_iteration)
@batched_options({"cpp.enable_loop_tail_vec": False})
def expand(problem: Problem, cons: Constraints, params, it: Iterate, opts: IPOptions,
           base: Optional[Base] = None) -> Model:
    """Everything the iteration needs at ``it``: one pass of ``torch.func`` over the batch, or, given the
    ``base`` expansion of a linear-quadratic problem, the values alone and its derivatives by products."""
    X, U = it.X, it.U
    nx = X.shape[-1]
    if base is None and problem.linear_quadratic:
        e = _linear_quadratic_expansion(problem, cons, params, it)
    elif base is None:
        e = _general_expansion(problem, cons, params, it, opts.record)
    else:
        e = _linear_quadratic_values(problem, cons, params, it, base)
    r = e.rows
    J = total_cost(problem, X, U, params) if e.J is None else e.J
    defects = e.f - X[:, 1:]
    knots = cons.ineq_knot_mask
    residuals = flat_abs(defects, r.h, r.hN, (r.g + it.s) * knots, r.gN + it.sN)
    theta, primal_error = residuals.sum(-1), residuals.amax(-1)
    violation = violation_of(defects, r.h, r.g, r.hN, r.gN)
    # Lagrangian gradient: x_k also appears in the dynamics row of stage k-1 (−λ_k); x_0 is fixed
    grad_x = e.Lz[:, 1:, :nx] - it.lam[:, 1:-1]
    grad_N = e.LNx - it.lam[:, -1]
    s_max = opts.scaling_threshold
    multipliers = flat_abs(it.lam, it.nu, it.nuN, it.y, it.yN, it.z, it.zN).sum(-1)
    count = it.lam[0].numel() + it.nu[0].numel() + it.nuN[0].numel() + 2 * (cons.mi * problem.N + cons.miN) + \
        U[0].numel() + X[0].numel()
    s_d = torch.clamp(multipliers / count, min=s_max) / s_max
    slack_grad = (it.y - it.z) * knots  # stationarity in s
    # the stationarity counts above its round-off: ten rounding errors of the largest gradient term (in float32 a
    # multiplier of 150 leaves ~2e-6 of noise in ∇L, above tol = 1e-6: the iteration would go on at random)
    roundoff = 10 * torch.finfo(X.dtype).eps * flat_abs(e.Lz, e.LNx).amax(-1)
    dual_error = torch.clamp(flat_abs(grad_x, e.Lz[:, :, nx:], grad_N, slack_grad, it.yN - it.zN).amax(-1)
                             - roundoff, min=0.0) / s_d
    if base is None:
        finite = all_finite([e.Lz, e.Lzz, e.LNxx, e.fz, r.Gz, r.Hz, r.GN, r.HN, J.unsqueeze(1), theta.unsqueeze(1)])
    else:  # the constant derivatives were checked with the first expansion
        finite = base.model.finite & all_finite([e.Lz, e.LNx, J.unsqueeze(1), theta.unsqueeze(1)])
    # the convergence test's third measure, here so that a compiled solve computes it in the expansion's kernel
    complementarity = complementarity_error(cons, it, it.s.new_zeros(it.s.shape[0]), opts)
    return Model(J=J, Lz=e.Lz, Lzz=e.Lzz, LNx=e.LNx, LNxx=e.LNxx, f=e.f, fz=e.fz, g=r.g, Gz=r.Gz, h=r.h, Hz=r.Hz,
                 gN=r.gN, GN=r.GN, hN=r.hN, HN=r.HN, theta=theta, violation=violation, dual_error=dual_error,
                 primal_error=primal_error, complementarity_error=complementarity, finite=finite, knots=knots)


def last_values(problem: Problem, cons: Constraints, params, it: Iterate, opts: IPOptions) -> tuple:
    """``(J, violation, finite)`` ``(B,)`` at ``it`` from the functions' values alone, no derivatives: the last
    iterate of a solve whose iterations ran out, untested (``IPOptions.test_last_iterate`` off)."""
    v = problem_values(problem, cons, it.X, it.U, params, record=opts.record)
    violation = violation_of(v.f - it.X[:, 1:], v.h, v.g * cons.ineq_knot_mask, v.hN, v.gN)
    return v.cost, violation, torch.isfinite(v.cost) & torch.isfinite(violation)


#: The fields of a linear-quadratic problem's :class:`Model` that change from point to point (its Jacobians and
#: Hessians are the problem's constants).
VALUE_FIELDS = ("J", "Lz", "LNx", "f", "g", "h", "gN", "hN", "theta", "violation", "dual_error", "primal_error",
                "complementarity_error", "finite")


def with_values(mask: Tensor, new: Model, model: Model) -> Model:
    """``model`` with the point-dependent fields (:data:`VALUE_FIELDS`) of ``new`` where ``mask (B,)``."""
    rows = RowPicker(mask)
    return dataclasses.replace(model, **{name: rows(getattr(new, name), getattr(model, name)) for name in VALUE_FIELDS})


def complementarity_error(cons: Constraints, it: Iterate, mu: Tensor, opts: IPOptions) -> Tensor:
    """``‖S z − μ‖∞ / s_c`` ``(B,)`` (IPOPT eq. 5); rows off at a knot do not count."""
    return complementarity_of(complementarity_parts(cons, it, opts), mu, cons.ineq_knot_mask)


def complementarity_parts(cons: Constraints, it: Iterate, opts: IPOptions) -> tuple:
    """What :func:`complementarity_error` reads of the iterate, for any number of ``μ``: ``(S z, S_N z_N, s_c)``."""
    knots = cons.ineq_knot_mask
    n = max(cons.mi * cons.problem.N + cons.miN, 1)
    s_max = opts.scaling_threshold
    s_c = torch.clamp(flat_abs(it.z * knots, it.zN).sum(-1) / n, min=s_max) / s_max
    return it.s * it.z, it.sN * it.zN, s_c


def complementarity_of(parts: tuple, mu: Tensor, knots: Tensor) -> Tensor:
    """:func:`complementarity_error` from its :func:`complementarity_parts`."""
    products, productsN, s_c = parts
    stage = (products - mu.reshape(-1, 1, 1)) * knots
    terminal = productsN - mu.unsqueeze(-1)
    return flat_abs(stage, terminal).amax(-1) / s_c


def kkt_error(model: Model) -> Tensor:
    """The convergence measure ``E_0`` ``(B,)`` at the model's iterate: the largest of the scaled dual, primal and
    complementarity errors."""
    return torch.maximum(torch.maximum(model.dual_error, model.primal_error), model.complementarity_error)


def initial_iterate(cons: Constraints, params, X: Tensor, U: Tensor, opts: IPOptions) -> Iterate:
    """Slacks ``max(−g, κ_1)`` (IPOPT's bound push for ``s ≥ 0``), ``z = dual_initial``, zero ``λ``, ``ν``, ``y``."""
    B, N, nx = X.shape[0], U.shape[1], X.shape[-1]
    rows = constraint_parts(cons, X, U, params, jacobians=False)
    knots = cons.ineq_knot_mask
    s = torch.where(knots > 0, torch.clamp(-rows.g, min=opts.bound_push), 1.0)
    sN = torch.clamp(-rows.gN, min=opts.bound_push)
    z = opts.dual_initial * knots.expand_as(s)
    zN = torch.full_like(sN, opts.dual_initial)
    return Iterate(X=X, U=U, s=s, sN=sN, z=z.clone(), zN=zN, y=torch.zeros_like(s), yN=torch.zeros_like(sN),
                   lam=X.new_zeros(B, N + 1, nx), nu=X.new_zeros(B, N, cons.me), nuN=X.new_zeros(B, cons.meN))
