r"""Batched derivatives of the problem functions with ``torch.func``.

At every stage point ``z_k = (x_k, u_k)``, k = 0..N-1, of every instance at once:

* dynamics:   ``f(z_k)`` and its Jacobian ``f_z = [A_k  B_k]``            (``jacrev``)
* stage cost: ``l(z_k)``, ``l_z``, ``l_zz``                                   (``jacrev(jacrev)``)
* terminal:   ``l_N(x_N)``, ``l_Nx``, ``l_Nxx``
* constraints: values and Jacobians ``c_z`` of any stage or terminal function
* the Hessian of the stage Lagrangian
  ``L_k(z) = l(z) + λ_{k+1}ᵀ f(z) + ν_kᵀ h(z) + μ_kᵀ g(z)`` and of the terminal one
  ``L_N(x) = l_N(x) + ν_Nᵀ h_N(x) + μ_Nᵀ g_N(x)`` (for the Newton-type solvers and the
  implicit-differentiation backward pass).

Every function is the user's per-instance function wrapped by ``jacrev`` and mapped over batch
and time by :mod:`torchtraj.core.batching`; nothing is differentiated by hand.

Why reverse mode everywhere, although the Jacobians are square or tall and forward mode would
be the textbook choice: with PyTorch 2.13 on CPU, ``vmap(jacfwd(·))`` routes products with
Python or 0-dim scalars through Python decompositions (``torch._refs``) under forward AD, and
measures several times slower than ``vmap(jacrev(·))`` on the problem set's models, for Jacobians and
for Hessians alike (``docs/benchmarks.md``, design choices). The results are the same to rounding.

Traced by ``torch.compile`` (:mod:`torchtraj.core.compiled`, whose kernels take the batch size as a symbol),
:func:`stage_jacobian`, :func:`terminal_jacobian`, their scalar functions' :func:`stage_gradient` and
:func:`terminal_gradient`, :func:`stage_hessian` and :func:`terminal_hessian` differentiate the mapped function
instead: its points are independent, so the pullback of the unit vector ``e_i`` on every point's output is row ``i``
of every point's Jacobian (:func:`_pullback_rows`), the pullback of ones a scalar function's gradient at every point
(:func:`_pullback_gradient`), and the Hessian the rows of the gradient's pullbacks. With PyTorch 2.13, ``jacrev``
inside ``vmap`` specialises the traced graph to the batch size: the batching rules of the backward operations
(``slice_backward``, ``cat``) read concrete sizes. The pullbacks run outside ``vmap``, on the batch's tensors, and are
the products ``jacrev`` forms (traced with Dynamo's eager backend, the same numbers to the last bit). A scalar
function takes the gradient's functions: the rows' pullbacks would take its last batch dimension (the stages, or the
instances at the terminal knot) for its rows, one pullback each, and read the batch size.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Iterator, Mapping

import torch
from torch import Tensor
from torch.func import jacrev, jvp, vjp
from torch.utils._python_dispatch import _disable_current_modes

from .batching import map_stage, map_state
from .compiled import matvec

Params = Mapping[str, Tensor]


@functools.cache
def differentiates_in_inference_mode() -> bool:
    """Whether ``torch.func``'s transforms differentiate under ``torch.inference_mode`` in this PyTorch. Releases
    before the fix of pytorch/pytorch#177318 (2.11 among them) run them with autograd's dispatch keys excluded and
    return zero derivatives, silently; ``tt.solve`` then runs a method's iterations under ``torch.no_grad`` instead
    (``torchtraj/solve.py``). Probed once, on the CPU, in both modes the package uses (reverse and forward), with
    the caller's dispatch modes set aside (an operator counter, a trace: the probe is no part of a solve)."""
    with _disable_current_modes(), torch.inference_mode():
        x = torch.ones((), dtype=torch.float64)
        reverse = vjp(torch.square, x)[1](x)[0]
        forward = jvp(torch.square, (x,), (x,))[1]
        return bool(reverse == 2.0) and bool(forward == 2.0)


def _on_z(fn: Callable, nx: int) -> Callable:
    """``fn(x, u, p)`` as a function of the stacked point ``z = (x, u)``."""
    return lambda z, p: fn(z[:nx], z[nx:], p)


def _value_and_jacobian(g: Callable) -> Callable:
    def wrapped(z, p):
        def aux(z_):
            out = g(z_, p)
            return out, out

        jac, value = jacrev(aux, has_aux=True)(z)
        return value, jac

    return wrapped


def _value_gradient_hessian(g: Callable) -> Callable:
    def wrapped(z, p):
        def value(z_):
            out = g(z_, p)
            return out, out

        def gradient(z_):
            grad, val = jacrev(value, has_aux=True)(z_)
            return grad, (grad, val)

        hess, (grad, val) = jacrev(gradient, has_aux=True)(z)
        return val, grad, hess

    return wrapped


def _pullback_rows(F: Callable, Z: Tensor):
    """Values ``(..., m)`` and Jacobians ``(..., m, n)`` of ``F: (..., n) -> (..., m)``, a per-point function mapped
    over the points ``Z``: the pullback of ``e_i`` on every point is row ``i`` of each point's Jacobian."""
    out, pull = vjp(F, Z)
    if out.shape[-1] == 0:
        return out, out.new_zeros(*out.shape, Z.shape[-1])
    return out, _rows(pull, out)


def _pullback_gradient(F: Callable, Z: Tensor):
    """Values ``(...)`` and gradients ``(..., n)`` of ``F: (..., n) -> (...)``, a scalar per-point function mapped
    over the points ``Z``: the pullback of ones."""
    value, pull = vjp(F, Z)
    return value, pull(torch.ones_like(value))[0]


def _pullback_hessian(F: Callable, Z: Tensor):
    """Values ``(...)``, gradients ``(..., n)`` and Hessians ``(..., n, n)`` of ``F: (..., n) -> (...)``, a scalar
    per-point function mapped over the points ``Z`` (:func:`_pullback_rows` of its gradient)."""
    def gradient(Z_):
        value, grad = _pullback_gradient(F, Z_)
        return grad, value

    grad, pull, value = vjp(gradient, Z, has_aux=True)
    return value, grad, _rows(pull, grad)


def _rows(pull: Callable, out: Tensor) -> Tensor:
    """The Jacobians ``(..., m, n)`` whose rows are the pullbacks ``pull`` of each unit vector ``e_i`` on every
    point's output ``out (..., m)``."""
    eye = torch.eye(out.shape[-1], dtype=out.dtype, device=out.device)
    return torch.stack([pull(eye[i].expand_as(out))[0] for i in range(out.shape[-1])], -2)


def _stage_points(X: Tensor, U: Tensor) -> Tensor:
    return torch.cat([X[:, : U.shape[1]], U], -1)


def _at_stages(fn: Callable, X: Tensor, U: Tensor, params: Params, traced: Callable, eager: Callable):
    """``fn(x, u, p)`` differentiated at every stage point: when traced, ``traced`` (a pullback, module docstring) of
    the mapped function; else the per-point transform ``eager`` mapped over the points."""
    nx = X.shape[-1]
    Z = _stage_points(X, U)
    if torch.compiler.is_compiling():
        return traced(lambda Z_: map_state(_on_z(fn, nx), Z_, params), Z)
    return map_state(eager(_on_z(fn, nx)), Z, params)


def _at_terminal(fn: Callable, xN: Tensor, params: Params, traced: Callable, eager: Callable):
    """``fn(x, p)`` differentiated at ``xN (B, nx)``, as :func:`_at_stages`."""
    if torch.compiler.is_compiling():
        return traced(lambda X_: map_state(fn, X_, params), xN)
    return map_state(eager(fn), xN, params)


def stage_jacobian(fn: Callable, X: Tensor, U: Tensor, params: Params):
    """Values ``(B, N, m)`` and Jacobians ``(B, N, m, nx+nu)`` of ``fn(x, u, p)`` at every stage."""
    return _at_stages(fn, X, U, params, _pullback_rows, _value_and_jacobian)


def terminal_jacobian(fn: Callable, xN: Tensor, params: Params):
    """Values ``(B, m)`` and Jacobians ``(B, m, nx)`` of ``fn(x, p)`` at ``xN (B, nx)``."""
    return _at_terminal(fn, xN, params, _pullback_rows, _value_and_jacobian)


def stage_gradient(fn: Callable, X: Tensor, U: Tensor, params: Params):
    """Values ``(B, N)`` and gradients ``(B, N, nx+nu)`` of a scalar ``fn(x, u, p)`` at every stage (eager, the
    Jacobian's ``jacrev``, which gives a scalar's gradient)."""
    return _at_stages(fn, X, U, params, _pullback_gradient, _value_and_jacobian)


def terminal_gradient(fn: Callable, xN: Tensor, params: Params):
    """Value ``(B,)`` and gradient ``(B, nx)`` of a scalar ``fn(x, p)`` at ``xN (B, nx)``."""
    return _at_terminal(fn, xN, params, _pullback_gradient, _value_and_jacobian)


def stage_hessian(fn: Callable, X: Tensor, U: Tensor, params: Params):
    """Value ``(B, N)``, gradient ``(B, N, nz)`` and Hessian ``(B, N, nz, nz)`` of a scalar ``fn(x, u, p)``."""
    return _at_stages(fn, X, U, params, _pullback_hessian, _value_gradient_hessian)


def terminal_hessian(fn: Callable, xN: Tensor, params: Params):
    """Value ``(B,)``, gradient ``(B, nx)`` and Hessian ``(B, nx, nx)`` of a scalar ``fn(x, p)``."""
    return _at_terminal(fn, xN, params, _pullback_hessian, _value_gradient_hessian)


def _from_first_stage(X: Tensor, U: Tensor) -> Tensor:
    """``z_k − z_0 (B, N, nx+nu)``: every stage point's offset from its instance's first."""
    Z = _stage_points(X, U)
    return Z - Z[:, :1]


def _broadcast(derivative: Tensor, N: int) -> Tensor:
    return derivative.expand(derivative.shape[0], N, *derivative.shape[2:])


def affine_stage_jacobian(fn: Callable, X: Tensor, U: Tensor, params: Params):
    """:func:`stage_jacobian` of an ``fn`` affine in ``(x, u)``, as a linear-quadratic problem's are
    (``Problem.linear_quadratic``): the Jacobian at each instance's first stage, broadcast over the stages (a view:
    the problem functions take no stage index, so it is every stage's); the values are evaluated at every stage.
    One differentiation per instance instead of one per stage."""
    _, jac = stage_jacobian(fn, X[:, :1], U[:, :1], params)
    return map_stage(fn, X[:, : U.shape[1]], U, params), _broadcast(jac, U.shape[1])


def quadratic_stage_hessian(fn: Callable, X: Tensor, U: Tensor, params: Params):
    """:func:`stage_hessian` of a quadratic scalar ``fn(x, u, p)``, as :func:`affine_stage_jacobian`: the Hessian
    of the first stage broadcast, the values and gradients moved from there (exactly, for a quadratic ``fn``)."""
    value, grad, hess = stage_hessian(fn, X[:, :1], U[:, :1], params)
    hess = _broadcast(hess, U.shape[1])
    dz = _from_first_stage(X, U)
    hdz = (hess @ dz.unsqueeze(-1)).squeeze(-1)
    return value + (grad * dz).sum(-1) + 0.5 * (dz * hdz).sum(-1), grad + hdz, hess


def multiplier_terms(fz: Tensor, Hz: Tensor, Gz: Tensor, HN: Tensor, GN: Tensor, costate_next: Tensor, nu: Tensor,
                     mu: Tensor, nuN: Tensor, muN: Tensor) -> tuple:
    """The multipliers' part of the Lagrangian gradients by the constraints' Jacobians: ``(B, N, nz)``
    ``f_zᵀ λ_{k+1} + h_zᵀ ν_k + g_zᵀ μ_k`` at the stages and ``(B, nx)`` ``h_{N,x}ᵀ ν_N + g_{N,x}ᵀ μ_N`` at the end
    (``Hz (B, N, me, nz)``, ``nu (B, N, me)`` and so on; the ``−λ_kᵀ x_k`` terms are left to the caller)."""
    def tmv(a: Tensor, v: Tensor) -> Tensor:
        return matvec(a.transpose(-1, -2), v)

    return tmv(fz, costate_next) + tmv(Hz, nu) + tmv(Gz, mu), tmv(HN, nuN) + tmv(GN, muN)


def linearize_dynamics(dynamics: Callable, X: Tensor, U: Tensor, params: Params):
    """``f (B, N, nx)``, ``A (B, N, nx, nx)``, ``B (B, N, nx, nu)`` at every stage of ``(X, U)``."""
    nx = X.shape[-1]
    f, fz = stage_jacobian(dynamics, X, U, params)
    return f, fz[..., :nx], fz[..., nx:]


@dataclass
class Expansion:
    """Second-order expansion of a scalar stage function and its terminal one (a cost or a Lagrangian):
    ``value (B, N)``, ``gradient (B, N, nz)``, ``hessian (B, N, nz, nz)`` over ``z = (x, u)``, and
    ``terminal_value (B,)``, ``terminal_gradient (B, nx)``, ``terminal_hessian (B, nx, nx)``.

    It unpacks in that order, as the positional tuple it replaces did (``l, lz, lzz, lN, lNx, lNxx = ...``),
    so that callers written for the tuple keep working; new code reads the fields by name."""

    value: Tensor
    gradient: Tensor
    hessian: Tensor
    terminal_value: Tensor
    terminal_gradient: Tensor
    terminal_hessian: Tensor

    def __iter__(self) -> Iterator[Tensor]:
        return iter((self.value, self.gradient, self.hessian, self.terminal_value, self.terminal_gradient,
                     self.terminal_hessian))


def quadratize_cost(stage_cost: Callable, terminal_cost: Callable, X: Tensor, U: Tensor, params: Params) -> Expansion:
    """Second-order expansion of the costs ``l(x_k, u_k)`` and ``l_N(x_N)`` at every stage of ``(X, U)``."""
    stage = stage_hessian(stage_cost, X, U, params)
    terminal = terminal_hessian(terminal_cost, X[:, -1], params)
    return Expansion(*stage, *terminal)


def lagrangian_hessian(
    stage_lagrangian: Callable,
    terminal_lagrangian: Callable,
    X: Tensor,
    U: Tensor,
    params: Params,
    stage_weights: Tensor,
    terminal_weights: Tensor,
):
    """Hessians of the stage and terminal Lagrangians.

    ``stage_lagrangian(x, u, w, p) -> ()`` and ``terminal_lagrangian(x, w, p) -> ()`` take per-stage
    multiplier vectors ``w`` (``stage_weights (B, N, mw)``, ``terminal_weights (B, mwN)``), e.g.
    ``w = (λ_{k+1}, ν_k, μ_k)``. Returns ``(H (B, N, nz, nz), H_N (B, nx, nx))``. Traced by ``torch.compile``, the
    Hessians of pullbacks of the mapped Lagrangians (as :func:`stage_hessian`'s), equal to rounding.
    """
    nx = X.shape[-1]
    Z = _stage_points(X, U)
    nz = Z.shape[-1]
    if torch.compiler.is_compiling():  # pullbacks outside vmap: jacrev inside it would specialise the batch size
        def mapped_stage(Z_):
            return map_state(lambda zw, p: stage_lagrangian(zw[:nx], zw[nx:nz], zw[nz:], p),
                             torch.cat([Z_, stage_weights], -1), params)

        def mapped_terminal(X_):
            return map_state(lambda xw, p: terminal_lagrangian(xw[:nx], xw[nx:], p),
                             torch.cat([X_, terminal_weights], -1), params)

        return _pullback_hessian(mapped_stage, Z)[2], _pullback_hessian(mapped_terminal, X[:, -1])[2]

    def stage(zw, p):
        z, w = zw[:nz], zw[nz:]
        return jacrev(jacrev(lambda z_: stage_lagrangian(z_[:nx], z_[nx:], w, p)))(z)

    def terminal(xw, p):
        x, w = xw[:nx], xw[nx:]
        return jacrev(jacrev(lambda x_: terminal_lagrangian(x_, w, p)))(x)

    H = map_state(stage, torch.cat([Z, stage_weights], -1), params)
    HN = map_state(terminal, torch.cat([X[:, -1], terminal_weights], -1), params)
    return H, HN


def _problem_lagrangians(problem, constraints, nx: int):
    """Per-instance stage and terminal Lagrangians of ``problem`` with stacked multiplier vectors:
    ``L_k(x, u, w) = l + λ_{k+1}ᵀ f + νᵀ h + μᵀ g`` with ``w = (λ_{k+1}, ν, μ)``, and
    ``L_N(x, w) = l_N + ν_Nᵀ h_N + μ_Nᵀ g_N`` with ``w = (ν_N, μ_N)``."""
    me, mi = constraints.me, constraints.mi

    def stage(x, u, w, p):
        lam, v, m = w[:nx], w[nx:nx + me], w[nx + me:]
        out = problem.stage_cost(x, u, p) + (lam * problem.dynamics(x, u, p)).sum()
        if me:
            out = out + (v * constraints.stage_eq(x, u, p)).sum()
        if mi:
            out = out + (m * constraints.stage_ineq(x, u, p)).sum()
        return out

    def terminal(x, w, p):
        v, m = w[:constraints.meN], w[constraints.meN:]
        out = problem.terminal_cost(x, p)
        if constraints.meN:
            out = out + (v * constraints.terminal_eq(x, p)).sum()
        if constraints.miN:
            out = out + (m * constraints.terminal_ineq(x, p)).sum()
        return out

    return stage, terminal


def weight_blocks(constraints, X: Tensor, U: Tensor, costate: Tensor, nu, mu, nuN, muN) -> tuple:
    """The stage weights ``(λ_{k+1}, ν_k, μ_k)`` and terminal ones ``(ν_N, μ_N)`` of the Lagrangians: missing
    multipliers of existing rows zero (their terms are then added as zeros, as the values were given), ``None`` for a
    block without rows, whose term is never added; ``μ_k`` masked to the knots where its rows apply."""
    B, N = U.shape[:2]
    me, mi, meN, miN = constraints.me, constraints.mi, constraints.meN, constraints.miN
    nu = (X.new_zeros(B, N, me) if nu is None else nu) if me else None
    mu = (X.new_zeros(B, N, mi) if mu is None else mu * constraints.ineq_knot_mask) if mi else None
    nuN = (X.new_zeros(B, meN) if nuN is None else nuN) if meN else None
    muN = (X.new_zeros(B, miN) if muN is None else muN) if miN else None
    return (costate[:, 1:], nu, mu), (nuN, muN)


def _stacked_weights(constraints, X, U, costate, nu, mu, nuN, muN):
    """:func:`weight_blocks` side by side: ``(B, N, nx + me + mi)`` and ``(B, meN + miN)``."""
    stage, terminal = weight_blocks(constraints, X, U, costate, nu, mu, nuN, muN)
    terminal = [w for w in terminal if w is not None]
    return (torch.cat([w for w in stage if w is not None], -1),
            torch.cat(terminal, -1) if terminal else X.new_zeros(X.shape[0], 0))


def problem_lagrangian_hessian(problem, constraints, X, U, params, costate, nu=None, mu=None, nuN=None, muN=None):
    """Hessians of the Lagrangian of ``problem`` at ``(X, U)``.

    ``L_k = l(x, u) + λ_{k+1}ᵀ f(x, u) + ν_kᵀ h(x, u) + μ_kᵀ g(x, u)`` and
    ``L_N = l_N(x) + ν_Nᵀ h_N(x) + μ_Nᵀ g_N(x)`` with ``costate (B, N+1, nx)`` (λ), stage
    multipliers ``nu (B, N, me)``, ``mu (B, N, mi)`` and terminal ``nuN (B, meN)``, ``muN (B, miN)``
    in the layout of :class:`~torchtraj.core.constraints.Constraints` (missing ones are zero).
    Returns ``(H (B, N, nx+nu, nx+nu), H_N (B, nx, nx))``.
    """
    stage, terminal = _problem_lagrangians(problem, constraints, X.shape[-1])
    stage_w, terminal_w = _stacked_weights(constraints, X, U, costate, nu, mu, nuN, muN)
    return lagrangian_hessian(stage, terminal, X, U, params, stage_w, terminal_w)


def problem_lagrangian_expansion(problem, constraints, X, U, params, costate, nu=None, mu=None, nuN=None,
                                 muN=None) -> Expansion:
    """Values, gradients and Hessians of the Lagrangians of :func:`problem_lagrangian_hessian` (the
    ``-λ_kᵀ x_k`` terms of the dynamics rows are left to the caller): ``L (B, N)``, ``L_z (B, N, nz)``,
    ``L_zz (B, N, nz, nz)``, ``L_N (B,)``, ``L_Nx (B, nx)``, ``L_Nxx (B, nx, nx)`` as an :class:`Expansion`.
    """
    nx = X.shape[-1]
    stage, terminal = _problem_lagrangians(problem, constraints, nx)
    stage_w, terminal_w = _stacked_weights(constraints, X, U, costate, nu, mu, nuN, muN)
    Z = _stage_points(X, U)
    nz = Z.shape[-1]

    def stage_vgh(zw, p):
        w = zw[nz:]
        return _value_gradient_hessian(lambda z, p_: stage(z[:nx], z[nx:], w, p_))(zw[:nz], p)

    def terminal_vgh(xw, p):
        w = xw[nx:]
        return _value_gradient_hessian(lambda x, p_: terminal(x, w, p_))(xw[:nx], p)

    L, Lz, Lzz = map_state(stage_vgh, torch.cat([Z, stage_w], -1), params)
    LN, LNx, LNxx = map_state(terminal_vgh, torch.cat([X[:, -1], terminal_w], -1), params)
    return Expansion(L, Lz, Lzz, LN, LNx, LNxx)
