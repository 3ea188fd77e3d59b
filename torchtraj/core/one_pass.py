r"""Everything a Newton-type iteration reads at a point, from one pass of ``torch.func`` over the batch and stages.

At a stage point ``z = (x, u)`` with multipliers ``w = (λ_{k+1}, ν_k, μ_k)``, the stage Lagrangian
``L(z) = l(z) + λ_{k+1}ᵀ f(z) + ν_kᵀ h(z) + μ_kᵀ g(z)`` is built from the values ``l, f, h, g``, which one forward
evaluation gives together. From it, one pass gives

.. math::  ∇L,\quad ∇²L,\quad f_z,\ h_z,\ g_z \quad\text{and}\quad J = Σ_k l_k + l_N,

where separate passes (:func:`~torchtraj.core.derivatives.problem_lagrangian_expansion`, then
:func:`~torchtraj.core.derivatives.stage_jacobian` for the dynamics and again for each row block, then
:func:`~torchtraj.kkt.model.total_cost`) evaluate and differentiate the user's functions again, each behind its own
``vmap``. The Hessian is the reverse-over-reverse derivative of ``∇L``; the rows' Jacobians are first-order
pullbacks of the same forward evaluation, taken beside the gradient's. Without multipliers (``costate=None``) the
Lagrangian is the cost alone, the Hessian of a Gauss-Newton model (iLQR, HM-iLQR); its gradient's graph is small,
and the Hessian's reverse pass runs over the stacked ``(∇l, f, h, g)``, which gives the rows' Jacobians with it in
the fewest calls. With multipliers, that single pass carries the rows' cotangents through the Lagrangian
gradient's graph, about twice the arithmetic of the separate pullbacks, in fewer calls; it is taken where the
points are few (:data:`HESSIAN_PASS_POINTS`: a single instance, a controller's step), whose time is the calls',
and the separate pullbacks where arithmetic is the cost (``docs/benchmarks.md`` has the figures). Both give the
same numbers: the single pass only adds the exact zeros of the rows' zero cotangents. The terminal point is the
same with ``L_N = l_N + ν_Nᵀ h_N + μ_Nᵀ g_N``. The results are those of the separate passes to the last bit.

:func:`problem_values` is the same point's values alone (a line search's trial points), in one ``vmap`` of the
stages and one of the end points.

Traced by ``torch.compile`` (:mod:`torchtraj.core.compiled`), the same derivatives come from pullbacks of the mapped
Lagrangian, outside ``vmap`` (:func:`_pullback_expansion`), as in :mod:`torchtraj.core.derivatives`: ``jacrev``
inside ``vmap`` would specialise the compiled kernel to the batch size. They agree with the eager ones to rounding.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor
from torch.func import jacrev, vjp, vmap

from .batching import concat, map_points, map_stage, map_state
from .derivatives import _rows, _stage_points, weight_blocks
from .recorded import Recorded, trace_at


@dataclass
class KKTExpansion:
    """The point's objective ``cost (B,)``, the Lagrangians' gradients and Hessians (``Lz (B, N, nz)``, ``Lzz``,
    ``LNx (B, nx)``, ``LNxx``; without the ``−λ_kᵀ x_k`` terms, as
    :func:`~torchtraj.core.derivatives.problem_lagrangian_expansion`'s), the dynamics ``f (B, N, nx)`` and
    Jacobians ``fz``, the stage rows ``h (B, N, me)``, ``g (B, N, mi)`` and terminal rows ``hN``, ``gN`` with their
    Jacobians ``Hz``, ``Gz``, ``HN``, ``GN`` (unmasked: rows off at a knot are the caller's to mask)."""

    cost: Tensor
    Lz: Tensor
    Lzz: Tensor
    LNx: Tensor
    LNxx: Tensor
    f: Tensor
    fz: Tensor
    h: Tensor
    Hz: Tensor
    g: Tensor
    Gz: Tensor
    hN: Tensor
    HN: Tensor
    gN: Tensor
    GN: Tensor


#: Most points (instances times stages) whose expansion with multipliers takes the rows' Jacobians out of the
#: Hessian's pass (module docstring): below it the calls are the time, above it the arithmetic.
HESSIAN_PASS_POINTS = 512


def _gradient_and_rows_jacobian(fn: Callable, rows_through_hessian: bool) -> Callable:
    """``fn(v) -> (L, (value, rows))`` as ``v ↦ (value, (∇L, rows), ∂(∇L, rows)/∂v)`` (module docstring).

    ``rows_through_hessian``: the rows' Jacobians come out of the Hessian's reverse pass, over ``(∇L, rows)``
    (the fewest calls; for a cost without multiplier terms, or a Lagrangian at few points). Otherwise (a
    Lagrangian, whose gradient's graph holds the rows' second derivatives, at many points) they get their own
    first-order pullbacks of the same forward evaluation: the Hessian's pass, batched over ``(∇L, rows)``, would
    carry the rows' cotangents through that graph, about twice the arithmetic."""
    def through_hessian(v):
        def first(v_):
            grad, (value, rows) = jacrev(fn, has_aux=True)(v_)
            stacked = concat([grad, *rows])
            return stacked, (stacked, value)

        jac, (stacked, value) = jacrev(first, has_aux=True)(v)
        return value, stacked, jac

    def own_pullbacks(v):
        def first(v_):
            def stacked(u):
                L, (value, rows) = fn(u)
                return concat([L.reshape(1), *rows]), value

            out, pullback, value = vjp(stacked, v_, has_aux=True)
            basis = torch.eye(out.shape[0], dtype=out.dtype, device=out.device)
            (grad,) = pullback(basis[0])
            if out.shape[0] > 1:
                (rows_jac,) = vmap(pullback)(basis[1:])
            else:
                rows_jac = v_.new_zeros(0, v_.shape[0])
            return grad, (grad, out[1:], rows_jac, value)

        hessian, (grad, rows, rows_jac, value) = jacrev(first, has_aux=True)(v)
        return value, concat([grad, rows]), concat([hessian, rows_jac])

    return through_hessian if rows_through_hessian else own_pullbacks


def _pullback_expansion(lagrangian_of: Callable, points: Tensor, weights: tuple, params):
    """What :func:`_gradient_and_rows_jacobian`'s ``own_pullbacks`` gives at every point of ``points (B, *E, n)``
    (``lagrangian_of(p, *w)`` the point's Lagrangian, its weights ``w`` mapped beside the points as in
    :func:`_mapped`), differentiating the mapped function instead: its points are independent, so the pullback of
    ``e_i`` on every point's output is row ``i`` of every point's Jacobian, as in
    :func:`~torchtraj.core.derivatives.stage_jacobian`'s compiled path. Traced by ``torch.compile``, ``jacrev``
    inside ``vmap`` would specialise the kernel to the batch size (:mod:`~torchtraj.core.compiled`); these pullbacks
    run outside it."""
    n = points.shape[-1]

    def outputs(P: Tensor):  # (L, rows) and the cost at every point
        def point(z, p, *w):
            L, (value, rows) = lagrangian_of(p, *w)(z)
            return concat([L.reshape(1), *rows]), value

        return _mapped(point, P, weights, params)

    def first(P: Tensor):
        out, pull, value = vjp(outputs, P, has_aux=True)
        eye = torch.eye(out.shape[-1], dtype=out.dtype, device=out.device)
        grad, *rows_jac = (pull(eye[i].expand_as(out))[0] for i in range(out.shape[-1]))
        rows_jac = torch.stack(rows_jac, -2) if rows_jac else P.new_zeros(*P.shape[:-1], 0, n)
        return grad, (grad, out[..., 1:], rows_jac, value)

    _, pull, (grad, rows, rows_jac, value) = vjp(first, points, has_aux=True)
    return value, torch.cat([grad, rows], -1), torch.cat([_rows(pull, grad), rows_jac], -2)


def _weighted(out: Tensor, weights: Optional[Tensor], values: Tensor) -> Tensor:
    return out if weights is None or not values.numel() else out + (weights * values).sum()


def _mapped(fn: Callable, points: Tensor, weights: tuple, params):
    """``fn(point, p, *weights)`` at every point of ``points (B, *E, n)``, the weights ``(B, *E, m)`` (``None``
    where absent) mapped beside them: not joined to the points, so that no call joins or splits them."""
    present = tuple(w is not None for w in weights)
    given = tuple(w for w in weights if w is not None)

    def point(z, *rest):
        *mapped, p = rest
        mapped = iter(mapped)
        return fn(z, p, *(next(mapped) if there else None for there in present))

    return map_points(point, (points, *given), params)


def problem_kkt_expansion(problem, constraints, X: Tensor, U: Tensor, params, costate: Optional[Tensor] = None,
                          nu=None, mu=None, nuN=None, muN=None, record: Optional[bool] = False) -> KKTExpansion:
    """The :class:`KKTExpansion` of ``problem`` at ``X (B, N+1, nx)``, ``U (B, N, nu)`` in one pass (module
    docstring): ``costate (B, N+1, nx)`` (``λ``) and the multipliers in the layout of
    :func:`~torchtraj.core.derivatives.problem_lagrangian_hessian` (missing ones zero), or ``costate=None`` and no
    multipliers for the cost's own Hessian. ``record`` (``True``, ``None``: when it pays; ``False``: never):
    replayed from its recorded operator graph (:mod:`~torchtraj.core.recorded`; the same numbers, fewer calls)."""
    if record is not False:
        return KKTExpansion(*_RECORDED_EXPANSION(problem, constraints, X, U, params, costate, nu, mu, nuN, muN,
                                                 trace_at=trace_at(record)))
    nx, nz = X.shape[-1], X.shape[-1] + U.shape[-1]
    me, mi, meN, miN = constraints.me, constraints.mi, constraints.meN, constraints.miN
    Z = _stage_points(X, U)
    if costate is None:
        if any(m is not None for m in (nu, mu, nuN, muN)):
            raise ValueError("multipliers without a costate: pass costate as well")
        stage_w = terminal_w = ()
    else:  # (λ_{k+1}, ν_k, μ_k) and (ν_N, μ_N), missing ones zero; a block without rows is left out (None)
        stage_w, terminal_w = weight_blocks(constraints, X, U, costate, nu, mu, nuN, muN)

    def stage_lagrangian(p, lam=None, v=None, m=None):  # the point's Lagrangian of z = (x, u), its weights fixed
        def lagrangian(z):
            x, u = z[:nx], z[nx:]
            cost, f = problem.stage_cost(x, u, p), problem.dynamics(x, u, p)
            h = constraints.stage_eq(x, u, p) if me else z.new_zeros(0)
            g = constraints.stage_ineq(x, u, p) if mi else z.new_zeros(0)
            out = _weighted(_weighted(_weighted(cost, lam, f), v, h), m, g)
            return out, (cost, (f, h, g))

        return lagrangian

    def terminal_lagrangian(p, v=None, m=None):
        def lagrangian(x):
            cost = problem.terminal_cost(x, p)
            h = constraints.terminal_eq(x, p) if meN else x.new_zeros(0)
            g = constraints.terminal_ineq(x, p) if miN else x.new_zeros(0)
            return _weighted(_weighted(cost, v, h), m, g), (cost, (h, g))

        return lagrangian

    if torch.compiler.is_compiling():
        l, rows, jac = _pullback_expansion(stage_lagrangian, Z, stage_w, params)
        lN, rowsN, jacN = _pullback_expansion(terminal_lagrangian, X[:, -1], terminal_w, params)
    else:
        by_hessian = costate is None or Z.shape[:-1].numel() <= HESSIAN_PASS_POINTS
        l, rows, jac = _mapped(lambda z, p, *w: _gradient_and_rows_jacobian(stage_lagrangian(p, *w), by_hessian)(z),
                               Z, stage_w, params)
        lN, rowsN, jacN = _mapped(
            lambda x, p, *w: _gradient_and_rows_jacobian(terminal_lagrangian(p, *w), by_hessian)(x), X[:, -1],
            terminal_w, params)
    Lz, f, h, g = rows.split([nz, nx, me, mi], -1)
    Lzz, fz, Hz, Gz = jac.split([nz, nx, me, mi], -2)
    LNx, hN, gN = rowsN.split([nx, meN, miN], -1)
    LNxx, HN, GN = jacN.split([nx, meN, miN], -2)
    return KKTExpansion(cost=l.sum(-1) + lN, Lz=Lz, Lzz=Lzz, LNx=LNx, LNxx=LNxx, f=f, fz=fz, h=h, Hz=Hz, g=g,
                        Gz=Gz, hN=hN, HN=HN, gN=gN, GN=GN)


@dataclass
class PointValues:
    """The values at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``: the objective ``cost (B, *E)``, the dynamics
    ``f (B, *E, N, nx)``, the stage rows ``h``, ``g`` and the terminal rows ``hN``, ``gN`` (unmasked)."""

    cost: Tensor
    f: Tensor
    h: Tensor
    g: Tensor
    hN: Tensor
    gN: Tensor


def problem_values(problem, constraints, X: Tensor, U: Tensor, params, record: Optional[bool] = False,
                   dynamics: bool = True) -> PointValues:
    """The :class:`PointValues` of ``problem`` at ``(X, U)``: one ``vmap`` of the stages, one of the end points;
    ``record`` as :func:`problem_kkt_expansion`'s; without ``dynamics`` (a rolled-out trajectory's merit), ``f``
    has no columns ``(B, *E, N, 0)``."""
    if record is not False:
        return PointValues(*_RECORDED_VALUES(problem, constraints, X, U, params, False, dynamics,
                                             trace_at=trace_at(record)))
    me, mi, meN, miN = constraints.me, constraints.mi, constraints.meN, constraints.miN

    def stage(x, u, p):
        h = constraints.stage_eq(x, u, p) if me else x.new_zeros(0)
        g = constraints.stage_ineq(x, u, p) if mi else x.new_zeros(0)
        return problem.stage_cost(x, u, p), problem.dynamics(x, u, p) if dynamics else x.new_zeros(0), h, g

    def terminal(x, p):
        h = constraints.terminal_eq(x, p) if meN else x.new_zeros(0)
        g = constraints.terminal_ineq(x, p) if miN else x.new_zeros(0)
        return problem.terminal_cost(x, p), h, g

    l, f, h, g = map_stage(stage, X[..., :-1, :], U, params)
    lN, hN, gN = map_state(terminal, X[..., -1, :], params)
    return PointValues(cost=l.sum(-1) + lN, f=f, h=h, g=g, hN=hN, gN=gN)


def _fields(value) -> tuple:
    return tuple(getattr(value, field.name) for field in dataclasses.fields(value))


# one record per signature, shared by every solve in the process
_RECORDED_EXPANSION = Recorded(lambda *args: _fields(problem_kkt_expansion(*args)))
_RECORDED_VALUES = Recorded(lambda *args: _fields(problem_values(*args)))
