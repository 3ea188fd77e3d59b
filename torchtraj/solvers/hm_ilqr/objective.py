r"""The objective HM-iLQR's inner M-iLQR iteration minimises, per instance in its stage, and its LQR model.

With the stage inequality rows ``g_k`` and the terminal ones ``g_N`` (:class:`~torchtraj.core.constraints.
Constraints`),

.. math::

    J_{[\cdot]}(X, U) = J(X, U) + \sum_{k \le N} \sum_i P_{k,i}(g_{k,i}),

where ``P`` is the AL term of :mod:`~torchtraj.solvers.hm_ilqr.augmented_lagrangian` for an instance in the AL stage
(``J_1``, eq. 13) and the relaxed log barrier of :mod:`~torchtraj.solvers.hm_ilqr.barrier` for one in the RLB stage
(``J_2``, eq. 17). Rows that do not apply at a knot (state rows at ``k = 0``) contribute nothing. The LQR model adds
the Gauss-Newton terms ``g_zᵀ P'`` and ``g_zᵀ diag(P'') g_z`` to the cost expansion (eq. 14); ``P'`` is also the
rows' multiplier.

**Equality rows** (the goal ``x_N = x_g``, stage equalities) are AL terms ``λ h + μ/2 h²`` in the AL stage (the
ALTRO form; a goal held exactly from a far start makes the first linearised steps enormous: on the cart-pole from
rest the line search then takes steps of 1e-3) and, in the RLB stage, the Riccati core's stagewise equalities
``C_k δx_k + D_k δu_k + h_k = 0`` (constraint back-propagation, switched per instance by the rows' mask): a barrier
cannot hold them, and as AL terms they would need the penalty to grow without bound, the ill-conditioning the RLB
stage is there to avoid. Held, the linear model meets them exactly, like the defects, and they enter the line
search's merit as the defects do: ``Σ hᵀh`` beside ``Σ dᵀd``, predicted to shrink to ``(1 − α)²`` of itself
(:mod:`~torchtraj.solvers.hm_ilqr.shooting`). Their multipliers are then the core's ``ν``.

**Dynamics curvature** (an extension beyond the paper, ``HMILQROptions.dynamics_curvature``, on by default). The
Gauss-Newton model leaves out ``Σ_i λ_{k+1,i} ∇²f_i(z_k)``, the dynamics' second derivatives weighted by the
costates, and converges linearly where they matter. On the cart-pole they do: from ``sample_x0`` starts the model's
curvature along the step was a third of the objective's (its full step raised the objective, ``α = 1/4`` was taken
for hundreds of iterations) and 21 of 64 ``cartpole_unconstrained`` starts ended ``MAX_ITERATIONS`` or ``STALLED``
(issue 23). In the RLB stage the model adds that term (DDP's second-order term; with it the LQR model is Newton's
on the barrier problem): the costates are those that make the objective's Lagrangian stationary in the states at
the expansion point, ``λ_N = q_N + C_Nᵀ ν_N``, ``λ_k = q_k + A_kᵀ λ_{k+1} + C_kᵀ ν_k``
(:func:`~torchtraj.solvers.hm_ilqr.shooting.costates`, the held rows' ``ν`` of the last LQR step), which within a
segment are the adjoints of the rollout, so that the model is the objective's second-order expansion along it. The
term can make the model nonconvex: where the backward pass at ``μ_V^0`` fails with it, the stage Hessians are
shifted by ``δ I``, the smallest on a short ladder of fractions of ``δ*``, the most negative eigenvalue of the
curvature blocks in magnitude, that succeeds (``HMILQROptions.curvature_shifts``; an inertia correction as IPOPT's,
Wächter & Biegler 2006, §3.1); the Gauss-Newton model where none does, and once after an iteration with the
curvature that failed (:mod:`~torchtraj.solvers.hm_ilqr.crls`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import map_stage, map_state, rows_of
from ...core.constraints import Constraints
from ...core.one_pass import PointValues, problem_kkt_expansion, problem_values
from ...riccati import LQR, LQRVectors
from .augmented_lagrangian import al_equality, al_inequality
from .barrier import relaxed_log_barrier
from .shooting import costates


@dataclass
class StageParameters:
    """Per instance: ``rlb (B,)`` whether in the RLB stage; AL multipliers of the inequality rows ``lam (B, N, mi)``,
    ``lamN (B, miN)`` and of the equality rows ``lamE (B, N, me)``, ``lamEN (B, meN)``, penalty ``mu (B,)``; barrier
    weight ``psi (B,)`` and relaxation ``delta (B,)``."""

    rlb: Tensor
    lam: Tensor
    lamN: Tensor
    lamE: Tensor
    lamEN: Tensor
    mu: Tensor
    psi: Tensor
    delta: Tensor


@dataclass
class InequalityRows:
    """The inequality rows of an expansion: Jacobians ``Cz (B, N, mi, nx+nu)`` and ``CN (B, miN, nx)`` (``None``
    without rows; zero where a row does not apply) and the penalty's ``P'``, ``P''`` (``d1``, ``d2``, ``d1N``,
    ``d2N``) at the expansion point."""

    Cz: Optional[Tensor] = None
    d1: Optional[Tensor] = None
    d2: Optional[Tensor] = None
    CN: Optional[Tensor] = None
    d1N: Optional[Tensor] = None
    d2N: Optional[Tensor] = None


def _lift(t: Tensor, like: Tensor) -> Tensor:
    """``t (B, ...)`` with singleton dimensions after B, to broadcast against ``like (B, *E, ...)``: a per-row
    tensor keeps its trailing dimensions, a per-instance ``(B,)`` one broadcasts over all of ``like``'s."""
    return t.reshape(t.shape[0], *([1] * (like.dim() - t.dim())), *t.shape[1:])


class HybridObjective:
    """``J_1`` / ``J_2`` of the module docstring for fixed stage parameters: value, equality residual, LQR model."""

    def __init__(self, constraints: Constraints, params: StageParameters, record: Optional[bool] = False):
        self.constraints = c = constraints
        self.problem = constraints.problem
        self.params = params
        #: the expansions replayed from their recorded graphs (``HMILQROptions.record``)
        self.record = record
        #: ``(N, mi)``: 1 where a stage inequality row applies.
        self.knot_mask = c.ineq_knot_mask
        self.mi, self.miN, self.me, self.meN = c.mi, c.miN, c.me, c.meN

    def rows(self, index: Tensor) -> "HybridObjective":
        """The objective of the instances ``index (R,)`` alone (their stage parameters)."""
        return HybridObjective(self.constraints, rows_of(self.params, index), self.record)

    # ------------------------------------------------------------------ the penalty of the inequality rows
    def penalty(self, g: Tensor, lam: Tensor, mask=None, derivatives: bool = True) -> tuple:
        """Value (summed over rows), ``P'`` and ``P''`` of rows ``g (B, *E, ..., m)`` with multipliers
        ``lam (B, ..., m)``, each instance in its stage; ``(value,)`` alone without ``derivatives``."""
        s = self.params
        lam = _lift(lam, g)
        mu, psi, delta, rlb = (_lift(v, g) for v in (s.mu, s.psi, s.delta, s.rlb))
        out = [torch.where(rlb, b, a) for a, b in zip(al_inequality(g, lam, mu, derivatives),
                                                      relaxed_log_barrier(g, psi, delta, derivatives))]
        if mask is not None:
            out = [v * mask for v in out]
        return (out[0].sum(-1), *out[1:])

    def equality_penalty(self, h: Tensor, lam: Tensor) -> tuple:
        """Value (summed over rows), ``P'``, ``P''`` of the AL terms of equality rows ``h (B, *E, ..., m)``; zero for
        an instance in the RLB stage (its rows are held by the Riccati core)."""
        al = _lift(~self.params.rlb, h).to(h.dtype)
        value, d1, d2 = al_equality(h, _lift(lam, h), _lift(self.params.mu, h))
        return (value * al).sum(-1), d1 * al, d2 * al

    # ------------------------------------------------------------------ values
    def stage_eq(self, X: Tensor, U: Tensor, params) -> Tensor:
        return map_stage(self.constraints.stage_eq, X[..., :-1, :], U, params)

    def terminal_eq(self, X: Tensor, params) -> Tensor:
        return map_state(self.constraints.terminal_eq, X[..., -1, :], params)

    def stage_ineq(self, X: Tensor, U: Tensor, params) -> Tensor:
        """``g_k`` ``(B, *E, N, mi)``; rows that do not apply are 0."""
        return map_stage(self.constraints.stage_ineq, X[..., :-1, :], U, params) * self.knot_mask

    def terminal_ineq(self, X: Tensor, params) -> Tensor:
        return map_state(self.constraints.terminal_ineq, X[..., -1, :], params)

    def point(self, X: Tensor, U: Tensor, params) -> PointValues:
        """The objective and the rows at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``, from one ``vmap`` of the
        stages and one of the end point (:func:`~torchtraj.core.one_pass.problem_values`, without the dynamics;
        replayed from its record as the expansion is): what :meth:`value` and :meth:`equality_residual` read, and
        the solver's cost and violation of the same point."""
        return problem_values(self.problem, self.constraints, X, U, params, record=self.record, dynamics=False)

    def value(self, X: Tensor, U: Tensor, params, point: Optional[PointValues] = None) -> Tensor:
        """``J_[·]`` at ``X (B, *E, N+1, nx)``, ``U (B, *E, N, nu)``: ``(B, *E)`` (from its :meth:`point`, given
        or evaluated here)."""
        v = self.point(X, U, params) if point is None else point
        J = v.cost
        if self.mi:
            J = J + self.penalty(v.g * self.knot_mask, self.params.lam, self.knot_mask, derivatives=False)[0].sum(-1)
        if self.miN:
            J = J + self.penalty(v.gN, self.params.lamN, derivatives=False)[0]
        if self.me:
            J = J + self.equality_penalty(v.h, self.params.lamE)[0].sum(-1)
        if self.meN:
            J = J + self.equality_penalty(v.hN, self.params.lamEN)[0]
        return J

    def equality_residual(self, X: Tensor, U: Tensor, params, point: Optional[PointValues] = None) -> Tensor:
        """``Σ hᵀh`` over the equality rows held by the Riccati core (an instance in the RLB stage), ``(B, *E)``
        (from the :meth:`point`, given or evaluated here)."""
        r = X.new_zeros(X.shape[:-2])
        if self.me or self.meN:
            v = self.point(X, U, params) if point is None else point
            if self.me:
                r = r + (v.h * v.h).sum((-1, -2))
            if self.meN:
                r = r + (v.hN * v.hN).sum(-1)
        return r * _lift(self.params.rlb, r).to(r.dtype)

    def multipliers(self, X: Tensor, U: Tensor, params) -> tuple:
        """``P'`` of every inequality row, ``(B, N, mi)`` and ``(B, miN)``: the AL multipliers' estimates and the
        barrier's implied multipliers."""
        stage = X.new_zeros(X.shape[0], U.shape[1], self.mi)
        terminal = X.new_zeros(X.shape[0], self.miN)
        if self.mi:
            stage = self.penalty(self.stage_ineq(X, U, params), self.params.lam, self.knot_mask)[1]
        if self.miN:
            terminal = self.penalty(self.terminal_ineq(X, params), self.params.lamN)[1]
        return stage, terminal

    # ------------------------------------------------------------------ the LQR model
    def expand(self, X: Tensor, U: Tensor, params):
        """The LQR model of ``J_[·]`` around ``(X, U)`` (eqs. 5, 10, 14), the equality rows by stage, the
        dynamics ``f(x_k, u_k) (B, N, nx)`` and the :class:`InequalityRows`; the defects ``c`` of the right-hand
        side are left to the caller."""
        nx = X.shape[-1]
        # the cost's Hessian with the dynamics' and the rows' Jacobians, in one pass
        point = problem_kkt_expansion(self.problem, self.constraints, X, U, params, record=self.record)
        f, A, Bm = point.f, point.fz[..., :nx], point.fz[..., nx:]
        H, g = point.Lzz, point.Lz
        HN, gN = point.LNxx, point.LNx
        rows, ineq = {}, InequalityRows()
        if self.mi:
            c, Cz = point.g * self.knot_mask, point.Gz * self.knot_mask.unsqueeze(-1)
            _, d1, d2 = self.penalty(c, self.params.lam, self.knot_mask)
            H = H + Cz.transpose(-1, -2) @ (d2.unsqueeze(-1) * Cz)
            g = g + (Cz.transpose(-1, -2) @ d1.unsqueeze(-1)).squeeze(-1)
            ineq.Cz, ineq.d1, ineq.d2 = Cz, d1, d2
        if self.miN:
            cN, CN = point.gN, point.GN
            _, d1, d2 = self.penalty(cN, self.params.lamN)
            HN = HN + CN.transpose(-1, -2) @ (d2.unsqueeze(-1) * CN)
            gN = gN + (CN.transpose(-1, -2) @ d1.unsqueeze(-1)).squeeze(-1)
            ineq.CN, ineq.d1N, ineq.d2N = CN, d1, d2
        e = eN = None
        held = self.params.rlb.to(X.dtype)
        if self.me:  # AL terms (AL stage) or held rows (RLB stage), per instance
            e, Hz = point.h, point.Hz
            _, d1, d2 = self.equality_penalty(e, self.params.lamE)
            H = H + Hz.transpose(-1, -2) @ (d2.unsqueeze(-1) * Hz)
            g = g + (Hz.transpose(-1, -2) @ d1.unsqueeze(-1)).squeeze(-1)
            rows.update(C=Hz[..., :nx], D=Hz[..., nx:], mask=torch.ones_like(e) * held.reshape(-1, 1, 1))
        if self.meN:
            eN, HNx = point.hN, point.HN
            _, d1, d2 = self.equality_penalty(eN, self.params.lamEN)
            HN = HN + HNx.transpose(-1, -2) @ (d2.unsqueeze(-1) * HNx)
            gN = gN + (HNx.transpose(-1, -2) @ d1.unsqueeze(-1)).squeeze(-1)
            rows.update(CN=HNx, maskN=torch.ones_like(eN) * held.reshape(-1, 1))
        if self.meN and not self.me:  # the core reads stage rows whenever it holds terminal ones: none here
            B, N = U.shape[:2]
            rows.update(C=X.new_zeros(B, N, 0, nx), D=X.new_zeros(B, N, 0, U.shape[-1]), mask=X.new_zeros(B, N, 0))
            e = X.new_zeros(B, N, 0)
        if self.me and not self.meN:
            rows.update(CN=X.new_zeros(X.shape[0], 0, nx), maskN=X.new_zeros(X.shape[0], 0))
            eN = X.new_zeros(X.shape[0], 0)
        lqr = LQR(A=A, B=Bm, Q=H[..., :nx, :nx], R=H[..., nx:, nx:], S=H[..., nx:, :nx], QN=HN, **rows)
        rhs = LQRVectors(q=g[..., :nx], r=g[..., nx:], qN=gN, c=torch.zeros_like(X[:, 1:]),
                         x0=torch.zeros_like(X[:, 0]), e=e, eN=eN)
        self.cost_hessian = point.Lzz
        return lqr, rhs, f, ineq

    def dynamics_curvature(self, lqr, rhs, X: Tensor, U: Tensor, params, curved: Tensor, nu, nuN) -> Tensor:
        """``Σ_i λ_{k+1,i} ∇²f_i(z_k)`` ``(B, N, nz, nz)`` at the point of the last :meth:`expand` (whose ``lqr``,
        ``rhs`` these are), zero outside the instances ``curved (B,)`` (module docstring, "Dynamics curvature");
        ``nu``, ``nuN``: the held rows' multipliers in the costates (:func:`~.shooting.costates`)."""
        lam = costates(lqr, rhs, nu, nuN) * curved.reshape(-1, 1, 1).to(X.dtype)
        lam = torch.where(torch.isfinite(lam), lam, torch.zeros_like(lam))
        return problem_kkt_expansion(self.problem, self.constraints, X, U, params, lam, record=self.record).Lzz \
            - self.cost_hessian
