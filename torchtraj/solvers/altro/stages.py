r"""ALTRO's two stages on a batch: the augmented-Lagrangian iLQR stage (Algorithm 1, outer and inner loops flattened
into one batched loop) and its finish, the projection (§III-D) and the :class:`~torchtraj.Solution` (module
docstring of :mod:`torchtraj.solvers.altro.solver`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import torch
from torch import Tensor

from ...core.compiled import kernel
from ...core.constraints import Constraints, multiplier_blocks, stack_blocks
from ...core.problem import Problem
from ...core.solution import History, Solution
from ...core.status import Status
from ...iterations.ilqr import ilqr_step, log_iteration, riccati_backward, start_status
from ...kkt.certificate import Tolerances
from ...kkt.merit import solution_measures
from ...riccati.square_root import factorize_sqrt
from .augmented_lagrangian import AugmentedLagrangian, Duals, penalty_limit, resolution_floor
from .options import ALTROOptions
from .polish import KKTPoint, kkt_error
from .projection import multipliers, project


def initial_duals(constraints: Constraints, opts: ALTROOptions, like: Tensor, warm: Optional[dict]) -> Duals:
    """Zero multipliers and ``penalty_initial``, or the warm start ``{"multipliers", "penalties"}``."""
    duals = Duals.initial(constraints, like.shape[0], opts.penalty_initial, like)
    if not warm:
        return duals
    lam, lamN = stack_blocks(constraints, warm.get("multipliers") or {}, 0.0, like)
    mu, muN = stack_blocks(constraints, warm.get("penalties") or {}, opts.penalty_initial, like)
    knots = torch.cat([constraints.ineq_knot_mask, like.new_ones(constraints.problem.N, constraints.me)], -1)
    is_ineq = torch.arange(lam.shape[-1], device=like.device) < constraints.mi
    is_ineqN = torch.arange(lamN.shape[-1], device=like.device) < constraints.miN
    # inequality multipliers are non-negative (eq. 17); rows that do not apply keep zero
    lam = torch.where(is_ineq, lam.clamp_min(0), lam) * knots
    lamN = torch.where(is_ineqN, lamN.clamp_min(0), lamN)
    return Duals(lam, lamN, mu, muN)


@dataclass
class ALStage:
    """State of the batch when the AL stage ends (inputs of the projection)."""

    problem: Problem
    al: AugmentedLagrangian
    X: Tensor
    U: Tensor
    status: Tensor
    al_done: Tensor
    iterations: Tensor
    rows: list
    K: Tensor  # gains of each instance's last backward pass (B, N, nu, nx)
    stalled: Tensor  # (B,) outer iterations spent, last inner solve converged: left to the projection


def al_stage(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params, opts: ALTROOptions,
             method: str, warm: Union[dict, Duals, None] = None) -> ALStage:
    """AL-iLQR (Algorithm 1) on the whole batch, outer and inner loops flattened (module docstring).

    ``warm``: the multipliers and penalties to start from, as the block dictionary of :func:`torchtraj.solve`
    or already stacked; ``None`` starts from zero multipliers and ``penalty_initial``."""
    B = x0.shape[0]
    inner = opts.ilqr
    constraints = Constraints.of(problem)
    duals = warm if isinstance(warm, Duals) else initial_duals(constraints, opts, x0, warm)
    al = AugmentedLagrangian(constraints, duals, opts.square_root, opts.ilqr.record)
    backward = factorize_sqrt if opts.square_root else riccati_backward(inner.sweep)
    measures = kernel(_measures, inner.compile)
    J = kernel(AugmentedLagrangian.value, inner.compile)(al, X, U, params)
    violation = kernel(_violation, inner.compile)(al, X, U, params)
    status = start_status(x0, X, J, inner)
    running = status == Status.RUNNING
    al_done = torch.zeros_like(running)
    stalled = torch.zeros_like(running)
    outer_limit = torch.zeros_like(running)
    rho = torch.full((B,), inner.regularization_initial, dtype=x0.dtype, device=x0.device)
    drho = torch.zeros_like(rho)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    inner_count = torch.zeros_like(iterations)
    outer_count = torch.zeros_like(iterations)
    K = x0.new_zeros(B, problem.N, U.shape[-1], x0.shape[-1])
    rows = []
    constraint_tolerance = opts.stage_tolerance()
    # AL-iLQR's answer is the AL stage's point (no projection follows): its inner solve finishes at the certificate's
    # stationarity (ALTROOptions.stationary_finish)
    stationary_finish = opts.stationary_finish and not opts.projection
    stationarity_tolerance = Tolerances.for_dtype(x0.dtype).stationarity
    stationarity = torch.zeros_like(rho)  # the last running iterate's: a stopped instance's history repeats it
    for it in range(opts.iterations_outer * opts.iterations_inner):
        if not bool(running.any()):
            break
        tol = torch.where(violation < constraint_tolerance, opts.cost_tolerance, opts.cost_tolerance_intermediate)
        s = ilqr_step(problem, al, params, x0, X, U, J, rho, drho, running, inner, backward, tol)
        X, U, J, rho, drho = s.X, s.U, s.J, s.rho, s.drho
        K = torch.where(running.reshape(B, 1, 1, 1), s.K, K)
        previous, stationarity = stationarity, torch.where(running, s.stationarity, stationarity)
        iterations = iterations + running.long()
        inner_count = inner_count + running.long()
        violation, complementarity, new_duals, J_updated = measures(al, X, U, params, opts)
        converged = s.converged
        if stationary_finish:  # an inner optimum short of the certificate goes on while its residual halves a step
            # (its first step under new duals has no previous residual to halve)
            falling = s.took & ((s.stationarity < 0.5 * previous) | (inner_count == 1))
            converged = converged & ~(falling & (s.stationarity > stationarity_tolerance))
        inner_done = running & (converged | (inner_count >= opts.iterations_inner))
        # met: feasible and complementary with the multiplier estimate λ + I_μ c, the KKT point the certificate asks
        # for (at the inner optimum that estimate makes the Lagrangian stationary); a violation of 1e-6 alone left
        # products λ c of 3e-6 on bounds with multipliers of 3 to 7. Both to the dtype's resolution at least. The
        # complementarity counts a held row's negative multiplier as well: on parallel_park starts rows left at
        # c ≈ −1e-9 with λ = 4e-3 and μ = 1e7 pulled with −5e-3, stationarity 1.5e-4 under the clamped estimate.
        satisfied = resolution_floor(X, U).clamp_min(constraint_tolerance)
        finished = inner_done & converged & (violation <= satisfied) & (complementarity <= satisfied)
        update = inner_done & ~finished
        status = torch.where(s.blown & ~finished, int(Status.MAX_REGULARIZATION), status)
        exhausted = update & (outer_count + 1 >= opts.iterations_outer)
        status = torch.where(exhausted, int(Status.MAX_ITERATIONS), status)
        stalled = stalled | (exhausted & converged)
        al_done = al_done | finished
        al = AugmentedLagrangian(constraints, new_duals.where(update, al.duals), opts.square_root, opts.ilqr.record)
        J = torch.where(update, J_updated, J)  # the objective changed with the duals
        outer_count = outer_count + update.long()
        inner_count = torch.where(update, 0, inner_count)
        running = (status == Status.RUNNING) & ~al_done
        rows.append({"cost": J, "max_violation": violation, "step_size": s.alpha, "regularization": rho,
                     "stationarity": stationarity, "penalty": _largest_penalty(al.duals),
                     "outer_iteration": outer_count.to(J.dtype),
                     # which limit a MAX_ITERATIONS instance hit (Solution.summary): the outer loop's
                     "outer_limit": (outer_limit | exhausted).to(J.dtype)})
        outer_limit = outer_limit | exhausted
        if opts.verbose:
            log_iteration(method, it, J, rho, running)
    status = torch.where(running, int(Status.MAX_ITERATIONS), status)
    return ALStage(problem, al, X, U, status, al_done, iterations, rows, K, stalled)


def _violation(al: AugmentedLagrangian, X: Tensor, U: Tensor, params) -> Tensor:
    """The largest violation ``(B,)`` of the stacked rows at ``(X, U)`` (one compiled kernel)."""
    return al.violation(*al.row_values(X, U, params))


def _measures(al: AugmentedLagrangian, X: Tensor, U: Tensor, params, opts: ALTROOptions):
    """At ``(X, U)``: the largest violation, the complementarity of the multiplier estimate, the duals of eqs. (17)-(18)
    and ``L_A`` under those duals (every instance; the loop keeps the updates of the instances it updates). One compiled
    kernel."""
    point = al.point(X, U, params)  # the objective and the rows, read by the measures and the updated L_A
    c, cN = al.row_values(X, U, params, point)
    duals = al.updated_duals(c, cN, opts.penalty_scaling, penalty_limit(opts.penalty_max, X.dtype), opts.dual_max)
    updated = AugmentedLagrangian(al.constraints, duals, al.square_root, al.record).value(X, U, params, point)
    # the updated multipliers are the estimate λ + I_μ c whatever the penalty: its complementarity, and the sign of the
    # multipliers the rows held by L_A pull with (the estimate clamps a negative one)
    complementarity = al.complementarity(duals, c, cN)
    if opts.multiplier_signs:
        complementarity = torch.maximum(complementarity, al.sign_mismatch(c, cN))
    return al.violation(c, cN), complementarity, duals, updated


#: Rounding error of eq. (17)'s multiplier estimate above which AL-iLQR solves for least-squares multipliers.
ESTIMATE_ROUNDING = 1e-7


def _refined(al: AugmentedLagrangian, params, x0: Tensor, X: Tensor, U: Tensor, done: Tensor, stage: Tensor,
             terminal: Tensor, opts: ALTROOptions):
    """AL-iLQR's multipliers: eq. (17)'s estimate ``λ + μ c``, or the least-squares ones of the held rows (the
    projection's multiplier solve) where the estimate is not a KKT point's and they do better.

    The estimate multiplies the rows' values by the penalty, so it carries their error times ``μ``: their rounding,
    ``μ ε max(1, |X|, |U|)`` (float32: ``μ ε`` alone is 1.2e-7 at ``μ = 1``; on the pendulum, with ``|x_N| = π`` and
    ``μ = 100``, 2.4e-5 on the goal constraint's multipliers, which fifty steps of the unstable dynamics amplify
    into stationarity residuals of 1e-3 to 1.6e-2, 37 of 64 instances ``STALLED``), and the inner solve's
    inaccuracy (float64, parallel_park's sample starts 26, 35 and 40: ``μ = 1e7``, stationarity 5e-6 to 1.1e-5
    with the estimate, 1e-9 with the least-squares multipliers). Above ``ESTIMATE_ROUNDING`` of rounding the
    least-squares multipliers are taken; otherwise where the estimate misses the certificate's stationarity and they
    lower the KKT error (:func:`~torchtraj.solvers.altro.polish.kkt_error`; ``multiplier_refinement``)."""
    rounding = _largest_penalty(al.duals) * resolution_floor(X, U) / 10.0
    rounded = done & (rounding > ESTIMATE_ROUNDING)
    missed = torch.zeros_like(done)
    error_k = kernel(kkt_error, opts.ilqr.compile)
    if opts.multiplier_refinement and bool(done.any()):
        error, _ = error_k(al, params, x0, KKTPoint(X, U, None, stage, terminal, None))
        missed = done & (error > Tolerances.for_dtype(X.dtype).stationarity)
    if not bool((rounded | missed).any()):
        return stage, terminal
    held = multipliers(al, params, X, U, opts.projection_options, compile=opts.ilqr.compile)
    take = rounded
    if bool(missed.any()):
        held_error, _ = error_k(al, params, x0, KKTPoint(X, U, None, held.stage, held.terminal, None))
        take = take | (missed & (held_error < error))
    return (torch.where(take.reshape(-1, 1, 1), held.stage, stage),
            torch.where(take.reshape(-1, 1), held.terminal, terminal))


def _largest_penalty(duals: Duals) -> Tensor:
    both = torch.cat([duals.stage_penalty.flatten(1), duals.terminal_penalty,
                      duals.terminal.new_zeros(duals.terminal.shape[0], 1)], -1)
    return both.amax(-1)


def finish(coarse: ALStage, x0: Tensor, params, opts: ALTROOptions, method: str) -> Solution:
    """Projection (if ``opts.projection``), final status, multipliers, gains and the Solution."""
    problem, al, X, U, status, al_done = coarse.problem, coarse.al, coarse.X, coarse.U, coarse.status, coarse.al_done
    constraints = al.constraints
    if opts.projection:
        result = project(al, params, x0, X, U, al_done | coarse.stalled, opts.projection_options,
                         compile=opts.ilqr.compile)
        X, U = result.X, result.U
        status = torch.where(result.converged, int(Status.CONVERGED), status)
        status = torch.where((al_done | coarse.stalled) & ~result.converged, int(Status.MAX_ITERATIONS), status)
        stage, terminal, costate, K = result.stage, result.terminal, result.costate, result.K
    else:
        status = torch.where(al_done, int(Status.CONVERGED), status)
        # at an inner optimum the first-order multiplier estimate is the update of eq. (17), λ + I_μ c projected
        # (Nocedal & Wright, §17.3): the gradient of L_A is the Lagrangian's with it. Unfinished instances keep the
        # multipliers they would go on with.
        estimate = al.updated_duals(*al.row_values(X, U, params), 1.0, opts.penalty_max, opts.dual_max)
        done = al_done.reshape(-1, 1, 1)
        stage = torch.where(done, estimate.stage, al.duals.stage)
        terminal = torch.where(al_done.reshape(-1, 1), estimate.terminal, al.duals.terminal)
        stage, terminal = _refined(al, params, x0, X, U, al_done, stage, terminal, opts)
        costate = None
        # the gains of the last backward pass, at the iterate before the last step: a converged step is below
        # the tolerances, and a new expansion and factorisation only for K would cost a third of an MPC step
        K = coarse.K
    # ALTRO's states start at x0, rolled out from it: no initial defect
    cost, violation = solution_measures(opts.ilqr.compile, opts.ilqr.record)(problem, constraints, X, U, params)
    return Solution(
        X=X, U=U, K=K, cost=cost, max_violation=violation, status=status, iterations=coarse.iterations,
        history=History.from_rows(coarse.rows), costate=costate,
        multipliers=multiplier_blocks(constraints, stage, terminal),
        penalties=multiplier_blocks(constraints, al.duals.stage_penalty, al.duals.terminal_penalty),
        method=method,
    )
