"""The KKT certificate: one first-order optimality test of a returned point, the same for every method.

At a trajectory ``X, U`` with inequality multipliers ``z`` (rows ``g ≤ 0`` that apply), equality multipliers ``ν``
and costates ``λ``, the Lagrangian of the problem is

    L = J + Σ_k λ_{k+1}ᵀ (f(x_k, u_k) − x_{k+1}) + Σ_k (z_kᵀ g_k + ν_kᵀ h_k) + z_Nᵀ g_N + ν_Nᵀ h_N.

The costates are the ones that make ``L`` stationary in the states, whatever the method returned: with ``L₀``
the Lagrangian without the dynamics terms and ``A_k = ∂f/∂x``, ``B_k = ∂f/∂u``,

    λ_N = ∂L₀/∂x_N,    λ_k = ∂L₀/∂x_k + A_kᵀ λ_{k+1}    (k = N−1 .. 1),

so what remains of the KKT conditions is checked per instance, as IPOPT's optimality error does (Wächter & Biegler
2006, §2.1, eq. (5), with its scaling):

    stationarity     max_k |∂L₀/∂u_k + B_kᵀ λ_{k+1}|∞ / s_d,
    feasibility      the largest violation of the dynamics, the equalities and the inequalities,
    complementarity  max_i |z_i g_i| / s_c,
    dual sign        max_i (−z_i) / s_d          (inequality multipliers are nonnegative),

with ``s_d = max(s_max, (‖z‖₁ + ‖ν‖₁ + ‖λ‖₁) / (m + N nx)) / s_max``, ``s_c = max(s_max, ‖z‖₁ / m) / s_max`` and
``s_max = 100``. :func:`certify` turns a method's ``CONVERGED`` into ``STALLED`` where one of them exceeds its
tolerance: a point a method stopped at is called converged only where it is a KKT point.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor
from torch.func import grad

from ..core.compiled import kernel
from ..core.constraints import Constraints, stack_blocks
from ..core.derivatives import stage_jacobian
from ..core.problem import Problem
from ..core.recorded import Recorded, under_transform
from ..core.status import Status
from ..riccati.sweep import costate_stages
from .merit import violation_of
from .model import total_cost

#: IPOPT's ``s_max`` (Wächter & Biegler 2006, eq. (6)): multipliers larger on average than this scale the dual
#: residuals down.
SCALE_MAX = 100.0


@dataclass(frozen=True)
class Tolerances:
    """The largest residuals of a certified point, per dtype (:meth:`for_dtype`)."""

    stationarity: float
    feasibility: float
    complementarity: float

    @classmethod
    def for_dtype(cls, dtype: torch.dtype) -> "Tolerances":
        """float64: 1e-6 on the scaled residuals (IPOPT's ``acceptable_tol``). float32 resolves about 1e-7 of a
        value, and a residual sums many such values: 1e-3 on stationarity, 1e-4 on the others."""
        if dtype == torch.float64:
            return cls(stationarity=1e-6, feasibility=1e-6, complementarity=1e-6)
        return cls(stationarity=1e-3, feasibility=1e-4, complementarity=1e-4)


@dataclass(frozen=True)
class KKTResiduals:
    """Per-instance residuals ``(B,)`` of the KKT conditions at a solution (module docstring)."""

    stationarity: Tensor
    feasibility: Tensor
    complementarity: Tensor
    dual_sign: Tensor

    def within(self, tol: Tolerances) -> Tensor:
        """``(B,)`` bool: every residual within ``tol`` (NaN fails)."""
        return ((self.stationarity <= tol.stationarity) & (self.feasibility <= tol.feasibility)
                & (self.complementarity <= tol.complementarity) & (self.dual_sign <= tol.stationarity))

    def as_dict(self) -> dict:
        return {"stationarity": self.stationarity, "feasibility": self.feasibility,
                "complementarity": self.complementarity, "dual_sign": self.dual_sign}


def residuals(problem: Problem, X: Tensor, U: Tensor, multipliers: dict, params, x0: Optional[Tensor] = None,
              constraints: Optional[Constraints] = None, record: Optional[bool] = False,
              compile: bool = False) -> KKTResiduals:
    """The KKT residuals of ``problem`` at ``X (B, N+1, nx)``, ``U (B, N, nu)`` with the per-block
    ``multipliers`` (:attr:`Solution.multipliers`; missing blocks count as zero); the initial defect ``x0 − x_0``
    counts where ``x0 (B, nx)`` is given. ``constraints`` default to the problem's own
    (``Constraints.of(problem, ignored=True)`` gives the unconstrained problem's KKT conditions). ``record``
    (``True``, ``None``: when it pays; ``False``: never): replayed from a recorded operator graph
    (:mod:`~torchtraj.core.recorded`; the same numbers, fewer calls: a controller certifies every step);
    ``compile``: one compiled kernel call instead (:func:`~torchtraj.core.compiled.kernel`; a compiled solve's)."""
    c = Constraints.of(problem) if constraints is None else constraints
    X, U = X.detach(), U.detach()
    given = {} if c.ignored else {k: v.detach() for k, v in multipliers.items() if k in _blocks(c)}
    x0 = None if x0 is None else x0.detach()
    rows = c.applied_ineq_rows + c.miN  # the inequality rows that apply somewhere (no host read: kernels call it)
    evaluated = kernel(_residuals, True) if compile else _RECORDED_RESIDUALS.option(record)
    return KKTResiduals(*evaluated(problem, c, X, U, given, params, x0, rows))


def _residuals(problem: Problem, c: Constraints, X: Tensor, U: Tensor, given: dict, params, x0: Optional[Tensor],
               rows: int) -> tuple:
    """:func:`residuals`' ``(stationarity, feasibility, complementarity, dual_sign)`` from the detached
    multipliers ``given`` of ``c``'s blocks, ``rows`` the inequality rows that apply (no host read here, so that
    it can be recorded). The Lagrangian's gradient is ``torch.func.grad``'s inside a transform (a trace's
    functionalisation, where ``requires_grad_`` is refused), under ``torch.inference_mode`` (where autograd
    records nothing, whatever ``enable_grad`` says) and of inference tensors (made in the caller's inference mode,
    which a solve leaves where ``torch.func`` would return zeros in it: autograd cannot save them), else autograd's
    on tensors that require it (faster eager); a compiled kernel's trace takes ``torch.func`` (Dynamo reads no
    ``is_inference``): the same operators, the same residuals to the last bit
    (``tests/test_certificate.py``)."""
    B, nx = X.shape[0], problem.nx
    stage, terminal = stack_blocks(c, given, 0.0, X)
    z, nu = stage[..., :c.mi], stage[..., c.mi:c.mi + c.me]
    zN, nuN = terminal[:, :c.miN], terminal[:, c.miN:c.miN + c.meN]
    applies = (c.ineq_knot_mask[:, :c.mi] > 0).expand(B, -1, -1)

    def lagrangian(X, U):  # L₀ summed over the batch, and the rows it evaluated
        values = c.evaluate(X, U, params)
        g = torch.where(applies, values.ineq, torch.zeros_like(values.ineq))
        out = (total_cost(problem, X, U, params) + (z * g).sum((1, 2)) + (nu * values.eq).sum((1, 2))
               + (zN * values.ineqN).sum(1) + (nuN * values.eqN).sum(1))
        return out.sum(), (g, values.eq, values.ineq, values.eqN, values.ineqN)

    if torch.compiler.is_compiling() or under_transform() or torch.is_inference_mode_enabled() or any(
            t.is_inference() for t in (X, U, *params.values())):
        (gx, gu), values = grad(lagrangian, argnums=(0, 1), has_aux=True)(X, U)
    else:
        with torch.enable_grad():
            Xg, Ug = X.clone().requires_grad_(True), U.clone().requires_grad_(True)
            total, values = lagrangian(Xg, Ug)
            gx, gu = torch.autograd.grad(total, (Xg, Ug))
        values = tuple(v.detach() for v in values)
    g, eq, ineq, eqN, gN = values
    f, jacobian = stage_jacobian(problem.dynamics, X[:, :-1], U, params)
    A, Bu = jacobian[..., :nx], jacobian[..., nx:]
    lam = costate_stages(A, gx[:, :-1], gx[:, -1])[:, 1:]  # λ_1 .. λ_N (the recursion's λ_0 is not a costate)
    reduced = gu + (Bu.mT @ lam.unsqueeze(-1)).squeeze(-1)

    z_on = torch.where(applies, z, torch.zeros_like(z))
    z_sum = z_on.abs().sum((1, 2)) + zN.abs().sum(1)
    dual_sum = z_sum + nu.abs().sum((1, 2)) + nuN.abs().sum(1) + lam.abs().sum((1, 2))
    s_d = torch.clamp(dual_sum / max(rows + c.me * problem.N + c.meN + problem.N * nx, 1), min=SCALE_MAX) / SCALE_MAX
    s_c = torch.clamp(z_sum / max(rows, 1), min=SCALE_MAX) / SCALE_MAX
    stationarity = reduced.abs().flatten(1).amax(1) / s_d
    zero = X.new_zeros(B)
    complementarity, dual_sign = zero, zero
    if rows:
        products = torch.cat([(z_on * g).abs().flatten(1), (zN * gN).abs()], 1)
        complementarity = products.amax(1) / s_c
        signs = torch.cat([(-z_on).flatten(1), -zN], 1)
        dual_sign = torch.clamp(signs.amax(1), min=0.0) / s_d
    # largest_violation's, from the values taken above
    feasibility = violation_of(f - X[:, 1:], eq, ineq, eqN, gN, None if x0 is None else x0 - X[:, 0])
    return stationarity, feasibility, complementarity, dual_sign


# one record per signature, shared by every solve in the process
_RECORDED_RESIDUALS = Recorded(_residuals)


def _blocks(c: Constraints) -> set:
    """The multiplier blocks ``c`` has rows for (a method's solution may carry others: eILQR's of the inequalities
    that its declared problem turned into barriers)."""
    names = {name for name, rows in c.ineq_blocks.items() if rows.stop > rows.start}
    sizes = {"stage_eq": c.me, "terminal_ineq": c.miN, "terminal_eq": c.meN}
    return names | {name for name, size in sizes.items() if size}


def certify(problem: Problem, status: Tensor, X: Tensor, U: Tensor, multipliers: dict, params, x0: Tensor,
            constraints: Constraints, tolerances: Optional[Tolerances] = None, record: Optional[bool] = False,
            compile: bool = False):
    """``(status, residuals)``: ``status`` with ``CONVERGED`` turned into ``STALLED`` wherever the point fails the
    certificate (module docstring), and the residuals; ``record`` and ``compile`` as :func:`residuals`'."""
    tol = Tolerances.for_dtype(X.dtype) if tolerances is None else tolerances
    res = residuals(problem, X, U, multipliers, params, x0, constraints, record, compile)
    stalled = (status == int(Status.CONVERGED)) & ~res.within(tol)
    return torch.where(stalled, torch.full_like(status, int(Status.STALLED)), status), res


def expansion_stationarity(lqr, rhs) -> Tensor:
    """``max_k ‖r_k + B_kᵀ λ_{k+1}‖_∞`` ``(B,)``: the objective's gradient in the controls of the rolled-out
    trajectory, with the costates ``λ_N = q_N``, ``λ_k = q_k + A_kᵀ λ_{k+1}`` of the expansion ``(lqr, rhs)``.

    For the problem's own cost it is the stationarity residual of the KKT conditions; for an augmented-Lagrangian
    objective (ALTRO), that of the Lagrangian at the multiplier estimate ``max(0, λ + μ c)``
    (ALTRO eq. 17). Not for an expansion with held rows (their multipliers would enter the residual).
    Unscaled: the methods' histories record it per iteration; :func:`certify` scales the final one as IPOPT does.
    """
    lam = costate_stages(lqr.A, rhs.q, rhs.qN)[:, 1:]
    reduced = rhs.r + (lqr.B.mT @ lam.unsqueeze(-1)).squeeze(-1)
    return reduced.abs().flatten(1).amax(-1)
