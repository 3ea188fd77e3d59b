r"""The Newton step of eILQR (Horizon §II-A to §II-E): one factorisation of the linearised KKT system by the shared
Riccati core, one backward pass with constraint back-propagation and one forward pass.

Linearising the KKT conditions of :mod:`~torchtraj.solvers.eilqr.model` at the iterate gives, stage by stage, the
equality-constrained LQR problem

.. math::

    \min \sum_k \tfrac12 δz_k^T (∇^2_{zz} L_k + ε I) δz_k + ∇\ell_k^T δz_k + \tfrac12 δx_N^T (∇^2 L_N + ε I) δx_N
        + ∇\ell_N^T δx_N
    \ \text{s.t.}\ δx_{k+1} = A_k δx_k + B_k δu_k + (f_k − x_{k+1}),\ C_k δx_k + D_k δu_k + h_k = 0,\
    C_N δx_N + h_N = 0,

with the defects as affine terms (multiple shooting, §II-E: any ``X0`` is a valid start) and ``δx_0 = x̄_0 − x_0``
or, with a free initial state, ``δx_0`` from the stage-0 system (:mod:`~torchtraj.solvers.eilqr.initial_state`).
It is :func:`torchtraj.kkt.newton.held_lqr` with every equality row held, solved by
:func:`torchtraj.kkt.newton.newton_step`; with the *cost* gradient as the linear term, the core's costates and row
multipliers are the new estimates ``λ⁺ = λ + δλ``, ``ν⁺ = ν + δμ`` (eqs. 6-7). ``ε I`` is the regularisation
(``ε_reg`` of the paper's Fig. 5): where a reduced Hessian is not positive definite (``RiccatiFactor.ok``, and the
stage-0 system's inertia) it rises by IPOPT's inertia correction and the instance is factorised again.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from ...core.batching import rows_of
from ...core.compiled import kernel
from ...globalization.regularization import corrected_attempts
from ...kkt.newton import held_lqr, newton_rhs, newton_step
from ...riccati import RiccatiFactor, all_finite
from ...riccati.range_space import TerminalGains, gains_of, select_gains
from .initial_state import initial_step
from .model import Iterate, Model
from .options import EILQROptions


@dataclass
class Direction:
    """The step ``dX (B, N+1, nx)``, ``dU (B, N, nu)``, the new multiplier estimates ``lam``, ``nu``, ``nuN``,
    ``mu0``, ``z``, ``zN`` (shaped as the :class:`~torchtraj.solvers.eilqr.model.Iterate`'s), the gains
    ``K (B, N, nu, nx)`` (with terminal rows by the range-space method their parts,
    :class:`~torchtraj.riccati.range_space.TerminalGains`, formed when the solution is made) and ``ok (B,)``:
    positive definite reduced Hessians and a finite step."""

    dX: Tensor
    dU: Tensor
    lam: Tensor
    nu: Tensor
    nuN: Tensor
    mu0: Tensor
    z: Tensor
    zN: Tensor
    K: "Tensor | TerminalGains"
    ok: Tensor
    #: the factorisation every instance's step came from (``None`` where the instances' steps come from several)
    factor: Optional[RiccatiFactor] = None


def _shifted(H: Tensor, eps: Tensor) -> Tensor:
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    return H + eps.reshape(-1, *([1] * (H.dim() - 1))) * eye


def _rhs(model: Model, it: Iterate, x0: Tensor):
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    start = torch.zeros_like(x0) if model.initial is not None else x0 - it.X[:, 0]
    return newton_rhs(model.lz, model.lNx, model.defects, start, model.h if me else None, model.hN if meN else None)


def direction(model: Model, it: Iterate, x0: Tensor, eps: Tensor,
              terminal_rows: str = "back-propagation") -> Direction:
    """The Newton step at ``it`` with the Hessian regularised by ``eps (B,)``; ``terminal_rows`` as
    :attr:`EILQROptions.terminal_rows <torchtraj.solvers.eilqr.options.EILQROptions>` (the range-space method only
    with a fixed initial state: a free start's stage-0 system reads the rows the back-propagation leaves there)."""
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    lqr = held_lqr(model.fz, _shifted(model.Lzz, eps), _shifted(model.LNxx, eps), rows=model.Hz if me else None,
                   rowsN=model.HN if meN else None)
    rhs = _rhs(model, it, x0)
    rows = terminal_rows if model.initial is None else "back-propagation"
    ns = newton_step(lqr, rhs, multipliers=model.initial is None, terminal_rows=rows)
    return _completed(ns.factor, rhs, ns.step, model, it)


def direction_alone(model: Model, it: Iterate, x0: Tensor, eps: Tensor,
                    terminal_rows: str = "back-propagation") -> Direction:
    """:func:`direction` without its factorisation (a compiled kernel hands back tensors only): a second-order
    correction then factorises its system again (the same ``ε``, the same arithmetic)."""
    return dataclasses.replace(direction(model, it, x0, eps, terminal_rows), factor=None)


def compiled_direction(enabled: bool) -> Callable[..., Direction]:
    """:func:`direction`, or (``enabled``, ``EILQROptions.compile``) its compiled kernel, which keeps no
    factorisation (:func:`direction_alone`)."""
    return kernel(direction_alone, True) if enabled else direction


def resolve(d: Direction, model: Model, it: Iterate, x0: Tensor) -> Direction:
    """The step of ``d``'s factorised system for the right-hand side of ``model`` (other constraint values: the
    second-order correction), one vector solve; ``d.factor`` must be kept (:func:`regularized_direction`)."""
    rhs = _rhs(model, it, x0)
    return _completed(d.factor, rhs, d.factor.solve(rhs, multipliers=model.initial is None), model, it)


def _completed(factor, rhs, step, model: Model, it: Iterate) -> Direction:
    """The :class:`Direction` of one solve; with a free start (§II-D), ``δx_0`` and ``η_0`` from the stage-0
    system and the forward pass again from them."""
    ok, mu0 = factor.ok, it.mu0
    if model.initial is not None:
        first = initial_step(factor, step, model.initial)
        step = factor.solve(dataclasses.replace(rhs, x0=first.dx0), multipliers=True, initial_multiplier=first.eta0)
        ok, mu0 = ok & first.ok, first.mu0
    nu = step.nu if step.nu is not None else it.nu
    nuN = step.nuN if step.nuN is not None else it.nuN
    ok = ok & all_finite([step.dx, step.du, step.costate])
    # the inequality rows' new multipliers, z⁺ = w s(t) + σ G δz (the primal-dual step: continuation module)
    ineq = model.rows
    dz = torch.cat([step.dx[:, :-1], step.du], -1)
    z = (model.zw + model.sigma * (ineq.G @ dz.unsqueeze(-1)).squeeze(-1)) * ineq.mask
    zN = model.zwN + model.sigmaN * (ineq.GN @ step.dx[:, -1].unsqueeze(-1)).squeeze(-1)
    return Direction(dX=step.dx, dU=step.du, lam=step.costate, nu=nu, nuN=nuN, mu0=mu0, z=z, zN=zN, K=gains_of(factor),
                     ok=ok, factor=factor)


#: the fields of a :class:`Direction` that hold its instances' values (not the shared factorisation)
_PER_INSTANCE = tuple(f.name for f in dataclasses.fields(Direction) if f.name != "factor")


def pick_direction(mask: Tensor, new: Direction, old: Direction) -> Direction:
    """``new`` for the instances of ``mask (B,)``, ``old`` elsewhere (no single factorisation is left)."""
    return Direction(**{name: select_gains(mask, getattr(new, name), getattr(old, name)) for name in _PER_INSTANCE})


def regularized_direction(attempt: Callable[..., Direction], floor: Tensor, last: Tensor, running: Tensor,
                          opts: EILQROptions, regularize: bool = True) -> tuple:
    """The step of every ``running (B,)`` instance with the smallest ``ε`` from ``floor (B,)`` up whose reduced
    Hessians are positive definite (IPOPT's inertia correction from ``last (B,)``, the last nonzero ``ε`` that
    worked: :func:`~torchtraj.globalization.regularization.corrected_attempts`); ``regularize=False`` takes the
    first attempt as it is. ``attempt(ε)`` factorises and solves the batch, ``attempt(ε, rows)`` the instances
    ``rows`` alone, which the attempts after the first take (``corrected_attempts``' ``write``, here
    :func:`write_direction`). Returns ``(direction, ε (B,))``, ``ε`` never ``floor`` itself (a kernel given both
    would see one tensor twice: a graph of its own, and Dynamo's reason for compiling it again failed on another
    problem's parameters)."""
    d, eps = corrected_attempts(attempt, floor, last, running, opts, pick_direction,
                                opts.regularization_attempts if regularize else 0, write_direction)
    return d, (eps.clone() if eps is floor else eps)


def write_direction(step: Direction, rows: Tensor, new: Direction) -> Direction:
    """``step`` with the instances ``rows (R,)`` replaced by ``new``'s (a direction of those instances alone; no
    single factorisation is left)."""
    return Direction(**{name: getattr(step, name).index_copy(0, rows, getattr(new, name)) for name in _PER_INSTANCE})


def instances(value, rows: Tensor):
    """The instances ``rows (R,)`` of a :class:`~torchtraj.solvers.eilqr.model.Model`,
    :class:`~torchtraj.solvers.eilqr.model.Iterate` or :class:`Direction`
    (:func:`~torchtraj.core.batching.rows_of`): the rows' knot mask ``(N, mi)`` is the batch's, a direction's
    factorisation is not taken apart (``None``)."""
    return rows_of(value, rows, shared=("mask",), dropped=("factor",))


def multiplier_size(d: Direction, free: bool) -> Tensor:
    """``max |y⁺| (B,)`` over the new multiplier estimates of every row of the merit: the dynamics (and the fixed
    start's, ``λ_0``), the equalities and a free start's rows."""
    B = d.lam.shape[0]
    parts = [d.lam[:, 1:] if free else d.lam, d.nu, d.nuN, d.mu0]
    return torch.cat([p.reshape(B, -1) for p in parts] + [d.lam.new_zeros(B, 1)], -1).abs().amax(-1)


def empty_multipliers(X: Tensor, me: int, meN: int, m0: Optional[int]) -> tuple:
    """Zero ``λ (B, N+1, nx)``, ``ν (B, N, me)``, ``ν_N (B, meN)``, ``μ_0 (B, m0)``: the start of every solve (the
    inequality rows' start at the barrier's own, :func:`~torchtraj.solvers.eilqr.continuation.barrier_multipliers`)."""
    B, N1, nx = X.shape
    return (X.new_zeros(B, N1, nx), X.new_zeros(B, N1 - 1, me), X.new_zeros(B, meN), X.new_zeros(B, m0 or 0))
