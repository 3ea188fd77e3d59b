r"""The augmented Lagrangian of ALTRO (Howell et al. 2019 §II-A, eqs. 2-3, 5-12, 17-18).

With the stage constraints stacked as ``c_k = (g_k, h_k)`` (inequalities first, then equalities)
and the terminal ones as ``c_N``, the objective the inner iLQR minimises is

.. math::

    \mathcal L_A = \ell_N(x_N) + (\lambda_N + \tfrac12 I_{\mu_N} c_N)^T c_N
        + \sum_{k<N} \ell_k(x_k, u_k) + (\lambda_k + \tfrac12 I_{\mu_k} c_k)^T c_k,

    I_{\mu, ii} = 0 \text{ if } c_i < 0 \wedge \lambda_i = 0 \ (i \in \mathcal I), \quad \mu_i \text{ otherwise.}

Its LQR expansion adds, with linearised constraints (eqs. 5-6, 8-12),
``c_zᵀ I_μ c_z`` to the cost Hessian and ``c_zᵀ (λ + I_μ c)`` to the gradient. Between inner solves the
multipliers follow eq. (17), ``λ ← λ + μ c`` (equalities) and ``λ ← max(0, λ + μ c)``
(inequalities), clipped to ``±dual_max``, and the penalties eq. (18), ``μ ← min(φ μ, μ_max)``.

Inequality rows that do not apply at a knot (state constraints at ``k = 0``, where ``x_0`` is fixed)
are multiplied by zero, so they never contribute and their multipliers stay zero.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import concat, map_stage, map_state
from ...core.constraints import Constraints
from ...core.derivatives import stage_jacobian, terminal_jacobian
from ...core.one_pass import PointValues, problem_kkt_expansion, problem_values
from ...riccati import LQR, LQRVectors
from ...riccati.square_root import psd_root


def _joint(lqr) -> Tensor:
    """``[[Q, Sᵀ], [S, R]] (B, N, nx+nu, nx+nu)``."""
    return torch.cat([torch.cat([lqr.Q, lqr.S.transpose(-1, -2)], -1), torch.cat([lqr.S, lqr.R], -1)], -2)


@dataclass
class Duals:
    """Multipliers ``λ`` and penalties ``μ``: stage ``(B, N, mi + me)``, terminal ``(B, miN + meN)``."""

    stage: Tensor
    terminal: Tensor
    stage_penalty: Tensor
    terminal_penalty: Tensor

    @classmethod
    def initial(cls, constraints: Constraints, batch: int, penalty: float, like: Tensor) -> "Duals":
        N = constraints.problem.N
        m, mN = constraints.mi + constraints.me, constraints.miN + constraints.meN
        stage = like.new_zeros(batch, N, m)
        terminal = like.new_zeros(batch, mN)
        return cls(stage, terminal, torch.full_like(stage, penalty), torch.full_like(terminal, penalty))

    def rows(self, index: Tensor) -> "Duals":
        """The instances ``index`` of the batch."""
        return Duals(self.stage[index], self.terminal[index], self.stage_penalty[index], self.terminal_penalty[index])

    def where(self, mask: Tensor, other: "Duals") -> "Duals":
        """``self`` for the instances in ``mask (B,)``, ``other`` elsewhere."""
        m3, m2 = mask.reshape(-1, 1, 1), mask.reshape(-1, 1)
        return Duals(torch.where(m3, self.stage, other.stage), torch.where(m2, self.terminal, other.terminal),
                     torch.where(m3, self.stage_penalty, other.stage_penalty),
                     torch.where(m2, self.terminal_penalty, other.terminal_penalty))


#: Rounding errors of the trajectory's magnitude that a residual is allowed (:func:`resolution_floor`).
ROUNDING_ERRORS = 10.0


def resolution_floor(X: Tensor, U: Tensor) -> Tensor:
    """``(B,)``: the smallest violation the dtype resolves at ``(X, U)``, ``10 ε max(1, |X|∞, |U|∞)``.

    A defect ``f(x_k, u_k) − x_{k+1}`` or a constraint value is a difference of numbers of the trajectory's
    magnitude, each rounded to ``ε`` of it: in float32 (``ε = 1.2e-7``) a state of order one has defects of 6e-8
    however exactly it was projected, and a tolerance of 1e-8 is never met (the Newton steps stop reducing ``v`` and
    the instance would end ``MAX_ITERATIONS`` at a KKT point). Ten rounding errors, as IPOPT compares values
    (``10 ε |φ|``); in float64 the floor lies far below the default tolerance."""
    scale = torch.cat([X.abs().flatten(1), U.abs().flatten(1), X.new_ones(X.shape[0], 1)], 1).amax(1)
    return ROUNDING_ERRORS * torch.finfo(X.dtype).eps * scale


#: The multiplier update's tolerated error, relative to the trajectory's magnitude (:func:`penalty_limit`).
MULTIPLIER_RESOLUTION = 1e-4


def penalty_limit(penalty_max: float, dtype: torch.dtype) -> float:
    """The largest penalty in ``dtype``: ``penalty_max``, or ``MULTIPLIER_RESOLUTION / ε`` where that is smaller.

    Eq. (17)'s update ``λ + μ c`` carries ``μ`` times the rounding error of ``c``, ``ε`` of the trajectory's
    magnitude, into the multipliers, which AL-iLQR returns as its multiplier estimate. At Altro.jl's cap of 1e8 that
    is 6 in float32 (``ε = 1.2e-7``: a double integrator's estimates were off by 0.2 to 6 at μ = 1e5 to 1e8, its
    stationarity residual as large); capped at 1e-4 / ε ≈ 840 the error stays ten times below float32's certified
    stationarity (1e-3), and the multiplier updates, not the penalty, drive the violation down. In float64 the
    limit (4.5e11) lies above the default ``penalty_max``."""
    return min(penalty_max, MULTIPLIER_RESOLUTION / torch.finfo(dtype).eps)


def _stacked(inequalities: Tensor, equalities: Tensor, dim: int) -> Tensor:
    """The two row blocks one above the other (one of them alone where the other has no rows)."""
    if not equalities.shape[dim]:
        return inequalities
    if not inequalities.shape[dim]:
        return equalities
    return torch.cat([inequalities, equalities], dim)


def _lift(t: Tensor, extra: int) -> Tensor:
    """``(B, ...)`` → ``(B, 1, ..., 1, ...)`` with ``extra`` singleton dimensions after B."""
    return t.reshape(t.shape[0], *([1] * extra), *t.shape[1:])


class AugmentedLagrangian:
    """``L_A`` of ``problem`` for fixed duals; same interface as :class:`~torchtraj.solvers.ilqr.CostObjective`."""

    def __init__(self, constraints: Constraints, duals: Duals, square_root: bool = False,
                 record: Optional[bool] = False):
        self.constraints = constraints
        #: also give the square-root pass the roots of the Hessian terms (``LQR.root``, eqs. 19-21)
        self.square_root = square_root
        #: the expansion replayed from its recorded operator graph (``ILQROptions.record``)
        self.record = record
        self.problem = constraints.problem
        self.duals = duals
        c = constraints
        ones = torch.ones(self.problem.N, c.me, dtype=self.problem.dtype, device=self.problem.device)
        #: ``(N, m)``: 1 where a stage row applies.
        self.knot_mask = torch.cat([c.ineq_knot_mask, ones], -1)
        self.is_ineq = torch.arange(c.mi + c.me, device=self.problem.device) < c.mi
        self.is_ineqN = torch.arange(c.miN + c.meN, device=self.problem.device) < c.miN
        #: number of inequality rows that apply (the mean multiplier of :meth:`complementarity`)
        self.ineq_rows = c.applied_ineq_rows + c.miN  # no host read: the constructor runs in compiled kernels

    def rows(self, index: Tensor) -> "AugmentedLagrangian":
        """``L_A`` of the instances ``index`` of the batch (their duals)."""
        out = copy.copy(self)
        out.duals = self.duals.rows(index)
        return out

    # the stacked per-instance constraint functions
    def stage_fn(self, x: Tensor, u: Tensor, p) -> Tensor:
        return concat([self.constraints.stage_ineq(x, u, p), self.constraints.stage_eq(x, u, p)])

    def terminal_fn(self, x: Tensor, p) -> Tensor:
        return concat([self.constraints.terminal_ineq(x, p), self.constraints.terminal_eq(x, p)])

    @property
    def m(self) -> int:
        return self.constraints.mi + self.constraints.me

    @property
    def mN(self) -> int:
        return self.constraints.miN + self.constraints.meN

    def row_jacobians(self, X: Tensor, U: Tensor, params) -> tuple:
        """``(c (B, N, m), C_z (B, N, m, nx+nu), c_N (B, mN), C_N (B, mN, nx))``: the rows' values and Jacobians at
        ``(X, U)``, unmasked; a problem without rows gets blocks of zero rows (the held-rows system of the
        projection and its Newton steps keeps them as such)."""
        B, N, nx = U.shape[0], U.shape[1], X.shape[-1]
        if self.m:
            c, Cz = stage_jacobian(self.stage_fn, X, U, params)
        else:
            c, Cz = X.new_zeros(B, N, 0), X.new_zeros(B, N, 0, nx + U.shape[-1])
        if self.mN:
            cN, CN = terminal_jacobian(self.terminal_fn, X[:, -1], params)
        else:
            cN, CN = X.new_zeros(B, 0), X.new_zeros(B, 0, nx)
        return c, Cz, cN, CN

    def stage_values(self, X: Tensor, U: Tensor, params) -> Tensor:
        """``c_k`` at every stage, ``(B, *E, N, m)``; rows that do not apply are 0."""
        if self.m == 0:
            return X.new_zeros(*U.shape[:-1], 0)
        return map_stage(self.stage_fn, X[..., :-1, :], U, params) * self.knot_mask

    def terminal_values(self, X: Tensor, params) -> Tensor:
        if self.mN == 0:
            return X.new_zeros(*X.shape[:-2], 0)
        return map_state(self.terminal_fn, X[..., -1, :], params)

    def _weights(self, c: Tensor, lam: Tensor, mu: Tensor, is_ineq: Tensor) -> Tensor:
        """Diagonal of ``I_μ`` (eq. 3)."""
        inactive = is_ineq & (c < 0) & (lam == 0)
        return torch.where(inactive, torch.zeros_like(mu), mu)

    def _penalty_terms(self, c, lam, mu, is_ineq, mask=None):
        w = self._weights(c, lam, mu, is_ineq)
        if mask is not None:
            w = w * mask
        return ((lam + 0.5 * w * c) * c).sum(-1)

    def point(self, X: Tensor, U: Tensor, params) -> PointValues:
        """The objective and the rows at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)`` from one ``vmap`` of the stages
        and one of the end point (:func:`~torchtraj.core.one_pass.problem_values` without the dynamics, replayed
        from its recorded graph as the expansion is): what :meth:`value` and :meth:`row_values` read."""
        return problem_values(self.problem, self.constraints, X, U, params, record=self.record, dynamics=False)

    def value(self, X: Tensor, U: Tensor, params, point: Optional[PointValues] = None) -> Tensor:
        """``L_A`` at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``: ``(B, *E)`` (from its :meth:`point`, given or
        evaluated here)."""
        extra = X.dim() - 3
        d = self.duals
        point = self.point(X, U, params) if point is None else point
        J = point.cost
        c, cN = self.row_values(X, U, params, point)
        if self.m:
            J = J + self._penalty_terms(c, _lift(d.stage, extra), _lift(d.stage_penalty, extra), self.is_ineq,
                                        self.knot_mask).sum(-1)
        if self.mN:
            J = J + self._penalty_terms(cN, _lift(d.terminal, extra), _lift(d.terminal_penalty, extra), self.is_ineqN)
        return J

    def expand(self, X: Tensor, U: Tensor, params):
        """LQR model of ``L_A`` around ``(X, U)`` (eqs. 5-12): the cost's Hessian and the dynamics' and rows'
        Jacobians from one ``torch.func`` pass (:func:`~torchtraj.core.one_pass.problem_kkt_expansion`)."""
        nx = X.shape[-1]
        point = problem_kkt_expansion(self.problem, self.constraints, X, U, params, record=self.record)
        H, g = point.Lzz, point.Lz
        lqr = LQR(A=point.fz[..., :nx], B=point.fz[..., nx:], Q=H[..., :nx, :nx], R=H[..., nx:, nx:],
                  S=H[..., nx:, :nx], QN=point.LNxx)
        rhs = LQRVectors(q=g[..., :nx], r=g[..., nx:], qN=point.LNx, c=torch.zeros_like(X[:, 1:]),
                         x0=torch.zeros_like(X[:, 0]))
        d = self.duals
        if self.m:  # the rows stacked as stage_fn stacks them: inequalities, then equalities
            c, Cz = _stacked(point.g, point.h, -1), _stacked(point.Gz, point.Hz, -2)
            c, Cz = c * self.knot_mask, Cz * self.knot_mask.unsqueeze(-1)
            w = self._weights(c, d.stage, d.stage_penalty, self.is_ineq) * self.knot_mask
            H = Cz.transpose(-1, -2) @ (w.unsqueeze(-1) * Cz)
            g = (Cz.transpose(-1, -2) @ (d.stage + w * c).unsqueeze(-1)).squeeze(-1)
            if self.square_root:
                lqr.root = torch.cat([psd_root(_joint(lqr)), w.clamp_min(0).sqrt().unsqueeze(-1) * Cz], -2)
            lqr.Q = lqr.Q + H[..., :nx, :nx]
            lqr.R = lqr.R + H[..., nx:, nx:]
            lqr.S = lqr.S + H[..., nx:, :nx]
            rhs.q = rhs.q + g[..., :nx]
            rhs.r = rhs.r + g[..., nx:]
        if self.mN:
            cN, CN = _stacked(point.gN, point.hN, -1), _stacked(point.GN, point.HN, -2)
            wN = self._weights(cN, d.terminal, d.terminal_penalty, self.is_ineqN)
            if self.square_root:
                lqr.rootN = torch.cat([psd_root(lqr.QN), wN.clamp_min(0).sqrt().unsqueeze(-1) * CN], -2)
            lqr.QN = lqr.QN + CN.transpose(-1, -2) @ (wN.unsqueeze(-1) * CN)
            rhs.qN = rhs.qN + (CN.transpose(-1, -2) @ (d.terminal + wN * cN).unsqueeze(-1)).squeeze(-1)
        return lqr, rhs

    def row_values(self, X: Tensor, U: Tensor, params, point: Optional[PointValues] = None) -> tuple:
        """``(c (B, *E, N, m), c_N (B, *E, mN))`` at ``(X, U)``: what the measures below read, evaluated once (or
        stacked from the :meth:`point`'s rows, inequalities then equalities, as ``stage_fn`` stacks them)."""
        if point is None:
            return self.stage_values(X, U, params), self.terminal_values(X, params)
        c = _stacked(point.g, point.h, -1) * self.knot_mask if self.m else X.new_zeros(*U.shape[:-1], 0)
        cN = _stacked(point.gN, point.hN, -1) if self.mN else X.new_zeros(*X.shape[:-2], 0)
        return c, cN

    def violation(self, c: Tensor, cN: Tensor) -> Tensor:
        """Largest violation ``(B,)`` of the stacked constraints (``max(g, 0)``, ``|h|``) of :meth:`row_values`."""
        parts = [c.new_zeros(c.shape[0], 1)]
        if self.m:
            parts.append(torch.where(self.is_ineq, c.clamp_min(0), c.abs()).flatten(1))
        if self.mN:
            parts.append(torch.where(self.is_ineqN, cN.clamp_min(0), cN.abs()))
        return torch.cat(parts, -1).amax(-1)

    def complementarity(self, duals: "Duals", c: Tensor, cN: Tensor) -> Tensor:
        """``(B,)``: the largest ``|λ_i c_i|`` of the inequality rows with the multipliers of ``duals``, over
        ``s_c = max(100, mean λ_i) / 100`` as :mod:`torchtraj.kkt.certificate` scales it."""
        parts, sums = [c.new_zeros(c.shape[0], 1)], c.new_zeros(c.shape[0])
        if self.m:
            lam = duals.stage * self.is_ineq * self.knot_mask
            parts.append((lam * c).abs().flatten(1))
            sums = sums + lam.flatten(1).sum(1)
        if self.mN:
            lamN = duals.terminal * self.is_ineqN
            parts.append((lamN * cN).abs())
            sums = sums + lamN.sum(1)
        scale = (sums / max(self.ineq_rows, 1)).clamp_min(100.0) / 100.0
        return torch.cat(parts, -1).amax(-1) / scale

    def sign_mismatch(self, c: Tensor, cN: Tensor) -> Tensor:
        """``(B,)``: the largest ``max(0, −(λ_i + I_μ,ii c_i))`` over the inequality rows: the multiplier a row pulls
        on the point with in ``L_A`` (eq. 7; zero on the rows ``I_μ`` leaves out). Eq. (17)'s estimate clamps a
        negative one to zero, so where this is nonzero a stationary point of ``L_A`` is not one of the Lagrangian
        with the estimate (a row left weakly inactive, ``c ≈ −1e-9``, with ``λ`` above ``−μ c``)."""
        d = self.duals
        parts = [c.new_zeros(c.shape[0], 1)]
        if self.m:
            w = self._weights(c, d.stage, d.stage_penalty, self.is_ineq) * self.knot_mask
            parts.append(((-(d.stage + w * c)).clamp_min(0) * self.is_ineq).flatten(1))
        if self.mN:
            wN = self._weights(cN, d.terminal, d.terminal_penalty, self.is_ineqN)
            parts.append((-(d.terminal + wN * cN)).clamp_min(0) * self.is_ineqN)
        return torch.cat(parts, -1).amax(-1)

    def updated_duals(self, c: Tensor, cN: Tensor, scaling: float, penalty_max: float, dual_max: float) -> Duals:
        """Eqs. (17)-(18) at the :meth:`row_values` ``c``, ``c_N`` of a point, for every instance (the caller
        masks)."""
        d = self.duals
        lam, lamN = d.stage, d.terminal
        if self.m:
            lam = d.stage + d.stage_penalty * c
            lam = torch.where(self.is_ineq, lam.clamp_min(0), lam).clamp(-dual_max, dual_max)
        if self.mN:
            lamN = d.terminal + d.terminal_penalty * cN
            lamN = torch.where(self.is_ineqN, lamN.clamp_min(0), lamN).clamp(-dual_max, dual_max)
        return Duals(lam, lamN, (d.stage_penalty * scaling).clamp_max(penalty_max),
                     (d.terminal_penalty * scaling).clamp_max(penalty_max))
