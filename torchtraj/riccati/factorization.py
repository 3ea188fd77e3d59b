r"""The matrix part of the Riccati recursion: one backward sweep that any number of right-hand sides reuse.

With the stage blocks stacked over ``z = (δx, δu)``, ``W_k = [A_k B_k]`` and ``H_k = [[Q_k, S_kᵀ], [S_k, R_k]]``,
each stage forms the Q-function's Hessian by one congruence and the value function's by another
(ALTRO, Howell et al. 2019 eqs. 14-15):

.. math::

    \begin{bmatrix} Q_{xx} & Q_{xu} \\ Q_{ux} & Q_{uu} \end{bmatrix} = H_k + W_k^T P_{k+1} W_k,\qquad
    K_k = -(Q_{uu} + \rho I)^{-1} Q_{ux},\qquad
    P_k = E^T \begin{bmatrix} Q_{xx} & Q_{xu} \\ Q_{ux} & Q_{uu} \end{bmatrix} E,\quad
    E = \begin{bmatrix} I \\ K_k \end{bmatrix},\quad P_N = Q_N.

``ρ`` regularises the gains only (ALTRO eq. 13): ``P_k`` is the unregularised value function along them. Stage
rows change the gain: back-propagated (:mod:`~torchtraj.riccati.propagation`) or declared simple bounds
(:mod:`~torchtraj.riccati.bounds`). Where some stage's reduced Hessian is not positive definite, the instance is
flagged (``RiccatiFactor.ok``) and its factor replaced by the identity; instances with non-finite entries are
swapped for a benign problem first (:mod:`~torchtraj.riccati.sanitize`): neither disturbs the other instances.
"""

from __future__ import annotations

from typing import Optional

from torch import Tensor

from .bounds import _held_controls
from .factor import RiccatiFactor
from .lqr import LQR, LQRSolution, LQRVectors
from .parallel import ParallelRiccatiFactor, choose_sweep, factorize_parallel
from .propagation import _stage_rows, _terminal_constraint, default_rank_tolerance
from .range_space import TERMINAL_ROWS, applies, factorize_range_space, penalised
from .rows import factorize_rows
from .sanitize import _sanitize_stacked
from .sweep import factorize_stages, finish_single


def factorize(lqr: LQR, regularization: Optional[Tensor] = None, rank_tolerance: Optional[float] = None,
              shift: Optional[Tensor] = None, sweep: str = "sequential",
              terminal_rows: str = "back-propagation") -> RiccatiFactor:
    """Backward Riccati sweep over the matrices of ``lqr``.

    Args:
        lqr: the batched LQR matrices.
        regularization: ``ρ (B,)`` added to ``Q_uu`` (ALTRO eq. 13) for the gains; the value function
            uses the unregularised ``Q_uu``.
        rank_tolerance: relative singular-value threshold for constraint rows; default
            :func:`default_rank_tolerance`.
        shift: ``δ (B,)`` added to the whole Hessian, every ``Q``, ``R`` and ``QN`` (IPOPT's inertia
            correction ``δ_w I``): the factorised problem, and the returned ``lqr``, are the shifted one.
        sweep: ``"sequential"`` (this backward sweep), ``"parallel"`` (the associative-scan sweep of
            :mod:`~torchtraj.riccati.parallel`, O(log N) deep; no back-propagated rows) or ``"auto"``
            (:func:`~torchtraj.riccati.parallel.choose_sweep`).
        terminal_rows: ``"back-propagation"`` (the rows take the constraint back-propagation) or
            ``"range-space"``: where the only rows are terminal ones and there is no ``regularization``, the
            unconstrained ``sweep`` and the Schur complement of the rows
            (:mod:`~torchtraj.riccati.range_space`), a :class:`~torchtraj.riccati.range_space.RangeSpaceFactor`.
    """
    if terminal_rows not in TERMINAL_ROWS:
        raise ValueError(f"terminal_rows must be one of {TERMINAL_ROWS}, not {terminal_rows!r}")
    if terminal_rows == "range-space" and applies(lqr, regularization):
        tol = default_rank_tolerance(lqr.A.dtype) if rank_tolerance is None else rank_tolerance
        unconstrained, correction = penalised(lqr, tol)
        return factorize_range_space(factorize(unconstrained, shift=shift, sweep=sweep), lqr, correction, tol)
    if sweep != "sequential" and choose_sweep(lqr, sweep) == "parallel":
        factor = factorize_parallel(lqr, regularization, shift)
        return factor if regularization is not None else _sequential_where_refused(factor, lqr, shift)
    exact = regularization is None and not lqr.propagated
    lqr, finite, W, Hs = _sanitize_stacked(lqr, shift)
    Bsz, nu = lqr.B.shape[0], lqr.B.shape[-1]
    dtype = lqr.A.dtype
    tol = default_rank_tolerance(dtype) if rank_tolerance is None else rank_tolerance
    if regularization is None:
        regularization = lqr.A.new_zeros(Bsz)
    held = _held_controls(lqr, dtype) if lqr.bounds is not None else None
    if not lqr.propagated:
        P, K, Quu, Qux, chol, ok = factorize_stages(W, Hs, lqr.QN, regularization, held)
        if nu == 1:
            chol, ok = finish_single(chol, ok)
        return RiccatiFactor(lqr=lqr, K=K, P=P, ok=finite & ok, Quu=Quu, Qux=Qux, chol=chol, free=None, stage=None,
                             terminal=None, exact=exact, fixed=held, W=W.transpose(0, 1))
    return _factorize_propagated(lqr, finite, W, Hs, regularization, tol)


def _sequential_where_refused(factor: ParallelRiccatiFactor, lqr: LQR,
                              shift: Optional[Tensor]) -> ParallelRiccatiFactor:
    """``factor`` with the instances it flags not ``ok`` factorised again by the sequential sweep.

    The parallel sweep asks every stage's own control Hessian ``R̃`` to be positive definite as well as the
    reduced ``Q_uu`` (:mod:`~torchtraj.riccati.parallel`); the sequential sweep asks only the latter, which is
    the inertia test of the Newton system. An instance whose ``R̃`` is indefinite while every ``Q_uu`` is
    positive definite (a nonconvex stage cost that the dynamics make convex) therefore takes the sequential
    sweep's factor, and the verdict ``ok`` is the sequential sweep's for every instance. An instance whose
    ``Q_uu`` failed the test where the scan's value functions are the sequential sweep's to round-off
    (:meth:`~torchtraj.riccati.parallel.ParallelRiccatiFactor.settled`) keeps the verdict without a second
    factorisation. Without ``regularization`` both sweeps factorise the same system, so the mixed factor solves it
    for all instances; each instance's factor depends on its own data only. Costs one host synchronisation (the
    count of refused instances) a factorisation, and one more where some were refused."""
    index = (~factor.ok).nonzero().squeeze(-1)
    if index.numel() == 0:
        return factor
    index = index[~factor.settled(index)]
    if index.numel() == 0:
        return factor
    rows = factorize(lqr.rows(index), shift=None if shift is None else shift[index])
    return factor.with_rows(index, rows)


def _factorize_propagated(lqr: LQR, finite: Tensor, W: Tensor, Hs: Tensor, regularization: Tensor,
                          tol: float) -> RiccatiFactor:
    """The matrix sweep with back-propagated rows (:mod:`~torchtraj.riccati.rows`)."""
    terminal = _terminal_constraint(lqr, tol)
    P, K, Quu, Qux, chol, ok, stage, sweep = factorize_rows(W, Hs, lqr.QN, _stage_rows(lqr), terminal.G,
                                                            regularization, tol)
    return RiccatiFactor(lqr=lqr, K=K, P=P, ok=finite & ok, Quu=Quu, Qux=Qux, chol=chol, free=sweep["Vf"],
                         stage=stage, terminal=terminal, exact=False, fixed=None, W=W.transpose(0, 1), rows=sweep)


def solve_lqr(lqr: LQR, rhs: LQRVectors, regularization: Optional[Tensor] = None,
              multipliers: bool = False, sweep: str = "sequential") -> LQRSolution:
    """Factorise and solve in one call (see :func:`factorize` and :meth:`RiccatiFactor.solve`)."""
    return factorize(lqr, regularization, sweep=sweep).solve(rhs, multipliers=multipliers)
