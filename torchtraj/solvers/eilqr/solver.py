r"""eILQR (Laurenzi, Ruscelli & Tsagarakis, Horizon's equality-constrained iLQR), batched: the loop.

Newton's method on the KKT conditions (§II-A, eqs. 2-4) of the problem with its equalities exact and its
inequalities as soft barriers on the cost (:mod:`~torchtraj.solvers.eilqr.barrier`). Each iteration of
:func:`solve_eilqr`, for every instance still running:

1. the KKT model at the multiple-shooting iterate ``(X, U, λ, ν, ν_N, μ_0, z, z_N)``
   (:mod:`~torchtraj.solvers.eilqr.model`); converged where the barrier's weight is the last one and the KKT error is
   below the tolerance; where the error is below ``κ_ε w`` at an earlier weight, the weight falls (the barrier
   continuation, an extension beyond the paper: :mod:`~torchtraj.solvers.eilqr.continuation`);
2. the Newton step by the shared Riccati core with constraint back-propagation, with the initial state optimised
   where asked (:mod:`~torchtraj.solvers.eilqr.newton`, :mod:`~torchtraj.solvers.eilqr.initial_state`),
   regularised until the reduced Hessians are positive definite;
3. the ℓ1 merit's weight ``γ`` from the step's multipliers, the full step, its second-order correction and the
   backtracking line search against the largest merit of the last ``nonmonotone_memory`` iterates (Grippo et al.'s
   nonmonotone test; :mod:`~torchtraj.solvers.eilqr.merit`, :mod:`~torchtraj.solvers.eilqr.globalization`);
   the accepted ``α`` moves the primal variables and the multipliers, ``y ← y + α (y⁺ − y)``. A step refused or cut
   below ``short_step`` raises the next iteration's regularisation (a shorter, more gradient-like step), a full one
   lowers it, one cut to ``α`` above ``short_step`` keeps it (``regularization_partial``: ``×min(1/α, κ_w^+)``)
   (the paper's Fig. 5: adaptive ``α`` and ``ε_reg``; :class:`EILQROptions`).

An instance has converged where, at the last weight, the KKT error is below the tolerance or a full Newton step
changes no variable by more than ten rounding errors of the iterate (the dtype can resolve no further step, and the
error left is the rounding of the model); such a step at an earlier weight ends that stage. With the paper's fixed
weight the KKT error is the soft problem's: besides the Lagrangian's stationarity with the multipliers ``z``, their
distance ``|z − w s(t)|`` to the barrier's own (the t-scaled complementarity ``|t (z − w s(t))|`` of the hard
problem lets them differ by ``tol / t``, which is 1 at an active row in float32). With the paper's fixed
weight and the multipliers read off the barrier, that was the float32 case of the double integrator of
``tests/test_float32_barrier_methods.py``: an active row's barrier has the curvature ``z*² / w`` (``1e6`` for
``z* = 10`` at ``w = 1e-4``), so its gradient at the float32 point nearest the optimum is off by that curvature times
the rounding of the row, a stationarity error up to ``5e-3`` that ``tt.solve``'s certificate reports ``STALLED``. The
primal-dual multipliers of the continuation module make the Lagrangian stationary to float32's accuracy instead.

Every decision is a mask on the batch: an instance that stops keeps its iterate and never changes another.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Optional

import torch

from ...core.batch import Batch
from ...core.compiled import kernel, rollout_kernel
from ...core.constraints import Constraints, multiplier_blocks
from ...core.problem import Problem
from ...core.solution import History, Solution
from ...core.status import Status
from ...kkt.merit import solution_measures
from ...riccati.range_space import formed, select_gains
from .continuation import barrier_multipliers, final_weight, first_weight, rows_at, weights_for
from .globalization import direction_and_first_trial, first_trial_ahead, globalized_step
from .initial_state import InitialState
from .merit import MeritMemory
from .model import Iterate, last_multipliers
from .newton import compiled_direction, empty_multipliers, instances, regularized_direction
from .options import EILQROptions
from .verdicts import advanced, advanced_ahead, advanced_expanded, expanded, reweighted

logger = logging.getLogger("torchtraj")

def solve_eilqr(problem: Problem, batch: Batch, options: Optional[EILQROptions] = None,
                method: str = "eilqr") -> Solution:
    """Solve the ``batch`` of instances of ``problem`` from ``x0 (B, nx)``, controls ``U0 (B, N, nu)`` and,
    optionally, states ``X0 (B, N+1, nx)`` (any guess: multiple shooting; without it the problem's own ``X_init``
    where it has one and ``problem_state_guess`` is on, else the rollout of the controls: :func:`state_guess`), with
    the parameters batched to B.

    The history has a row per iteration (at the iterate the step starts from): ``cost`` (the barrier-augmented cost
    the iteration minimises), ``max_violation`` (the largest defect, equality or initial-row residual),
    ``step_size`` (``α``, 0 where refused), ``regularization`` (``ε_reg``) and in ``extra`` ``defects``,
    ``equality`` (``‖h, h_N‖∞``), ``merit``, ``gamma``, ``stationarity`` (the Lagrangian's, ``model.dual``) and
    ``kkt_error``. ``Solution.cost`` is the problem's own
    cost; ``multipliers`` hold the equalities' (``stage_eq``, ``terminal_eq``), the barrier's implied ones under the
    inequality blocks' names and, with a free start, ``initial``."""
    opts = options or EILQROptions()
    x0, params = batch.x0, batch.params
    B = x0.shape[0]
    cons = Constraints.of(problem)
    tol = opts.tolerance_for(x0.dtype)
    final = final_weight(opts, tol, x0.dtype)
    # the barrier's weight per instance: the first stage's, or the last's where there is no inequality row
    weight = x0.new_full((B,), first_weight(opts) if cons.mi + cons.miN else final)
    weights = weights_for(weight, opts)
    initial = InitialState(opts.free_initial_state, opts.initial_eq, x0) \
        if opts.free_initial_state is not False else None
    X = start_states(problem, batch, opts).clone()
    if initial is None:
        X[:, 0] = x0  # a fixed start: the guess's first state is the given one
    m0 = initial.evaluate(X[:, 0], params).e0.shape[-1] if initial is not None else 0
    z, zN = barrier_multipliers(rows_at(cons, X, batch.U0, params), weights)
    it = Iterate(X, batch.U0.clone(), *empty_multipliers(X, cons.me, cons.meN, m0), z=z, zN=zN)
    status = torch.full((B,), int(Status.RUNNING), dtype=torch.long, device=x0.device)
    start_ok = torch.isfinite(X).flatten(1).all(-1) & torch.isfinite(it.U).flatten(1).all(-1)
    status = torch.where(~torch.isfinite(x0).all(-1), int(Status.NON_FINITE), status)
    status = torch.where((status == Status.RUNNING) & ~start_ok, int(Status.INFEASIBLE_START), status)
    gamma = torch.zeros(B, dtype=x0.dtype, device=x0.device)
    floor, last = torch.zeros_like(gamma), torch.zeros_like(gamma)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    K = x0.new_zeros(B, problem.N, problem.nu, problem.nx)
    unresolved = torch.zeros(B, dtype=torch.bool, device=x0.device)
    rows = []
    memory = MeritMemory.empty(B, opts.nonmonotone_memory, x0)
    expanded_k, advanced_k = kernel(expanded, opts.compile), kernel(advanced, opts.compile)
    direction_k = compiled_direction(opts.compile)
    both_k = kernel(direction_and_first_trial, True) if first_trial_ahead(opts) else None
    # from a step to the next iteration's tests: with them its first attempt where compiled kernels make it
    ahead_k = kernel(advanced_ahead, True) if both_k is not None else None
    onward_k = kernel(advanced_expanded, opts.compile) if ahead_k is None else None
    untested = None  # the instances whose last iterate the iterations left untested (test_last_iterate off)
    tests = None  # the iterate's expansion and tests, made with the move that reached it
    made = None  # the first attempt's step and first trial, made with the move (ahead_k) from the floor
    for step in range(opts.iterations + 1):
        if step == opts.iterations and not opts.test_last_iterate:
            z, zN = kernel(last_multipliers, opts.compile)(cons, params, it, weights)
            it = dataclasses.replace(it, z=z, zN=zN)
            untested = status == Status.RUNNING
            break
        if tests is None:
            tests = expanded_k(problem, cons, params, it, x0, initial, weights, opts.record, status, final, tol,
                               unresolved, opts)
        model, status, advance, l1, defects, equality = tests
        if made is None:  # else the kernel that made the tests applied them
            it = dataclasses.replace(it, z=model.z, zN=model.zN)  # the safeguarded multipliers
            if bool(advance.any()):  # the barrier's new weight changes J: the past merits do not compare
                it, weights, model, memory = reweighted(model, it, weights, memory, advance, final, opts)
        running = status == Status.RUNNING
        if step == opts.iterations or not bool(running.any()):
            break
        # the first attempt's step and its first trial point, made in one kernel (`fresh`: made before the attempts)
        ahead = {} if made is None else {"d": made[0], "trial": made[1], "fresh": True}

        def attempt(e, rows=None):  # `rows`: the instances of a correction alone
            if rows is not None:
                return direction_k(instances(model, rows), instances(it, rows), x0[rows], e[rows], opts.terminal_rows)
            if ahead.pop("fresh", False):  # the first attempt, from the floor, made with the move
                return ahead["d"]
            if both_k is None or ahead:  # the attempts after the first: their step alone
                return direction_k(model, it, x0, e, opts.terminal_rows)
            ahead["d"], ahead["trial"] = both_k(model, it, x0, e, problem, cons, params, initial, gamma, l1, weights,
                                                memory, running, opts)
            return ahead["d"]

        d, eps = regularized_direction(attempt, floor, last, running, opts, regularize=opts.globalization)
        factored = running & (d.ok | (not opts.globalization))
        d, ls, merit0, gamma, memory = globalized_step(problem, cons, params, model, it, x0, initial, d, eps, gamma,
                                                       l1, factored, opts, weights, memory,
                                                       ahead["trial"] if ahead.get("d") is d else None)
        weight, made = weights.weight, None  # the weight of this iteration's row (ahead_k sets the next one's)
        if ahead_k is not None and (step + 1 < opts.iterations or opts.test_last_iterate):
            # the next iteration's tests, weight and first attempt with the move
            it, take, unresolved, floor, last, iterations, step_size, tests, weights, memory, made = ahead_k(
                problem, cons, params, x0, initial, weights, opts.record, final, tol, it, d, ls.alpha, ls.found,
                factored, running, eps, floor, last, status, iterations, gamma, memory, opts)
        elif step + 1 < opts.iterations or opts.test_last_iterate:  # the next iteration's tests with the move
            it, take, unresolved, floor, last, iterations, step_size, tests = onward_k(
                problem, cons, params, x0, initial, weights, opts.record, final, tol, it, d, ls.alpha, ls.found,
                factored, running, eps, floor, last, status, iterations, opts)
        else:
            it, take, unresolved, floor, last, status, iterations, step_size = advanced_k(
                it, d, ls.alpha, ls.found, factored, running, eps, floor, last, status, iterations, opts)
            tests = None
        K = select_gains(take, d.K, K)  # formed for the solution (range-space rows: once, at the end)
        rows.append(dict(cost=model.J, max_violation=model.primal, step_size=step_size, regularization=eps,
                         defects=defects, equality=equality, merit=merit0, gamma=gamma, kkt_error=model.error,
                         stationarity=model.dual, complementarity=model.complementarity,
                         barrier_weight=weight))
        if opts.verbose:
            logger.info("%s %4d  cost %.10g..%.10g  kkt %.2e  gamma %.1e  running %d", method, step,
                        model.J.min().item(), model.J.max().item(), model.error.max().item(),
                        gamma.max().item(), running.sum().item())
    status = torch.where(status == Status.RUNNING, int(Status.MAX_ITERATIONS), status)
    solution = _solution(problem, it, formed(K), status, iterations, rows, x0, params, initial, method, opts)
    if untested is None:
        return solution
    # an untested last iterate is told from its cost and violation, which the solution evaluates
    finite = torch.isfinite(solution.cost) & torch.isfinite(solution.max_violation)
    diverged = untested & finite & (it.X.abs().flatten(1).amax(-1) > opts.max_state)
    status = torch.where(untested & ~finite, int(Status.NON_FINITE), torch.where(diverged, int(Status.DIVERGED),
                                                                                  status))
    return dataclasses.replace(solution, status=status)


def start_states(problem: Problem, batch: Batch, opts: EILQROptions) -> torch.Tensor:
    """The states ``(B, N+1, nx)`` a solve starts from: :func:`state_guess`, else the rollout of ``U0``."""
    guess = state_guess(problem, batch, opts)
    if guess is not None:
        return guess
    return rollout_kernel(opts.compile)(problem.dynamics, batch.x0, batch.U0, batch.params)


def state_guess(problem: Problem, batch: Batch, opts: EILQROptions) -> Optional[torch.Tensor]:
    """The states a solve starts from: the caller's ``X0``; else the problem's own ``X_init`` where it has one and
    ``problem_state_guess`` is on; else ``None`` (the rollout of ``U0``)."""
    if batch.X0 is not None or not opts.problem_state_guess or problem.X_init is None:
        return batch.X0
    return problem.X_init.to(batch.x0).expand(batch.B, *problem.X_init.shape)


def _solution(problem, it, K, status, iterations, rows, x0, params, initial, method, opts) -> Solution:
    """The shared :class:`~torchtraj.Solution`: the problem's own cost and violation (the barrier's are not the
    problem's; replayed from their record where ``opts.record`` says so, a controller's every step), the costates,
    the equalities' multipliers and the inequality rows' (the primal-dual iterates, ``w s(t)`` to the
    complementarity tolerance)."""
    cons = Constraints.of(problem)
    stage = torch.cat([it.z, it.nu], -1)
    terminal = torch.cat([it.zN, it.nuN], -1)
    multipliers = multiplier_blocks(cons, stage, terminal)
    if initial is not None:
        multipliers["initial"] = it.mu0
    cost, violation = solution_measures(opts.compile, opts.record)(problem, cons, it.X, it.U, params,
                                                                   None if initial is not None else x0)
    if initial is not None:
        e0 = initial.evaluate(it.X[:, 0], params).e0
        violation = torch.maximum(violation, torch.cat([e0.abs(), e0.new_zeros(e0.shape[0], 1)], -1).amax(-1))
    history = History.from_rows(rows)
    return Solution(X=it.X, U=it.U, K=K, cost=cost, max_violation=violation,
                    status=status, iterations=iterations, history=history, costate=it.lam,
                    multipliers=multipliers, method=method)
