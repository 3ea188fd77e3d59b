r"""A primal-dual interior-point method on multiple shooting, batched (FATROP, Vanroye et al. 2023): the loop.

FATROP (§II-B, §III) is IPOPT's algorithm applied to the multiple-shooting problem, with the reduced primal-dual
system solved by a Riccati recursion generalised to stagewise equality constraints. The inequality rows
``g(w) ≤ 0`` get slacks ``s ≥ 0`` and a log barrier ``−μ Σ log s``, and each iteration of
:func:`solve_interior_point`, for every instance still running, is:

1. the model at the iterate and its optimality measures ``E_μ``, ``θ``
   (:mod:`~torchtraj.solvers.ipm.expansion`); converged where ``E_0 ≤ tol``; at the first iterate, the
   least-squares multipliers (:mod:`~torchtraj.solvers.ipm.initialization`, W&B §3.6);
2. for a linear-quadratic problem, the active-set crossover of the instances near a solution
   (:mod:`~torchtraj.solvers.ipm.crossover_driver`, :mod:`~torchtraj.solvers.ipm.crossover`);
3. the barrier update, monotone or Mehrotra's (:mod:`~torchtraj.solvers.ipm.barrier`);
4. the Newton step: the reduced primal-dual system as an LQR problem, factorised with IPOPT's inertia correction
   (:mod:`~torchtraj.solvers.ipm.newton`, :mod:`torchtraj.globalization.regularization`);
5. the filter line search with the fraction-to-boundary rule and second-order corrections
   (:mod:`~torchtraj.solvers.ipm.line_search`, :mod:`~torchtraj.solvers.ipm.soc`, :mod:`torchtraj.globalization`),
   or the watchdog's full steps (:mod:`~torchtraj.solvers.ipm.watchdog`), or Mehrotra's corrector taken whole;
   then the step taken and the iteration's one read back to the host (besides the running count): whether an
   instance enters restoration or took a tiny step, and whether a watchdog runs or may start at the next iteration
   (:mod:`~torchtraj.solvers.ipm.conclusion`);
6. where no step was found, the feasibility restoration phase of those instances, gathered
   (:mod:`~torchtraj.solvers.ipm.restoration`, W&B §3.3): back with a point the filter accepts, or
   ``LOCALLY_INFEASIBLE``;
7. finished instances leave the batch being iterated (:mod:`~torchtraj.solvers.ipm.compaction`).

Compiled, steps 1 and 3 are one kernel call (:mod:`~torchtraj.solvers.ipm.opening`), and the kernel of the line
search's first round ends the iteration where it settles the search (:mod:`~torchtraj.solvers.ipm.conclusion`);
where none of the iteration's host reads changes its course, steps 1 to 5 are one kernel call
(:mod:`~torchtraj.solvers.ipm.whole_iteration`), for a batch after an iteration whose first attempt held for every
instance.

Where the iterations run out, the last iterate is expanded and tested as every other; with
``IPOptions.test_last_iterate`` off (the control steps), its values alone are evaluated: its cost and violation,
and ``MAX_ITERATIONS`` for the instances still running. With ``IPOptions.stop_feasible_after`` (a control step's
adaptive budget), an instance whose iterate is feasible to ``stop_feasible_violation`` after that many iterations
stops there as if its budget were spent: each iteration from then on first evaluates the iterate's values.

The defaults are IPOPT's (Wächter & Biegler 2006; FATROP §III defers to it), in :class:`IPOptions`, but for the
restoration phase's penalty ``ρ`` (see there).

Also from IPOPT: the watchdog and the filter reset heuristic (W&B §3.2, :mod:`~torchtraj.solvers.ipm.watchdog`)
and very small search directions (§3.9, :mod:`~torchtraj.solvers.ipm.barrier`). The perturbation ``δ_c`` of the
constraint block (§3.1) for degenerate constraint Jacobians has no counterpart here: the Riccati core eliminates
the equality rows by a rank-revealing SVD (:mod:`torchtraj.riccati.propagation`), so that linearly dependent rows
are dropped as round-off instead of making the system singular, and its step is the ``δ_c → 0`` limit of IPOPT's
(``tests/test_ipm_safeguards.py`` solves problems with duplicated and dependent equality rows). A row whose
gradient vanishes where it holds, ``(x − 1)² = 0``, is no case for it either: its Jacobian is small, never singular,
IPOPT never perturbs it and ends ``Error_In_Step_Computation`` at a violation of 1e-16, and so does this iteration
(``MAX_REGULARIZATION``) after the same iterates. IPOPT's ``δ_c`` proper, ``δ̄_c μ^{κ_c}`` on every equality row
once a factorisation reports a singular system, would need the Riccati core to report the rank it dropped and to
take a ``(2,2)`` block ``−δ_c I``: on the stage rows ``M w + h = δ_c ν`` (a penalty ``MᵀM/δ_c`` on the stage
Hessian, ``ν = (M w + h)/δ_c``), on the dynamics ``x_{k+1} = A x_k + B u_k + c_k − δ_c λ_{k+1}`` (the cost-to-go
``P ← P (I + δ_c P)^{-1}`` before each stage's elimination). With
``IPOptions(restoration=False)`` an instance whose line search finds no acceptable step keeps its iterate and
retries with a larger ``δ_w`` (a shorter, more gradient-like step); past ``regularization_max`` its status is
``MAX_REGULARIZATION``; so does a restoration phase whose own line search fails. The filter holds the last
``filter_size`` entries of each instance.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Optional

import torch

from ...core.batch import Batch
from ...core.batching import param_rows
from ...core.compiled import DYNAMIC_FROM, rollout_kernel
from ...core.constraints import Constraints, multiplier_blocks
from ...core.problem import Problem
from ...core.solution import Solution
from ...core.status import Status
from ...globalization.filter import Filter
from ...riccati.range_space import formed, select_gains
from .barrier import average_complementarity, barrier_step, mehrotra_step
from .compaction import Final, full_history, gather_laid_out, gather_rows, history_row, pick
from .conclusion import conclude, first_round_concluded, settle, take_step, tiny_counts
from .crossover_driver import cross_over
from .expansion import Base, expand, initial_iterate, last_values, with_values
from .initialization import least_squares_multipliers
from .iterate import Hooks
from .kernels import compiled_kernels, eager_kernels, kernel_of, kernel_on_call, uses_graphs
from .line_search import batch_first_round, line_search
from .newton import batch_sweep, direction, direction_of_rows, newton_direction, newton_lqr, regularized_direction
from .opening import checked, opened, tested
from .options import IPOptions
from .restoration import restore
from .scaling import scaled_problem, unscale
from .soc import correction_of_rows, second_order_correction
from .start import start_states
from .warm_start import warm_start_hooks
from .watchdog import Watchdog, merge_steps, watched_step
from .whole_iteration import whole_iteration

logger = logging.getLogger("torchtraj")


def solve_interior_point(problem: Problem, batch: Batch, options: Optional[IPOptions] = None,
                         method: str = "ipm") -> Solution:
    """Solve the ``batch`` of instances of ``problem``: from ``x0 (B, nx)``, controls ``U0 (B, N, nu)`` and,
    optionally, states ``X0 (B, N+1, nx)`` (any guess: multiple shooting starts from defects), with the parameters
    batched to B. Without ``X0`` the states start at the problem's own guess ``Problem.X_init`` where it has one
    and the controls are the problem's own (as IPOPT's reference does: car_escape's waypoints; from the rollout of
    its controls, which drives through the walls, IPOPT itself ends ``Infeasible_Problem_Detected`` after 487
    iterations), else at the rollout of ``U0`` (:func:`~torchtraj.solvers.ipm.start.state_guess`)."""
    opts = options or IPOptions()
    X0 = start_states(problem, batch, opts)  # given, for the objective's scaling
    problem, batch, scale = scaled_problem(problem, dataclasses.replace(batch, X0=X0), opts)  # W&B §3.8
    hooks = warm_start_hooks(Constraints.of(problem), batch.duals, scale, batch.B, batch.x0, opts)
    out, cons, records = run(problem, batch, opts, hooks, method=method)
    history = full_history(records)
    if scale is not None:
        out, history = unscale(out, history, scale)
    knots = cons.ineq_knot_mask
    multipliers = multiplier_blocks(cons, torch.cat([out.z * knots, out.nu], -1), torch.cat([out.zN, out.nuN], -1))
    return Solution(
        X=out.X, U=out.U, K=out.K, cost=out.J, max_violation=out.violation, status=out.status,
        iterations=out.iterations, history=history, costate=out.lam, multipliers=multipliers,
        method=method,
    )


def run(problem: Problem, batch: Batch, opts: IPOptions, hooks: Optional[Hooks] = None, method: str = "ipm"):
    """The iteration of :func:`solve_interior_point` (module docstring), with the caller's per-instance
    :class:`Hooks`. Returns ``(Final, Constraints, history records)``."""
    hooks = hooks or Hooks()
    x0, U0, X0, params = batch.x0, batch.U0, batch.X0, batch.params
    B, N, nx = x0.shape[0], problem.N, problem.nx
    cons = Constraints.of(problem)
    opts = batch_first_round(batch_sweep(opts, cons, B, N, nx, problem.nu, x0.device), B, x0.device)
    tol = opts.tolerance_for(x0.dtype)
    if X0 is None:
        X = rollout_kernel(opts.compile)(problem.dynamics, x0, U0, params)
    else:
        X = torch.cat([x0.unsqueeze(1), X0[:, 1:]], 1)
    it = initial_iterate(cons, params, X, U0, opts)
    if hooks.start is not None:
        it = hooks.start(it)
    expand_k = kernel_on_call(expand, opts, x0.device)
    eager = eager_kernels(opts, x0.device)
    # compiled kernels: the Newton step's kernel forms its system (Mehrotra's steps run eager, on a kept factor)
    fused = compiled_kernels(opts, x0.device) and opts.barrier_strategy != "mehrotra"
    newton_k = kernel_of(newton_direction, opts, x0.device) if fused else None
    direction_k = None if fused else kernel_of(direction, opts, x0.device)
    barrier_k = kernel_on_call(barrier_step, opts, x0.device) if fused else barrier_step
    conclude_k = kernel_on_call(conclude, opts, x0.device) if fused else None
    first_round_k = kernel_on_call(first_round_concluded, opts, x0.device) if fused else None
    estimate_k = kernel_on_call(least_squares_multipliers, opts, x0.device) if fused else least_squares_multipliers
    mu = torch.full((B,), opts.barrier_initial, dtype=x0.dtype, device=x0.device) if hooks.barrier is None \
        else hooks.barrier.clone()
    budget = torch.full((B,), opts.iterations, dtype=torch.long, device=x0.device) if hooks.budget is None \
        else hooks.budget
    mehrotra = opts.barrier_strategy == "mehrotra"
    # a restoration phase has none of its own; Mehrotra's steps have no filter to return to
    restoring = opts.restoration and hooks.leave is None and not mehrotra
    budgeted = hooks.budget is not None  # else the loop's own count is the budget, until a restoration phase
    status = torch.full((B,), int(Status.RUNNING), dtype=torch.long, device=x0.device)
    start_ok = torch.isfinite(X).flatten(1).all(-1) & torch.isfinite(U0).flatten(1).all(-1)
    status = torch.where(~torch.isfinite(x0).all(-1), int(Status.NON_FINITE), status)
    status = torch.where((status == Status.RUNNING) & ~start_ok, int(Status.INFEASIBLE_START), status)
    filt = Filter.empty(B, opts.filter_size, x0)
    wd = Watchdog.start(it)  # W&B §3.2: the watchdog and the filter reset's counts
    tiny_steps = torch.zeros(B, dtype=torch.long, device=x0.device)  # W&B §3.9: successive steps at round-off
    last = torch.zeros_like(mu)  # last nonzero δ_w that gave a positive definite system
    floor = torch.zeros_like(mu)  # smallest δ_w of the next attempt (raised after a failed line search)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    K = x0.new_zeros(B, N, problem.nu, nx)
    records = []  # the history's rows (compaction.full_history)
    theta_max = theta_min = None
    base = None
    compacting = opts.compact_below > 0 and not uses_graphs(opts, x0.device)
    fewest = DYNAMIC_FROM if opts.compile else 1  # compiled kernels have graphs of their own for one instance
    crossing = opts.crossover and problem.linear_quadratic and cons.mi + cons.miN > 0
    # from the unconstrained optimum only where every row is a control bound: with state rows the active-set
    # updates can go round in circles (the oscillator of the tests: eight sets without settling)
    starting = crossing and opts.crossover_start_rounds > 0 and cons.bound_rows() is not None
    # IPOPT's mu_max: its factor times the initial average complementarity
    ceiling = opts.mehrotra_mu_max_factor * average_complementarity(it.s, it.sN, it.z, it.zN, cons.ineq_knot_mask)
    index, final = None, None  # the rows of the full batch being iterated (None: all), and the others' results
    may_return = may_watch = False  # a watchdog runs / may start (known at the last iteration's synchronisation)
    held = True  # the last iteration's first attempt factorised every running instance (whole_iteration)
    # a single instance takes the one call whatever `held`: its round made again costs less than the calls it saves
    # (compiled, a batch never leaves fewer than two rows: `fewest`)
    whole_always = B == 1
    may_reset = opts.filter_reset_trigger <= 1  # a filter reset may come at this step (the same synchronisation)

    # compiled, with no test of the caller's nor crossover: the expansion, the tests and the barrier update one kernel
    opened_k = kernel_of(opened, opts, x0.device) if fused and hooks.leave is None and not crossing else None
    whole_k = None if opened_k is None else kernel_on_call(whole_iteration, opts, x0.device)
    corrects = opts.second_order_corrections > 0

    def expanded(params, it, base, status, iterations, budgeted, mu, tiny_steps, filt):  # (model, the rest or None)
        if opened_k is None:
            return expand_k(problem, cons, params, it, opts, base), None
        model, *rest = opened_k(problem, cons, params, it, opts, base, status, iterations, budget, budgeted, tol, mu,
                                tiny_steps, filt)
        return model, rest

    # the instances whose multipliers take the least-squares estimate (a warm start's cold ones: Hooks.estimate)
    estimated = hooks.estimate if hooks.start is not None and hooks.estimate is not None and bool(
        opts.least_squares_multipliers and hooks.estimate.any()) else None
    estimated_rows = (lambda rows: rows) if estimated is None else (lambda rows: rows & estimated)
    measures = None  # the last iterate's objective and violation, where it is evaluated untested
    for step in range(opts.iterations + 1):
        ran_out = step == opts.iterations and not opts.test_last_iterate
        adaptive = 0 < opts.stop_feasible_after <= step  # a control step's adaptive budget
        if (ran_out or adaptive) and hooks.leave is None:  # the iterate's values alone, untested
            J, violation, finite = kernel_of(last_values, opts, x0.device)(problem, cons, params, it, opts)
            running = status == Status.RUNNING
            largest = it.X.abs().flatten(1).amax(-1)
            if ran_out:  # the iterations ran out: NON_FINITE and DIVERGED are still told
                status = torch.where(running & ~finite, int(Status.NON_FINITE), status)
                status = torch.where(running & finite & (largest > opts.max_state), int(Status.DIVERGED), status)
                measures = (J, violation)
                break
            stop = running & finite & (violation <= opts.stop_feasible_violation) \
                & (iterations >= opts.stop_feasible_after) & (largest <= opts.max_state)
            status = torch.where(stop, int(Status.MAX_ITERATIONS), status)
            if not bool((running & ~stop).any()):  # every instance stopped or ended: these values are the answer's
                measures = (J, violation)
                break
        budget_spent = budgeted and step < opts.iterations  # a budget (Hooks), or iterations a restoration took
        ahead = None  # compiled: the iteration's step, first round and end, made with its start (whole_iteration)
        if whole_k is not None and theta_max is not None and (held or whole_always) and not (may_return or may_watch):
            (model, *head), ahead = whole_k(problem, cons, params, it, opts, base, status, iterations, budget,
                                            budget_spent, tol, mu, tiny_steps, filt, x0, floor, wd, last, theta_max,
                                            theta_min, restoring, corrects)
        else:
            model, head = expanded(params, it, base, status, iterations, budget_spent, mu, tiny_steps, filt)
        if problem.linear_quadratic and base is None:  # the initial iterate's multipliers are zero
            base = Base(it.X, it.U, model)
        # W&B §3.6, then re-expanded; where the crossover starts from the unconstrained optimum, after it, for the
        # instances it did not end (its first candidate holds no row and reads no multiplier)
        estimating = step == 0 and opts.least_squares_multipliers and (hooks.start is None or estimated is not None)
        if estimating and not starting:
            it = estimate_k(cons, model, it, estimated_rows(status == Status.RUNNING), opts)
            model, head = expanded(params, it, base, status, iterations, budget_spent, mu, tiny_steps, filt)
        if theta_max is None:
            theta_0 = torch.clamp(torch.nan_to_num(model.theta, nan=1.0, posinf=1.0), min=1.0)
            theta_max, theta_min = opts.theta_max_factor * theta_0, opts.theta_min_factor * theta_0
        running = status == Status.RUNNING
        if head is None:
            error, status = tested(model, it, status, running, tol, params, hooks.leave)
            status = checked(it, status, running, iterations, budget, budget_spent, opts)
        else:
            error, status, head = head
        running = status == Status.RUNNING
        start = starting and step == 0
        rounds = opts.crossover_start_rounds if start else opts.crossover_rounds
        trying = running & ((error <= opts.crossover_from) | start) if crossing and rounds > 0 else None
        if trying is not None and bool(trying.any()):
            it, model, error, K, taken = cross_over(problem, cons, params, model, it, x0, base, opts, tol, error,
                                                    formed(K), trying, rounds, start)
            status = torch.where(taken > 0, int(Status.CONVERGED), status)
            iterations = iterations + taken.abs()  # each round solves a Newton system, as an iteration
            running = status == Status.RUNNING
        if estimating and starting and bool(running.any()):
            it = estimate_k(cons, model, it, estimated_rows(running), opts)
            model = with_values(running, expand_k(problem, cons, params, it, opts, base), model)
            estimated_error, status = tested(model, it, status, running, tol, params, hooks.leave)
            error = torch.where(running, estimated_error, error)
            running = status == Status.RUNNING
        count = int(running.sum())
        if step == opts.iterations or count == 0:
            break
        if compacting and fewest <= count <= opts.compact_below * running.shape[0]:
            # the finished instances' results are final: iterate on the running ones alone
            now = Final.of(it, (model.J, model.violation), status, iterations, formed(K))
            final = gather_rows(now, torch.arange(running.shape[0], device=x0.device)) if final is None \
                else final.write(index, now)  # the first: copies of the full batch's
            # what the history repeats for the instances that leave (its values at their final iterate)
            records.append((index, history_row(model, torch.zeros_like(mu), floor, mu, error), False))
            keep = running.nonzero().squeeze(-1)
            index = keep if index is None else index[keep]
            # compiled: the model's rows laid out as every expansion's, as the kernels take them
            model = (gather_laid_out if opts.compile else gather_rows)(model, keep)
            it, filt, base = gather_rows(it, keep), gather_rows(filt, keep), \
                None if base is None else gather_rows(base, keep)
            wd = gather_rows(wd, keep)
            mu, status, last, floor, iterations, K, theta_max, theta_min, x0, error, running, ceiling, budget, \
                tiny_steps = (v[keep] for v in (mu, status, last, floor, iterations, K, theta_max, theta_min, x0,
                                                error, running, ceiling, budget, tiny_steps))
            params = param_rows(params, keep)
            head = ahead = None  # the barrier update and all after it again, on the rows that stay
        if mehrotra:  # the affine-scaling predictor: complementarity S z = 0
            target_mu = torch.zeros_like(mu)
        else:
            # W&B §3.9: where steps were at round-off, μ decreased, or at its floor, stop (compiled: one kernel)
            mu, filt, status, running, tiny_steps, changed = head if head is not None else barrier_k(
                cons, model, it, mu, status, running, tiny_steps, filt, tol, opts, not fused)
            wd = wd.stop(changed)  # its reference φ^W belongs to the old μ
            target_mu = mu
        lqr, rhs = (None, None) if fused else newton_lqr(model, it, target_mu, x0, nx)

        def attempt(delta, rows=None):  # Mehrotra runs eager, keeping the factorisation for its corrector (kernels:
            # no kwargs); `rows`: the instances of a correction alone (regularized_direction's by_rows; not with
            # CUDA graphs, which replay the batch's shapes)
            if fused:
                return newton_k(model, it, target_mu, x0, delta, opts.sweep, opts.terminal_rows) if rows is None \
                    else direction_of_rows(newton_k, model, it, target_mu, x0, delta, rows, opts.sweep,
                                           opts.terminal_rows)
            system = (lqr, rhs, delta, model, it, target_mu) if rows is None else (
                lqr.rows(rows), gather_rows(rhs, rows), delta[rows], gather_rows(model, rows), gather_rows(it, rows),
                target_mu[rows])
            if mehrotra:
                return direction(*system, keep_factor=True, sweep=opts.sweep, terminal_rows=opts.terminal_rows)
            # eager, the factorisation is kept for the second-order corrections (they solve the same system)
            return direction_k(*system, None, None, eager, opts.sweep, opts.terminal_rows)

        d, delta = regularized_direction(attempt, floor, last, running, opts, by_rows=eager or fused,
                                         first=None if ahead is None else ahead[0])
        ahead = ahead if ahead is not None and d is ahead[0] else None  # (further attempts: the search made again)
        held = delta is floor  # no further attempt (corrected_attempts)
        factored = running & d.ok
        lost = torch.zeros_like(running)
        concluded = None  # compiled: the iteration's end, made by the kernel of its line search's first round
        # (compiled, δ_w is the floor itself where the first attempt was factorised: a copy, for one specialisation)
        delta_k = delta.clone() if fused and delta is floor else delta
        if mehrotra:  # no line search: the corrector's largest steps to the boundary
            mu, d, ls = mehrotra_step(model, it, d, lqr, delta, x0, tol / 10.0, ceiling, filt, factored, opts)
            factored = factored & d.ok
        else:
            def correct(need, a_max, phi, slope, first):  # W&B §2.3, on this iteration's system (the rows of the
                # instances that need it alone, but with CUDA graphs)
                return (correction_of_rows if eager or fused else second_order_correction)(
                    problem, cons, params, it, d, model, mu, phi, slope, filt, theta_max, theta_min, need, a_max,
                    first, lqr, delta, x0, opts)

            lost = running & ~d.ok & wd.running()  # a watchdog's full steps led where no step is found: back
            if may_return:  # a watchdog ran at the last synchronisation: no host test of `lost` itself
                it, last, wd = pick(lost, wd.it, it), torch.where(lost, wd.last, last), wd.stop(lost)
            watching = factored & (wd.running() | (wd.shortened >= opts.watchdog_trigger)) \
                if opts.watchdog_trigger > 0 else None
            # a superset of the instances watched now, known at the last synchronisation (watched_step on an empty
            # mask changes nothing)
            watched = watching is not None and may_watch
            pending = factored & ~watching if watched else factored
            first = None
            if fused and not watched:  # where that round settles the search
                first, settled_round, _, concluded = ahead[1] if ahead is not None else first_round_k(
                    problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, pending, corrects, opts, wd,
                    delta_k, last, tol, restoring, tiny_steps, floor, running, lost, status, iterations)
                first, concluded = (None, concluded) if bool(settled_round) else (first, None)
            if concluded is None:
                ls = line_search(problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, pending, opts,
                                 correct if corrects else None, first)
            if watched:
                watch, wd, returned = watched_step(problem, cons, params, it, d, model, mu, filt, theta_max,
                                                   theta_min, wd, watching, last, opts)
                ls = merge_steps(watching, watch, ls)
                last = torch.where(returned, wd.last, last)
        # the step taken, and the iteration's one synchronisation with the host (conclusion.Taken.flags); compiled,
        # one kernel call with the counts that follow it (and a filter reset's test whether or not one may come: the
        # same answer, and one graph)
        counted = None if mehrotra else watching if watched else torch.zeros_like(factored)
        if concluded is not None:
            taken, tiny_steps, settled = concluded
        elif fused:
            taken, tiny_steps, settled = conclude_k(wd, ls, d, it, filt, delta_k, last, factored, counted,
                                                    model.primal_error, tol, opts, True, restoring, tiny_steps, floor,
                                                    running, lost, status, iterations)
        else:
            taken, settled = take_step(wd, ls, d, it, filt, delta, last, factored, counted, model.primal_error,
                                       tol, opts, may_reset, restoring), None
        wd, it, filt, last, take, missed, entering = (taken.wd, taken.it, taken.filter, taken.last, taken.take,
                                                      taken.missed, taken.entering)
        enter_any, tiny_any, may_return, may_watch, may_reset, every = taken.flags.tolist()
        K = d.K if every else select_gains(take, d.K, K)  # formed for the solution (range-space rows: at the end)
        if not fused and ls.tiny is not None:  # (compiled: counted in the kernel)
            tiny_steps = tiny_counts(take, ls.tiny, d, tiny_steps, opts) if tiny_any \
                else torch.where(take, 0, tiny_steps)
        if enter_any:
            back = restore(problem, cons, params, x0, it, model, mu, filt, theta_max, entering, budget - iterations,
                           tol, opts, run)
            it, filt = back.it, back.filter
            status = torch.where(entering & ~back.returned, back.status, status)
            iterations = iterations + back.iterations
            floor = torch.where(back.returned, 0.0, floor)
            wd = wd.stop(entering)
            missed = missed & ~entering  # back, or ended with the restoration's status: no larger δ_w
            budgeted, settled = True, None
        floor, status, iterations = settle(take, missed, delta, floor, running, d.ok, lost, status, iterations, opts) \
            if settled is None else settled
        records.append((index, history_row(model, taken.step_size, delta, mu, error), True))
        if opts.verbose:
            logger.info("%s %4d  cost %.10g..%.10g  kkt %.2e  mu %.1e  running %d", method, step,
                        model.J.min().item(), model.J.max().item(), error.max().item(), mu.max().item(),
                        running.sum().item())
    status = torch.where(status == Status.RUNNING, int(Status.MAX_ITERATIONS), status)
    out = Final.of(it, (model.J, model.violation) if measures is None else measures, status, iterations,
                   (kernel_of(formed, opts, x0.device) if fused else formed)(K))
    return (out if final is None else final.write(index, out)), cons, records
