r"""iLQR for batches of unconstrained problems (ALTRO §II-A, Howell et al. 2019).

Each iteration, for every instance still running:

1. expand the problem around the current rollout ``(X, U)``: ``A_k, B_k`` from the dynamics,
   ``l_z, l_zz`` from the costs (:mod:`torchtraj.core.derivatives`);
2. backward pass (:mod:`torchtraj.riccati`) with the regularisation ``ρ`` added to ``Q_uu``
   (eq. 13): gains ``K_k``, feedforward ``d_k``, expected change ``ΔV(α) = α dV1 + α² dV2``
   (eq. 16). A failed Cholesky factorisation raises ``ρ`` and skips the step;
3. forward pass with line search: the closed-loop rollouts
   ``u_k = U_k + α d_k + K_k (x_k − X_k)`` for every ``α ∈ {1, β, β², …}`` are simulated
   *together* (one batched rollout), and each instance takes the largest ``α`` whose ratio
   ``z = (J − J(α)) / (−ΔV(α))`` lies in ``[z_lo, z_hi]``. If none does, ``ρ`` is raised.
4. ``ρ`` follows the schedule of Tassa et al. used by ALTRO
   (:func:`~torchtraj.globalization.regularization.rho_schedule`): on success
   ``δ ← min(δ/φ, 1/φ), ρ ← ρ δ`` (set to 0 below ``ρ_min``); on failure
   ``δ ← max(δ φ, φ), ρ ← max(ρ δ, ρ_min)``.

An instance converges when an accepted step changes the cost by less than
``cost_tolerance`` and the scaled control step ``mean_k max_i |d_ki| / (|u_ki| + 1)`` is below
``gradient_tolerance``, or when the model predicts a decrease below ``expected_decrease_tolerance``. Each
tolerance is met at the dtype's resolution where it lies below it (float32: a cost change of ten rounding errors of
the cost, a predicted decrease of one, a scaled step of √eps), so that a float32 solve stops where float32 can tell no
more instead of raising its regularisation until it fails. A step whose predicted decrease lies below the cost's
resolution is still taken before the instance stops, where it raises the cost by no more than ten rounding errors (the
line search compares values as IPOPT does, up to ``10 ε |J|``): its model comes from derivatives and is exact to
rounding where the value is not. Converged and failed instances are frozen by masks; the batch stops when no
instance is running.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from ..core.batching import closed_loop_rollout, param_rows
from ..core.compiled import DYNAMIC_FROM, kernel
from ..core.masks import RowPicker
from ..core.problem import Problem
from ..core.status import Status
from ..globalization.line_search import Accepted, backtrack
from ..globalization.regularization import rho_schedule
from ..kkt.certificate import expansion_stationarity
from ..kkt.model import cost_model, total_cost
from ..riccati import factorize

logger = logging.getLogger("torchtraj")


@dataclass
class ILQROptions:
    """Options of iLQR (method ``"ilqr"``) and of ALTRO's inner iLQR.

    The defaults are ALTRO's (Altro.jl ``SolverOptions``) except the three stopping tolerances: Altro.jl's
    (``cost_tolerance = 1e-4``, ``gradient_tolerance = 10``, ``expected_decrease_tolerance = 1e-10``, :meth:`fast`)
    stop the pendulum's swing-up well above its optimum, at a point that is no KKT point. These stop where the
    KKT certificate of :func:`torchtraj.solve` (stationarity 1e-6) holds on the problem set and the tests' problems:
    the pendulum with the torque bound of ``tests/test_implicit.py`` stopped at 4e-6 with ``gradient_tolerance =
    1e-4`` and the expected decrease at 1e-10."""

    #: Maximum iterations (``iterations_inner``).
    iterations: int = 300
    #: Converged when an accepted step changes the cost by less than this (``cost_tolerance``; Altro.jl: 1e-4).
    cost_tolerance: float = 1e-12
    #: ... and the scaled control step is below this (``gradient_tolerance``; Altro.jl: 10).
    gradient_tolerance: float = 1e-6
    #: Converged when the predicted decrease ``-dV1`` is below this (Altro.jl: 1e-10).
    expected_decrease_tolerance: float = 1e-14
    #: Initial regularisation ``ρ`` (``bp_reg_initial``).
    regularization_initial: float = 0.0
    #: Scaling ``φ`` of the regularisation schedule (``bp_reg_increase_factor``).
    regularization_increase: float = 1.6
    #: Smallest nonzero ``ρ`` (``bp_reg_min``).
    regularization_min: float = 1e-8
    #: Largest ``ρ`` before the instance fails (``bp_reg_max``).
    regularization_max: float = 1e8
    #: Line-search step shrink factor ``β`` (``line_search_decrease_factor``).
    line_search_decrease: float = 0.5
    #: Accepted ratio of actual to expected decrease, lower bound (``line_search_lower_bound``).
    line_search_lower: float = 1e-8
    #: ... upper bound (``line_search_upper_bound``).
    line_search_upper: float = 10.0
    #: Number of step sizes tried, all in one batched rollout (``iterations_linesearch``).
    line_search_steps: int = 20
    #: Step sizes simulated together per round; 0 picks ``min(steps, 128 / √B)`` eager (at least 1; a round after
    #: the first simulates only the instances still looking, :func:`~torchtraj.globalization.line_search.backtrack`):
    #: at small batches a round costs its calls, and all step sizes go together, at large ones its arithmetic. With
    #: ``compile``, ``min(steps, 8192 // B)`` (a single round keeps the iteration one graph). The accepted step is
    #: the same whatever the rounds.
    line_search_parallel: int = 0
    #: Once the running instances are at most this share of the batch, an iteration runs on their rows alone
    #: (gathered with their parameters and multipliers; the others are returned unchanged as always): the answers are
    #: the same, bit for bit, and the finished instances stop costing arithmetic. ``0``: never; with ``compile``, on
    #: two running instances or more (the kernels' batch dimension is dynamic from two on).
    compact_below: float = 0.75
    #: Divergence limits on the cost and on |x| (``max_cost_value``, ``max_state_value``).
    max_cost: float = 1e8
    max_state: float = 1e8
    #: ``torch.compile`` the per-iteration kernels (rollouts, objective, expansion, Riccati; in ALTRO the
    #: projection's steps too); the first solve of each problem and shape compiles them
    #: (:mod:`torchtraj.core.compiled`).
    compile: bool = False
    #: Replay the expansion and the rollouts' stages from their operator graphs recorded once per batch size
    #: (:mod:`torchtraj.core.recorded`): the same numbers with fewer, cheaper calls, after a trace of a fraction of
    #: a second per shape. ``None`` (default): a shape is recorded once it has been evaluated about as often as its
    #: trace costs (a long solve, repeated solves); ``True``: early (a controller's steps); ``False``: never. Read
    #: by ALTRO's and AL-iLQR's inner iLQR.
    record: Optional[bool] = None
    #: Log one line per iteration through the ``torchtraj`` logger.
    verbose: bool = False
    #: The Riccati sweep of the backward pass (:func:`~torchtraj.riccati.factorize`): ``"sequential"``,
    #: ``"parallel"`` (the associative-scan sweep of :mod:`torchtraj.riccati.parallel`, O(log N) deep; there ``ρ``
    #: is a proximal term on the controls) or ``"auto"``. Read by method ``"ilqr"`` and by ALTRO's inner iLQR
    #: (not with ``ALTROOptions.square_root``); ALTRO's projection keeps the sequential sweep of its rows.
    sweep: str = "sequential"

    @classmethod
    def fast(cls, **changes) -> "ILQROptions":
        """Altro.jl's own stopping tolerances (cost change 1e-4, scaled step 10, expected decrease 1e-10): fewer
        iterations, a point short of the optimum (``tt.solve`` reports it ``STALLED`` unless it happens to be a KKT
        point). For warm-started repeated solves where a rough answer will do."""
        return cls(**{"cost_tolerance": 1e-4, "gradient_tolerance": 10.0, "expected_decrease_tolerance": 1e-10,
                      **changes})


def _scaled_step(d: Tensor, U: Tensor) -> Tensor:
    """ALTRO's gradient measure ``mean_k max_i |d_ki| / (|u_ki| + 1)``: ``(B,)``."""
    return (d.abs() / (U.abs() + 1.0)).amax(-1).mean(-1)


def _candidates(problem, params, x0, X, U, K, d, alphas, record: bool = False):
    """Closed-loop rollouts ``u = U + α d + K (x − X)`` for every ``α`` at once: ``(B, L, ...)``."""
    B, L = U.shape[0], alphas.shape[0]
    starts = x0.unsqueeze(1).expand(B, L, x0.shape[-1])
    feedforward = U.unsqueeze(1) + alphas.reshape(1, L, 1, 1) * d.unsqueeze(1)
    return closed_loop_rollout(problem.dynamics, starts, feedforward, params, X, K, record=record)


def _line_search(problem, objective, params, x0, X, U, J, K, d, dV1, dV2, active, opts: ILQROptions):
    """Backtracking line search on the step size; returns the accepted ``(X, U, J, alpha)`` and a found mask.

    The candidates ``α = β^j`` are simulated in rounds of ``opts.line_search_parallel`` step sizes,
    all instances and step sizes of a round in one batched rollout; a new round starts only if some
    running instance has not yet found an acceptable step (:func:`~torchtraj.globalization.line_search.backtrack`).
    """
    B = U.shape[0]
    L = opts.line_search_steps
    per_round = opts.line_search_parallel or max(1, min(L, 8192 // max(B, 1) if opts.compile
                                                       else int(128 / math.sqrt(max(B, 1)))))
    all_alphas = opts.line_search_decrease ** torch.arange(L, dtype=X.dtype, device=X.device)

    def ratio_test(alphas, rows=None):  # the step is accepted where the actual decrease is a fair share of the
        # predicted one; `rows`: of those instances alone (backtrack's by_rows)
        if rows is None:
            o, p, x0_, X_, U_, K_, d_, J_, dV1_, dV2_ = objective, params, x0, X, U, K, d, J, dV1, dV2
        else:
            o, p = objective.rows(rows), param_rows(params, rows)
            x0_, X_, U_, K_, d_, J_, dV1_, dV2_ = (v[rows] for v in (x0, X, U, K, d, J, dV1, dV2))
        Xc, Uc = _candidates(problem, p, x0_, X_, U_, K_, d_, alphas, opts.record)
        Jc = o.value(Xc, Uc, p)  # (B, l)
        expected = -(alphas * dV1_.unsqueeze(1) + alphas**2 * dV2_.unsqueeze(1))
        actual = J_.unsqueeze(1) - Jc
        # the ratio test compared as IPOPT compares values, up to ten rounding errors of the cost: a step whose
        # predicted decrease the cost cannot resolve is judged by whether it leaves the cost where it was
        slack = 10 * torch.finfo(J.dtype).eps * J_.abs().unsqueeze(1)
        bounded = (Xc.abs().flatten(2).amax(-1) < opts.max_state) & (Jc < opts.max_cost)
        accept = (torch.isfinite(Jc) & bounded & (expected > 0)
                  & (actual > opts.line_search_lower * expected - slack)
                  & (actual < opts.line_search_upper * expected + slack))
        return accept, (Xc, Uc, Jc)

    # no host synchronisation before the first round: a compiled iteration stays one graph while it takes one round
    start = Accepted(found=torch.zeros(B, dtype=torch.bool, device=X.device), alpha=torch.zeros_like(J),
                     values=(X, U, J))
    step = backtrack(all_alphas, per_round, ratio_test, active, start, by_rows=not opts.compile)
    Xa, Ua, Ja = step.values
    return Xa, Ua, Ja, step.alpha, step.found


class CostObjective:
    """The problem's own objective, as the iLQR loop sees it: a value and an LQR expansion.

    The augmented-Lagrangian objective of :mod:`torchtraj.solvers.altro.augmented_lagrangian` has the same two methods.
    """

    def __init__(self, problem: Problem):
        self.problem = problem

    def value(self, X: Tensor, U: Tensor, params) -> Tensor:
        """``(B, *E)`` for ``X (B, *E, N+1, nx)``."""
        return total_cost(self.problem, X, U, params)

    def expand(self, X: Tensor, U: Tensor, params):
        return cost_model(self.problem, X, U, params)

    def rows(self, index: Tensor) -> "CostObjective":
        """The objective of the instances ``index`` (the same: it holds nothing per instance)."""
        return self


@dataclass
class Step:
    """Outcome of one iLQR iteration for every instance (all ``(B, ...)``)."""

    X: Tensor
    U: Tensor
    J: Tensor
    rho: Tensor
    drho: Tensor
    took: Tensor  # accepted a step
    converged: Tensor  # met the convergence test this iteration
    blown: Tensor  # regularisation above its maximum
    alpha: Tensor
    K: Tensor
    dJ: Tensor
    stationarity: Tensor  # at the iterate the step started from (kkt.certificate.expansion_stationarity)


def _backward_pass(objective, backward, X: Tensor, U: Tensor, params, rho: Tensor):
    """Expansion and Riccati sweep: gains ``K``, feedforward ``k``, the expected decrease
    terms ``dV1``, ``dV2``, the factorisation's ``ok`` and the iterate's stationarity residual."""
    lqr, rhs = objective.expand(X, U, params)
    factor = backward(lqr, rho)
    step = factor.solve(rhs, forward=False)
    return factor.K, step.k, step.dV1, step.dV2, factor.ok, expansion_stationarity(lqr, rhs)


def _factorize_parallel(lqr, rho):
    return factorize(lqr, rho, sweep="parallel")


def _factorize_auto(lqr, rho):
    return factorize(lqr, rho, sweep="auto")


#: the backward pass of each ``ILQROptions.sweep``: module-level functions, one compiled kernel serves every solve
_BACKWARDS = {"sequential": factorize, "parallel": _factorize_parallel, "auto": _factorize_auto}


def riccati_backward(sweep: str):
    """The ``backward(lqr, ρ)`` of :func:`ilqr_step` that factorises with ``sweep`` (``ILQROptions.sweep``)."""
    if sweep not in _BACKWARDS:
        raise ValueError(f"ILQROptions.sweep must be one of {', '.join(_BACKWARDS)}, not {sweep!r}")
    return _BACKWARDS[sweep]


def ilqr_step(problem, objective, params, x0, X, U, J, rho, drho, active, opts: ILQROptions,
              backward=None, cost_tolerance=None) -> Step:
    """One iteration (expansion, backward pass, line search, regularisation update) on the instances in ``active``.

    ``backward(lqr, rho)`` returns a :class:`~torchtraj.riccati.RiccatiFactor`; the default is
    :func:`~torchtraj.riccati.factorize` with ``opts.sweep`` (:func:`riccati_backward`). ``cost_tolerance`` (a float
    or ``(B,)``) overrides ``opts.cost_tolerance``. Instances outside ``active`` are returned unchanged. With
    ``opts.compile`` the iteration is one compiled kernel (one graph while the line search takes a single round).
    """
    cost_tolerance = opts.cost_tolerance if cost_tolerance is None else cost_tolerance
    iteration = kernel(_iteration, opts.compile)
    backward = backward or riccati_backward(opts.sweep)
    if opts.compact_below > 0 and active.shape[0] > 1:
        rows = active.nonzero().squeeze(-1)  # the iteration's host synchronisation
        fewest = DYNAMIC_FROM if opts.compile else 1  # compiled kernels have graphs of their own for one instance
        if fewest <= rows.numel() <= opts.compact_below * active.shape[0]:
            return _on_rows(iteration, rows, problem, objective, params, x0, X, U, J, rho, drho, active, opts,
                            backward, cost_tolerance)
    return iteration(problem, objective, params, x0, X, U, J, rho, drho, active, opts, backward, cost_tolerance)


def _on_rows(iteration, rows: Tensor, problem, objective, params, x0, X, U, J, rho, drho, active, opts, backward,
             cost_tolerance) -> Step:
    """:func:`_iteration` on the instances ``rows`` alone (``ILQROptions.compact_below``), gathered; the others'
    fields of the :class:`Step` are those of an instance outside ``active``: unchanged, no step, zero where the
    callers read them only for active instances (gains, stationarity)."""
    tol = cost_tolerance[rows] if isinstance(cost_tolerance, Tensor) and cost_tolerance.dim() else cost_tolerance
    s = iteration(problem, objective.rows(rows), param_rows(params, rows), x0[rows], X[rows], U[rows], J[rows],
                  rho[rows], drho[rows], active[rows], opts, backward, tol)

    def put(full: Tensor, part: Tensor) -> Tensor:
        return full.index_copy(0, rows, part)

    no, zero = torch.zeros_like(active), torch.zeros_like(J)
    K = X.new_zeros(X.shape[0], *s.K.shape[1:])
    return Step(put(X, s.X), put(U, s.U), put(J, s.J), put(rho, s.rho), put(drho, s.drho), put(no, s.took),
                put(no, s.converged), put(no, s.blown), put(zero, s.alpha), put(K, s.K), put(zero, s.dJ),
                put(zero, s.stationarity))


def _iteration(problem, objective, params, x0, X, U, J, rho, drho, active, opts: ILQROptions, backward,
               cost_tolerance) -> Step:
    K, k, dV1, dV2, ok, residual = _backward_pass(objective, backward, X, U, params, rho)
    # tolerances below what the dtype resolves are met at its resolution (module docstring), not iterated after until
    # the line search fails and the regularisation runs away
    eps = torch.finfo(J.dtype).eps
    exact = -dV1 < opts.expected_decrease_tolerance
    stationary = exact | (-dV1 <= eps * J.abs())
    Xn, Un, Jn, alpha, found = _line_search(problem, objective, params, x0, X, U, J, K, k, dV1, dV2, active & ok, opts)
    success = ok & found
    # a step whose predicted decrease is below the cost's resolution is still taken (the model, from derivatives, is
    # exact to rounding there, the value is not): in float32 skipping it left an augmented Lagrangian's violation
    # where a multiplier update had moved the inner optimum by less than the cost resolves
    take = active & success & ~exact
    dJ = J - Jn
    grad = _scaled_step(k, U)
    taking = RowPicker(take)
    X, U, J = taking(Xn, X), taking(Un, U), taking(Jn, J)
    rho_new, drho_new = rho_schedule(rho, drho, success | stationary, opts.regularization_increase,
                                     opts.regularization_min)
    rho, drho = torch.where(active, rho_new, rho), torch.where(active, drho_new, drho)
    settled = (dJ.abs() < cost_tolerance) | (dJ.abs() <= 10 * eps * J.abs())
    small = (grad < opts.gradient_tolerance) | (grad <= eps ** 0.5)
    converged = active & ok & (stationary | (take & settled & small))
    blown = active & ~converged & (rho > opts.regularization_max)
    alpha = torch.where(take, alpha, torch.zeros_like(alpha))
    return Step(X, U, J, rho, drho, take, converged, blown, alpha, K, torch.where(take, dJ, 0.0), residual)


def start_status(x0: Tensor, X: Tensor, J: Tensor, opts: ILQROptions) -> Tensor:
    """``RUNNING``, or ``NON_FINITE`` (x0 not finite) / ``INFEASIBLE_START`` (initial rollout unusable)."""
    B = x0.shape[0]
    status = torch.full((B,), int(Status.RUNNING), dtype=torch.long, device=x0.device)
    x0_finite = torch.isfinite(x0).all(-1)
    start_ok = torch.isfinite(J) & torch.isfinite(X).reshape(B, -1).all(-1) & (J < opts.max_cost)
    status = torch.where(~x0_finite, int(Status.NON_FINITE), status)
    return torch.where(x0_finite & ~start_ok, int(Status.INFEASIBLE_START), status)


def log_iteration(name: str, it: int, J: Tensor, rho: Tensor, active: Tensor) -> None:
    running = active.sum().item()
    logger.info("%s %4d  cost %.10g..%.10g  reg %.2e  running %d", name, it, J.min().item(), J.max().item(),
                rho.max().item(), running)
