r"""Implicit differentiation of solutions: a solve is a differentiable layer.

``tt.solve`` on inputs that require grad returns ``X``, ``U`` and ``cost`` as functions of ``x0`` and the tensors of
``Problem.params`` (:func:`attach_gradients`). The forward pass refines the solver's point onto the KKT point of its
active set (:mod:`torchtraj.differentiation.refine`); the backward pass solves the adjoint KKT system and takes the
parameters' products (:mod:`torchtraj.differentiation.adjoint`); the KKT system itself, its active set and its
multipliers are :mod:`torchtraj.differentiation.kkt_system`. Gradients flow to ``x0`` and the tensors of
``Problem.params``; bounds, initial guesses and options get none.

Instances get a **zero gradient**, and a ``RuntimeWarning`` names them with the reason, where

* they did not converge (``status != CONVERGED``; warned at the solve),
* their KKT system could not be factorised: a stage's reduced Hessian is not positive definite (the
  point is not a strict local minimum with its active set held: a saddle, or a solver that stopped
  short of a minimum), or non-finite values;
* their active rows are linearly dependent (LICQ fails,
  :func:`~torchtraj.differentiation.kkt_system.dependent_rows`), so that the multipliers and, in general, the
  derivative are not defined;
* refinement did not reach a KKT point (its stationarity test; skipped with ``refine_steps=0``);
* the gradient is not finite;

(at the backward pass for all but the first); other instances of the batch are unaffected. "Zero" is exact, for
shared parameters too: every mask is a ``torch.where`` (its backward selects, where a product ``0 · g`` would turn
the ``NaN`` derivative of a failed instance into a ``NaN`` sum over the batch), and the cost's explicit
``∂l/∂p`` reaches the parameters only through the rows kept (:func:`masked_cost`).

Second-order gradients are not available: the backward pass is not itself differentiable, and differentiating
its result again (``create_graph=True`` then a second ``backward``) raises a ``RuntimeError`` that says so.

Unrolled mode (``tt.solve(..., gradients="unrolled")``): the derivative of one final iLQR
(Gauss-Newton SQP) step taken at the solver's point with its active set held, the iterations before it
cut off (their iterate treated as a constant). The step solves ``M δ = -F(w, θ)`` with iLQR's model

.. math::

    M = \begin{bmatrix} \nabla^2_w \textstyle\sum_k l(z_k) + l_N & ∂c/∂w^T \\ ∂c/∂w & 0 \end{bmatrix},

the cost Hessian in place of the Lagrangian's (the multiplier-weighted curvature of the dynamics and
the constraint rows left out), so ``∂(w + δ)/∂θ = -M^{-1} ∂F/∂θ - (∂M^{-1}/∂θ) F``; at the solver's
point ``F ≈ 0`` and the second term is dropped. That is the adjoint formula with ``K`` replaced by ``M``:
the same adjoint code with one factorisation of ``M``, no refinement, no Lagrangian Hessian (the
second derivatives of the dynamics, the dear part of an RK4 model's expansion). It is the gradient of
differentiating through the last LQR approximation (as mpc.pytorch does at its fixed point). It
equals the exact gradient where ``M = K``: linear dynamics and linear constraints with a quadratic
cost (the bench's ``linear_box``), up to the solver's tolerance, which is not refined away. It
disagrees wherever the dynamics or an active constraint is curved, by about ``‖M^{-1}(K - M)‖``
relative: ``python -m torchtraj.bench --grad --gradients unrolled`` reports its agreement with
finite differences on the pendulum next to the linear rows (README), and the tests measure both
sides. Only instances that did not converge get zero gradients; the others get the unrolled
derivative at whatever point the solver stopped.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Mapping, Optional

import torch
from torch import Tensor

from ..core.masks import where_rows
from ..core.problem import Problem
from ..core.solution import Solution
from ..core.status import Status
from ..kkt.merit import largest_violation
from ..kkt.model import total_cost
from .adjoint import _adjoint
from .kkt_system import constraints_of, graphed_where_capturable
from .refine import Refined, refine

#: How a differentiable solve differentiates (``tt.solve(..., gradients=...)``).
GRADIENT_MODES = ("implicit", "unrolled")


def check_gradients_mode(gradients: str) -> None:
    """A clear error for a ``gradients`` value not in :data:`GRADIENT_MODES`."""
    if gradients not in GRADIENT_MODES:
        raise ValueError(f"gradients must be one of {GRADIENT_MODES}, got {gradients!r}")


def requires_gradients(x0: Tensor, params: Mapping[str, Tensor]) -> bool:
    """Whether a solve from ``x0`` with ``params`` must return differentiable ``X``, ``U``, ``cost``."""
    if not torch.is_grad_enabled():
        return False
    return x0.requires_grad or any(v.requires_grad for v in params.values())


@dataclasses.dataclass(frozen=True, eq=False)
class _Spec:
    """What the backward pass needs besides the saved tensors."""

    problem: Problem
    names: tuple
    usable: Tensor  # (B,) bool: instances that converged
    stationary: Tensor  # (B,) bool: instances refined to a KKT point (all True without refinement)
    constrained: bool
    active_tolerance: Optional[float]
    refined: Optional[Refined]
    gauss_newton: bool = False  # the unrolled mode (module docstring)
    cuda_graphs: bool = False  # the adjoint replayed from a CUDA graph (attach_gradients)


class ImplicitSolution(torch.autograd.Function):
    """``(X, U)`` of a solved batch as a function of ``(x0, *params)``; the backward pass is
    :func:`~torchtraj.differentiation.adjoint.backward_solve` (the implicit function theorem on the KKT conditions)."""

    @staticmethod
    def forward(spec: _Spec, X: Tensor, U: Tensor, x0: Tensor, *params: Tensor):
        return X.clone(), U.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        spec, X, U, x0, *params = inputs
        ctx.spec = spec
        ctx.save_for_backward(X, U, x0, *params)

    @staticmethod
    def backward(ctx, X_bar: Tensor, U_bar: Tensor):
        # grad mode is on here only under create_graph=True: the gradients are computed without a graph and
        # marked so that differentiating them again raises a clear error (module docstring)
        second_order = torch.is_grad_enabled()
        with torch.no_grad():
            grads = ImplicitSolution._gradients(ctx, X_bar.detach(), U_bar.detach())
        if not second_order:
            return grads
        anchors = tuple(t for t, needed in zip(ctx.saved_tensors[2:], ctx.needs_input_grad[3:]) if needed)
        return tuple(None if g is None else FirstOrderOnly.apply(g, *anchors) for g in grads)

    @staticmethod
    def _gradients(ctx, X_bar: Tensor, U_bar: Tensor) -> tuple:
        spec: _Spec = ctx.spec
        X, U, x0, *values = ctx.saved_tensors
        params = dict(zip(spec.names, values))
        refined = spec.refined
        cons = constraints_of(spec.problem, spec.constrained)
        adjoint = graphed_where_capturable(_adjoint, spec.cuda_graphs, cons)
        x0_bar, p_bar, ok, dependent = adjoint(
            spec.problem, cons, x0, X, U, params, X_bar.contiguous(), U_bar.contiguous(), spec.constrained,
            spec.active_tolerance, None if refined is None else refined.kkt,
            None if refined is None else refined.multipliers, None if refined is None else refined.active,
            spec.gauss_newton)
        B = X.shape[0]
        finite = torch.isfinite(x0_bar).all(-1)
        for v in p_bar.values():
            finite = finite & torch.isfinite(v.reshape(B, -1)).all(-1)
        # one reason per instance, the first that applies (module docstring)
        unfactorised = spec.usable & ~ok
        degenerate = spec.usable & ok & dependent
        not_kkt = spec.usable & ok & ~dependent & ~spec.stationary
        keep = spec.usable & ok & ~dependent & spec.stationary & finite
        non_finite = spec.usable & ~keep & ~unfactorised & ~degenerate & ~not_kkt
        reasons = [(unfactorised, "the KKT system could not be factorised (reduced Hessian not positive "
                                  "definite: not a strict local minimum with the active set held, often a "
                                  "solver stopped short of one; tighter solver tolerances help)"),
                   (degenerate, "the active constraint rows are linearly dependent (LICQ fails: more active "
                                "rows than the controls can satisfy, or rows at round-off); the derivative is not "
                                "defined there. Remove redundant constraints (a bound also written as a "
                                "stage_ineq row, an equality stated twice), or give a row that only touches its "
                                "bound some margin; attach_gradients' active_tolerance sets which rows count as "
                                "active"),
                   (not_kkt, "the point is not a KKT point (Newton refinement with the active set held "
                             "could not reach stationarity: the solver stopped short of a solution; "
                             "tighter solver tolerances help)"),
                   (non_finite, "the gradient is not finite")]
        for bad, why in reasons:
            if bool(bad.any()):
                warnings.warn(f"implicit gradients: instance(s) {_indices(bad)}: {why}; their gradients are "
                              "zero", RuntimeWarning, stacklevel=2)

        def masked(g):
            return where_rows(keep, g, torch.zeros_like(g))

        grads = [masked(p_bar[n]) if ctx.needs_input_grad[4 + i] else None for i, n in enumerate(spec.names)]
        x0_grad = masked(x0_bar) if ctx.needs_input_grad[3] else None
        return (None, None, None, x0_grad, *grads)


class FirstOrderOnly(torch.autograd.Function):
    """The identity on a gradient of :class:`ImplicitSolution`, whose own backward raises: the implicit layer gives
    first-order gradients only (module docstring). ``anchors`` (the inputs that require grad) connect it to the
    graph so that a second differentiation reaches it."""

    @staticmethod
    def forward(gradient: Tensor, *anchors: Tensor):
        return gradient.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        pass

    @staticmethod
    def backward(ctx, *grads):
        raise RuntimeError("tt.solve gives first-order gradients only: the implicit layer's backward pass (an "
                           "adjoint KKT solve) is not differentiable again, so second-order gradients (a Hessian, "
                           "a gradient of a gradient) through a solve are not available; take finite differences "
                           "of first-order gradients instead")


def masked_cost(problem: Problem, keep: Tensor, X: Tensor, U: Tensor, params: Mapping[str, Tensor]) -> Tensor:
    """The total cost ``(B,)`` at ``X (B, N+1, nx)``, ``U (B, N, nu)`` whose gradients come from the instances in
    ``keep (B,)`` only: the other rows of ``X``, ``U`` and of every parameter that requires grad are cut by
    ``torch.where`` before the cost is evaluated, so a failed instance's non-finite ``∂l/∂p`` is selected away rather
    than multiplied by zero (``0 · NaN = NaN``, which a shared parameter's sum over the batch would spread)."""
    def cut(t: Tensor) -> Tensor:
        return where_rows(keep, t, t.detach()) if t.requires_grad else t

    cost = total_cost(problem, cut(X), cut(U), {k: cut(v) for k, v in params.items()})
    return torch.where(keep, cost, cost.detach())


def _indices(mask: Tensor) -> list:
    return torch.nonzero(mask).reshape(-1).tolist()


def attach_gradients(problem: Problem, x0: Tensor, params: Mapping[str, Tensor], solution: Solution,
                     refine_steps: int = 4, active_tolerance: Optional[float] = None,
                     gradients: str = "implicit", cuda_graphs: bool = False, constrained: bool = True) -> Solution:
    """``solution`` with ``X``, ``U`` and ``cost`` differentiable with respect to ``x0`` and ``params``.

    Args:
        problem: the solved problem.
        x0: ``(B, nx)`` initial states, possibly requiring grad.
        params: the problem's parameters batched to B (``Problem.batched_params``), possibly requiring grad.
        solution: the method's result, computed from detached ``x0`` and ``params``.
        refine_steps: at most this many Newton steps of :func:`~torchtraj.differentiation.refine.refine` on the
            converged instances before differentiating (0: differentiate at the solver's point as it is).
        active_tolerance: inequality rows with ``g > -active_tolerance`` are held active;
            default :func:`~torchtraj.differentiation.kkt_system.default_active_tolerance`.
        gradients: ``"implicit"`` (exact, this module) or ``"unrolled"`` (the derivative of a final
            iLQR step at the solver's point, unrefined: module docstring).
        cuda_graphs: on a GPU, replay refinement's Newton steps and the backward pass's adjoint solve from
            CUDA graphs (:mod:`torchtraj.core.graphs`; ``tt.solve`` passes
            :func:`~torchtraj.core.graphs.graphs_used`), where the constraint rows are control bounds alone or there
            are none (the Riccati core's SVD of general rows cannot be captured).
        constrained: whether the solution is a KKT point of the constrained problem; ``False`` for a method that
            ignores the constraints, whose KKT conditions are then the unconstrained ones.

    Instances whose status is not ``CONVERGED`` get zero gradients (and are not refined); a
    ``RuntimeWarning`` names them. So do, at the backward pass, instances that refinement could not
    bring to a KKT point, and those whose KKT system is not factorisable or degenerate (module
    docstring). ``max_violation`` is re-evaluated at the refined point.
    """
    check_gradients_mode(gradients)
    unrolled = gradients == "unrolled"
    refine_steps = 0 if unrolled else refine_steps
    usable = solution.status == Status.CONVERGED
    if not bool(usable.all()):
        warnings.warn(f"implicit gradients: instance(s) {_indices(~usable)} did not converge (status "
                      f"{Status.describe(solution.status[~usable])}); their gradients will be zero",
                      RuntimeWarning, stacklevel=3)
    x0_d = x0.detach()
    detached = {k: v.detach() for k, v in params.items()}
    X, U = solution.X.detach(), solution.U.detach()
    violation, refined = solution.max_violation, None
    if refine_steps > 0 and bool(usable.any()):
        refined = refine(problem, x0_d, X, U, detached, refine_steps, constrained, active_tolerance, usable,
                         {k: v.detach() for k, v in solution.multipliers.items()}, cuda_graphs)
        X, U = refined.X, refined.U
        violation = torch.where(usable, largest_violation(problem, X, U, detached, x0=x0_d), violation)
    names = tuple(params)
    stationary = torch.ones_like(usable) if refined is None else refined.stationary
    spec = _Spec(problem=problem, names=names, usable=usable, stationary=stationary, constrained=constrained,
                 active_tolerance=active_tolerance, refined=refined, gauss_newton=unrolled, cuda_graphs=cuda_graphs)
    X, U = ImplicitSolution.apply(spec, X, U, x0, *(params[n] for n in names))
    # where an instance gets no gradient, its cost gets none either (not even the explicit ∂l/∂p)
    cost = masked_cost(problem, usable, X, U, params)
    return dataclasses.replace(solution, X=X, U=U, cost=cost, max_violation=violation)
