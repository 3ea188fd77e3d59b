r"""The primal-dual Newton step of the barrier problem as an LQR problem (FATROP §II-B eqs. 6-9, §III).

The barrier problem's primal-dual Newton step (FATROP eq. 6) with the inequality multipliers ``z`` (the multiplier
``y`` of ``g + s = 0`` is the bound multiplier of ``s`` at stationarity in ``s``), after eliminating ``Δs`` and ``Δz``
(eqs. 7-8), is the equality-constrained LQR problem (eq. 9)

.. math::

    H_k = ∇^2_{z_k z_k} \mathcal L + G_k^T Σ_k G_k + δ_w I,\quad
    \begin{bmatrix} q_k \\ r_k \end{bmatrix} = ∇_{z_k} \mathcal L + G_k^T S_k^{-1} (μ e + Z_k g_k),\quad
    Σ_k = S_k^{-1} Z_k,

with the dynamics linearised around the (possibly defective) trajectory — the defects ``f(x_k, u_k) − x_{k+1}``
are the affine terms ``c_k`` — and the equality rows ``h`` as stagewise constraints of the shared Riccati core
(:mod:`torchtraj.riccati`). Because the linear terms are the *whole* Lagrangian gradient ``∇\mathcal L``
(costates ``λ``, equality multipliers ``ν``, ``z``), the core's costates and constraint multipliers are the steps
``Δλ``, ``Δν``. Then (eq. 8)

.. math::  Δs = −(g + s) − G Δw, \qquad Δz = S^{-1} (μ e + Z g + Z G Δw).

A complementarity target other than ``μ e`` row by row (Mehrotra's corrector, :mod:`~torchtraj.solvers.ipm.barrier`)
changes the right-hand side alone.

**Inertia correction** (FATROP §III "Hessian regularization"; Wächter & Biegler 2006 §3.1): the Riccati recursion
reports whether every reduced Hessian is positive definite (``RiccatiFactor.ok``); if not, ``δ_w`` grows by
IPOPT's rule (:func:`~torchtraj.globalization.regularization.inertia_correction`) and the batch is factorised
again, instances that already succeeded keeping their factor.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from ...core.compiled import matmul as _mm
from ...core.compiled import matvec as _mv
from ...core.constraints import Constraints
from ...core.graphs import capturing
from ...globalization.regularization import corrected_attempts
from ...kkt import newton as kkt_newton
from ...riccati import LQR, LQRVectors, RiccatiFactor, all_finite, factorize, sweep_for_batch
from ...riccati.range_space import TerminalGains, gains_of
from .compaction import gather_laid_out, kernel_rows, pick, write_rows
from .iterate import Iterate, Model
from .options import IPOptions


def _targets(mu: Tensor, target: Optional[tuple]):
    """The complementarity targets ``(stage (B, N|1, mi|1), terminal (B, miN|1))``: ``μ`` on every row, or
    ``target``."""
    return (mu.reshape(-1, 1, 1), mu.unsqueeze(-1)) if target is None else target


def newton_lqr(model: Model, it: Iterate, mu: Tensor, x0: Tensor, nx: int, target: Optional[tuple] = None):
    """The reduced primal-dual system (FATROP eq. 9) as LQR matrices (without ``δ_w``) and right-hand side
    (:func:`newton_rhs`)."""
    sigma = it.z / it.s  # rows off at a knot: z = 0
    sigmaN = it.zN / it.sN
    H = model.Lzz + _mm(model.Gz.transpose(-1, -2), sigma.unsqueeze(-1) * model.Gz)
    HN = model.LNxx + _mm(model.GN.transpose(-1, -2), sigmaN.unsqueeze(-1) * model.GN)
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    # the equality rows alone are held: the inequalities are in the barrier-augmented Hessian
    lqr = kkt_newton.held_lqr(model.fz, H, HN, rows=model.Hz if me else None, rowsN=model.HN if meN else None)
    return lqr, newton_rhs(model, it, mu, x0, nx, target)


def newton_rhs(model: Model, it: Iterate, mu: Tensor, x0: Tensor, nx: int, target: Optional[tuple] = None):
    """The right-hand side of the reduced system for the complementarity ``S z = μ`` or, given, ``S z = target``
    row by row (:func:`_targets`)."""
    m, mN = _targets(mu, target)
    barrier = (it.z - it.y + (m + it.z * model.g) / it.s) * model.knots  # zero on rows that are off
    grad = model.Lz + _mv(model.Gz.transpose(-1, -2), barrier)
    grad = torch.cat([grad[..., :nx] - it.lam[:, :-1], grad[..., nx:]], -1)
    barrierN = it.zN - it.yN + (mN + it.zN * model.gN) / it.sN
    gradN = model.LNx - it.lam[:, -1] + _mv(model.GN.transpose(-1, -2), barrierN)
    me, meN = model.h.shape[-1], model.hN.shape[-1]
    return kkt_newton.newton_rhs(grad, gradN, model.f - it.X[:, 1:], x0 - it.X[:, 0], model.h if me else None,
                                 model.hN if meN else None)


@dataclass
class Direction:
    """The Newton step of every primal-dual variable (each shaped as its :class:`Iterate` field), the feedback
    gains of the factorised system (``(B, N, nu, nx)``, or with terminal rows by the range-space method their
    parts, :class:`~torchtraj.riccati.range_space.TerminalGains`, formed when the solution is made) and
    ``ok (B,)``: its reduced Hessians were positive definite and the step is finite."""

    dX: Tensor
    dU: Tensor
    ds: Tensor
    dsN: Tensor
    dz: Tensor
    dzN: Tensor
    dy: Tensor
    dyN: Tensor
    dlam: Tensor
    dnu: Tensor
    dnuN: Tensor
    K: "Tensor | TerminalGains"
    ok: Tensor
    factor: Optional[RiccatiFactor] = None  # kept when asked for (a corrector reuses it)


def batch_sweep(opts: IPOptions, cons: Constraints, B: int, N: int, nx: int, nu: int, device) -> IPOptions:
    """``opts`` with ``sweep="auto"`` decided once for the batch of ``B`` (:func:`~torchtraj.riccati.sweep_for_batch`;
    sequential where rows are back-propagated: stage equality rows, or terminal ones with
    ``terminal_rows="back-propagation"``). A factorisation of the running or pending instances alone (the batch's
    compaction, the corrections by rows) then takes the same sweep, so that an instance's round-off does not
    depend on how many others are still iterating."""
    if opts.sweep != "auto":
        return opts
    propagated = cons.me > 0 or (cons.meN > 0 and opts.terminal_rows == "back-propagation")
    return dataclasses.replace(opts, sweep="sequential" if propagated else sweep_for_batch(B, N, nx, nu, device))


def factorize_step(lqr: LQR, delta: Tensor, opts: IPOptions) -> RiccatiFactor:
    """The factorisation of the reduced system regularised by ``δ_w I`` (``delta (B,)``) with the options' Riccati
    ``sweep`` and ``terminal_rows``."""
    return factorize(lqr, shift=delta, sweep=opts.sweep, terminal_rows=opts.terminal_rows)


def direction(lqr: LQR, rhs: LQRVectors, delta: Tensor, model: Model, it: Iterate, mu: Tensor,
              target: Optional[tuple] = None, factor: Optional[RiccatiFactor] = None,
              keep_factor: bool = False, sweep: str = "sequential",
              terminal_rows: str = "back-propagation") -> Direction:
    """Factorise the system regularised by ``δ_w I`` (``delta (B,)``; or take its ``factor``) with the Riccati
    ``sweep`` and ``terminal_rows`` (``IPOptions``), solve it and recover ``Δs``, ``Δz`` (FATROP eq. 8) for the
    complementarity ``μ`` or ``target`` (:func:`newton_rhs`)."""
    factor = factorize(lqr, shift=delta, sweep=sweep, terminal_rows=terminal_rows) if factor is None else factor
    if _none_factorised(factor):  # an attempt of the inertia correction that failed for every instance
        return _failed(it, factor, keep_factor)
    sol = factor.solve(rhs, multipliers=True)
    dX, dU = sol.dx, sol.du
    dw = torch.cat([dX[:, :-1], dU], -1)
    Gdw = _mv(model.Gz, dw)
    GdwN = _mv(model.GN, dX[:, -1])
    on = model.knots
    m, mN = _targets(mu, target)
    ds = (-(model.g + it.s) - Gdw) * on
    dz = (m + it.z * model.g + it.z * Gdw) / it.s * on
    dsN = -(model.gN + it.sN) - GdwN
    dzN = (mN + it.zN * model.gN + it.zN * GdwN) / it.sN
    dnu = sol.nu if sol.nu is not None else it.nu.new_zeros(it.nu.shape)
    dnuN = sol.nuN if sol.nuN is not None else it.nuN.new_zeros(it.nuN.shape)
    finite = all_finite([dX, dU, sol.costate])
    # the full step takes the multipliers y of g + s = 0 to z + Δz (stationarity in s)
    dy, dyN = (it.z + dz - it.y) * on, it.zN + dzN - it.yN
    return Direction(dX=dX, dU=dU, ds=ds, dsN=dsN, dz=dz, dzN=dzN, dy=dy, dyN=dyN, dlam=sol.costate, dnu=dnu,
                     dnuN=dnuN, K=gains_of(factor), ok=factor.ok & finite, factor=factor if keep_factor else None)


def newton_direction(model: Model, it: Iterate, mu: Tensor, x0: Tensor, delta: Tensor, sweep: str = "sequential",
                     terminal_rows: str = "back-propagation") -> Direction:
    """:func:`newton_lqr` and :func:`direction` in one function: the Newton step of a compiled solve
    (``IPOptions.compile``), whose kernel forms the reduced system from the model itself, so that its matrices and
    right-hand side are not some eighty eager calls an iteration between kernels."""
    lqr, rhs = newton_lqr(model, it, mu, x0, it.X.shape[-1])
    return direction(lqr, rhs, delta, model, it, mu, None, None, False, sweep, terminal_rows)


def direction_of_rows(newton_k: Callable[..., Direction], model: Model, it: Iterate, mu: Tensor, x0: Tensor,
                      delta: Tensor, rows: Tensor, sweep: str, terminal_rows: str) -> Direction:
    """The Newton step of a compiled solve (``newton_k``, the kernel of :func:`newton_direction`) of the instances
    ``rows (R,)`` alone: an inertia correction's later attempt, whose other instances have their step. Their rows
    are gathered laid out as the batch's (:func:`~torchtraj.solvers.ipm.compaction.gather_laid_out`), as many as a
    kernel takes (:func:`~torchtraj.solvers.ipm.compaction.kernel_rows`: a single instance taken twice, its step kept
    once), so that the kernels compiled for the batch serve every count; each instance's arithmetic is the same."""
    index = kernel_rows(rows)
    d = newton_k(*(gather_laid_out(v, index) for v in (model, it, mu, x0, delta)), sweep, terminal_rows)
    return d if index is rows else gather_laid_out(d, torch.arange(rows.numel(), device=rows.device))


def _none_factorised(factor: RiccatiFactor) -> bool:
    """Whether no instance's system is positive definite, read where a host read costs nothing: eager and on a
    CPU (a traced kernel or a captured graph cannot read it, and on an accelerator it would wait for the device)."""
    ok = factor.ok
    return ok.device.type == "cpu" and not torch.compiler.is_compiling() and not capturing() and not bool(ok.any())


def _failed(it: Iterate, factor: RiccatiFactor, keep_factor: bool) -> Direction:
    """The step of an attempt that no instance passed: zero, not ``ok``; its solve would be thrown away (the
    inertia correction takes an attempt's step only where it is ``ok``, and an instance whose attempts all fail
    stops without one)."""
    zero = torch.zeros_like
    return Direction(dX=zero(it.X), dU=zero(it.U), ds=zero(it.s), dsN=zero(it.sN), dz=zero(it.z), dzN=zero(it.zN),
                     dy=zero(it.y), dyN=zero(it.yN), dlam=zero(it.lam), dnu=zero(it.nu), dnuN=zero(it.nuN),
                     K=gains_of(factor), ok=factor.ok, factor=factor if keep_factor else None)


def regularized_direction(attempt: Callable[..., Direction], floor: Tensor, last: Tensor, running: Tensor,
                          opts: IPOptions, by_rows: bool = False, first: Optional[Direction] = None) -> tuple:
    """The step of every ``running (B,)`` instance with the smallest ``δ_w`` (from ``floor (B,)``) whose system is
    positive definite, by IPOPT's inertia correction
    (:func:`~torchtraj.globalization.regularization.corrected_attempts`; ``last (B,)``: the last nonzero ``δ_w`` that
    was); ``attempt(δ_w)`` factorises and solves the batch. ``by_rows``: the attempts after the first take the
    pending instances alone, ``attempt(δ_w, rows)`` (``corrected_attempts``' ``write``, here :func:`write_rows`).
    ``first``: the step of the first attempt, made already (a compiled iteration's one kernel call). Returns
    ``(direction, δ_w (B,))``."""
    return corrected_attempts(attempt, floor, last, running, opts, pick, opts.regularization_attempts,
                              write_rows if by_rows else None, first)
