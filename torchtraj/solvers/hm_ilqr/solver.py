r"""HM-iLQR (method ``"hm-ilqr"``; Tang, Chu, Jin & Au, Algorithm 4) for batches, each instance in its own stage.

Every instance runs the paper's two stages on the multiple-shooting M-iLQR iteration
(:mod:`~torchtraj.solvers.hm_ilqr.shooting`):

1. **AL stage** (Algorithm 2): M-iLQR iterations on ``J_1`` (:mod:`~torchtraj.solvers.hm_ilqr.objective`) with
   plain line search; the multiplier update (15) after an iteration that changed ``J_1`` by less than
   ``al_update_tolerance`` (the "if update"), with the penalty update (16) where the violation did not halve; it
   hands over once the violation of the constraints and of the defects is below ``c_min^al`` (or after
   ``al_iterations``);
2. **RLB stage** (Algorithm 3): M-iLQR iterations on ``J_2`` with CRLS (:mod:`~torchtraj.solvers.hm_ilqr.crls`),
   ``ψ, δ`` follow (18a-b) after a step whose predicted decrease was below ``κ ψ`` (the barrier problem of that
   ``ψ`` nearly solved). Beyond the paper (``dynamics_curvature``, ``second_order_correction``, on by default):
   the model adds the dynamics' curvature (Newton's model of the barrier problem;
   :mod:`~torchtraj.solvers.hm_ilqr.objective`), with the stage Hessians shifted where it is not convex, the
   Gauss-Newton one where no shift helps and once after a failed iteration with it, and a refused full step gets
   a second-order correction (:mod:`~torchtraj.solvers.hm_ilqr.crls`);
3. **done** where ``ψ`` has reached ``ψ_min``, the violation of the constraints and the defects is at most
   ``c_min^rlb`` and the stationarity residual at the iterate, with the inequality multipliers ``z⁺`` of its Newton
   step (:mod:`~torchtraj.solvers.hm_ilqr.multipliers`), is below ``stationarity_tolerance`` (that step is still
   taken where the point it reaches passes the same test, else the iterate is returned); or where an RLB iteration
   changes the objective by less than ``ε_v`` (the paper's test; off by default,
   :mod:`~torchtraj.solvers.hm_ilqr.options` says why) or the model predicts no decrease and no step is found. The
   tolerances are met at the dtype's resolution where they lie below it.

The stage of each instance is a mask; no instance waits on another, and the only host synchronisations are the
batch-wide "anything still running" test of each iteration and those of the line search and CRLS rounds. The start
is a state guess ``X0`` (any, dynamically inconsistent: its knots at the segment starts are the nodes), else the
problem's ``X_init``, else the paper's linear interpolation from ``x_0`` to the goal where the problem's parameters
name one (``params["goal"]``, as the problem set's do), else the rollout of ``U0``.

The solution carries the multipliers of every block: on the inequality rows the barrier's implied multipliers
``B' = ψ / (−g)`` corrected along the Newton step at the final point (``z⁺``; the AL estimates
``max(0, λ + μ g)`` for an instance still in the AL stage), on the
equality rows the Riccati core's ``ν`` (RLB stage) or ``λ + μ h`` (AL stage), the costates of the expanded
objective and the gains of a backward pass at the final point; a converged solve is a KKT point of the problem up to
``ψ_min``, which the implicit layer refines (``kkt_point``).
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from ...core.batch import Batch
from ...core.batching import recorded_map_stage, rollout
from ...core.compiled import kernel
from ...core.constraints import Constraints, multiplier_blocks
from ...core.masks import RowPicker
from ...core.problem import Problem
from ...core.solution import History, Solution
from ...core.status import Status
from .augmented_lagrangian import increased_penalty, updated_multipliers
from .barrier import updated_barrier
from .crls import factorized, iterate, with_curvature
from .multipliers import stepped_multipliers, with_multipliers
from .objective import HybridObjective, StageParameters
from .options import HMILQROptions
from .shooting import Segments, defects, rollout_segments, stationarity

logger = logging.getLogger("torchtraj")
AL, RLB = 0, 1


def initial_states(problem: Problem, batch: Batch) -> Tensor:
    """The state guess ``(B, N+1, nx)`` or ``None`` (module docstring)."""
    if batch.X0 is not None:
        return batch.X0
    if problem.X_init is not None:
        return problem.X_init.expand(batch.B, *problem.X_init.shape)
    goal = batch.params.get("goal")
    if goal is not None and goal.shape[-1:] == (problem.nx,) and goal.dim() == 2:
        s = torch.linspace(0, 1, problem.N + 1, dtype=problem.dtype, device=problem.device).reshape(1, -1, 1)
        return batch.x0.unsqueeze(1) + s * (goal - batch.x0).unsqueeze(1)
    return None


def start_states(problem: Problem, batch: Batch) -> Tensor:
    """The states ``(B, N+1, nx)`` a solve starts from: :func:`initial_states`, else the rollout of ``U0`` (no
    defects to close)."""
    guess = initial_states(problem, batch)
    return rollout(problem.dynamics, batch.x0, batch.U0, batch.params) if guess is None else guess


def solve_hm_ilqr(problem: Problem, batch: Batch, options: HMILQROptions, method: str = "hm-ilqr") -> Solution:
    """Solve the ``batch`` of instances of ``problem`` by HM-iLQR (module docstring)."""
    opts = options
    x0, params, B = batch.x0, batch.params, batch.B
    constraints = Constraints.of(problem)
    segments = Segments.of(problem.N, opts.segments, x0.device)
    guess = start_states(problem, batch)
    nodes = guess[:, segments.starts].clone()
    nodes[:, 0] = x0
    X, U, gaps = rollout_segments(problem.dynamics, params, nodes, batch.U0, segments,  # Algorithm 1, lines 2-8
                                  record=opts.record)
    like = x0
    c = constraints
    stage_params = StageParameters(
        rlb=torch.full((B,), opts.al_iterations == 0, dtype=torch.bool, device=x0.device),
        lam=like.new_zeros(B, problem.N, c.mi), lamN=like.new_zeros(B, c.miN),
        lamE=like.new_zeros(B, problem.N, c.me), lamEN=like.new_zeros(B, c.meN),
        mu=like.new_full((B,), opts.penalty_initial), psi=like.new_full((B,), opts.barrier_initial),
        delta=like.new_full((B,), opts.relaxation_initial))
    objective = HybridObjective(constraints, stage_params, opts.record)
    point, last_violation, violation = _measures(objective, constraints, problem, segments, X, U, params)
    J = objective.value(X, U, params, point)
    D = gaps + objective.equality_residual(X, U, params, point)
    status = torch.full((B,), int(Status.RUNNING), dtype=torch.long, device=x0.device)
    finite_start = torch.isfinite(J) & torch.isfinite(X).flatten(1).all(-1) & torch.isfinite(D)
    status = torch.where(~torch.isfinite(x0).all(-1), int(Status.NON_FINITE), status)
    status = torch.where((status == Status.RUNNING) & ~finite_start, int(Status.INFEASIBLE_START), status)
    mu_V = like.new_full((B,), opts.regularization_initial)
    defect_weight = like.new_full((B,), opts.defect_weight)
    iterations = torch.zeros(B, dtype=torch.long, device=x0.device)
    al_iterations = torch.zeros_like(iterations)
    tol = opts.tolerances(x0.dtype)
    rows = []
    stationarity = torch.zeros_like(mu_V)  # the last running iterate's: a stopped instance's history repeats it
    nu = nuN = None
    flat = torch.zeros(B, dtype=torch.bool, device=x0.device)
    expand_k, measures_k = kernel(HybridObjective.expand, opts.compile), kernel(_measures, opts.compile)
    curvature_k = kernel(HybridObjective.dynamics_curvature, opts.compile)
    for it in range(opts.iterations):
        active = status == Status.RUNNING
        if not bool(active.any()):  # the iteration's host synchronisation
            break
        s = objective.params
        lqr, rhs, f, ineq = expand_k(objective, X, U, params)
        rhs.c = defects(f, X, segments)
        crls = s.rlb & opts.crls
        start_mu_V = torch.where(crls, torch.full_like(mu_V, opts.regularization_initial), mu_V)
        curved = active & s.rlb & ~flat
        factor = None
        if opts.dynamics_curvature and bool(curved.any()):  # the iteration's second host synchronisation
            lqr, curved, factor = with_curvature(
                lqr, curvature_k(objective, lqr, rhs, X, U, params, curved, nu, nuN), curved, start_mu_V,
                opts.terminal_rows, opts.curvature_shifts, opts.compile)
        else:
            curved = torch.zeros_like(curved)
        t = iterate(problem, objective, params, segments, X, U, J, D, lqr, rhs, ineq, start_mu_V, active, crls, opts,
                    defect_weight if opts.monotone_defect_weight else None, curved, factor)
        # the floor keeps the weights of steps of CRLS's first round (μ_V^0) only (options: monotone_defect_weight)
        keeps = active & t.took & (~crls | (t.mu_V <= start_mu_V))
        defect_weight = torch.where(keeps, torch.maximum(defect_weight, t.weight), defect_weight)
        stationarity = torch.where(active, t.residual, stationarity)
        # the held rows' multipliers for the next expansion's costates (the last LQR step's)
        nu, nuN = _finite(t.nu, nu, active), _finite(t.nuN, nuN, active)
        # converged: the start point is a KKT point of the problem (with the multipliers z⁺) at the barrier's
        # final weight; its step, a Newton step on the barrier problem, is taken all the same (the solution then
        # follows the barrier's minimiser smoothly in x0 and the parameters, as a re-solve from a perturbed start
        # does: central differences of re-solves stopped a step short differed from the gradient by 6e-4), where its
        # point passes the same test; where it does not, the start point is returned (_stepped_stationarity)
        kkt = (active & s.rlb & (violation <= tol.constraint) & (s.psi <= tol.barrier * (1 + 1e-9))
               & (t.residual <= tol.stationarity))
        dJ = J - t.J
        start = X, U, J, D
        X, U, J, D = t.X, t.U, t.J, t.D
        if bool(kkt.any()):  # the step's point must pass the test as well, or the start point is returned
            back = kkt & ~(_stepped_stationarity(objective, X, U, params, segments, opts.terminal_rows)
                          <= tol.stationarity)
            undo = RowPicker(back)
            X, U, J, D = (undo(before, after) for before, after in zip(start, (X, U, J, D)))
        iterations = iterations + active.long()
        # regularisation: CRLS keeps what it reached; plain LS follows its schedule
        plain = torch.where(t.took | t.stationary, (mu_V / opts.regularization_increase).clamp_min(
            opts.regularization_initial), (mu_V * opts.regularization_increase).clamp_max(opts.regularization_max))
        mu_V = torch.where(active, torch.where(crls, t.mu_V, plain), mu_V)
        # the iterate's objective and rows, read by everything below
        point, rows_violation, violation = measures_k(objective, constraints, problem, segments, X, U, params)
        moved = t.took | t.stationary
        # the exit tests of an RLB instance, before its parameters move (its multipliers are those of this ψ): the
        # stationarity residual at the start point (above), or no step left, or the paper's ε_v
        done = kkt | (active & s.rlb & moved & (violation <= tol.constraint)
                      & (s.psi <= tol.barrier * (1 + 1e-9))
                      & (t.stationary | (dJ.abs() < opts.cost_tolerance)))
        failed = active & t.failed & (crls | (mu_V >= opts.regularization_max)) & ~kkt & ~curved
        flat = torch.where(active, t.failed & curved, flat)  # the Gauss-Newton model once after a failed Newton one
        # the paper's pure LS (Fig. 5): a failed line search of the RLB stage ends the solve
        stopped = active & t.failed & s.rlb & ~crls & opts.failed_search_stops & ~kkt & ~failed
        # AL stage: multipliers and penalty after every iteration (eqs. 15-16); RLB stage: ψ, δ (18) and the
        # equality rows' AL terms after every accepted step
        # Algorithm 2's "if update": the multipliers move once the inner M-iLQR has nearly converged on J_1 (a
        # relative change of J_1 below al_update_tolerance; inf: after every iteration)
        inner_done = moved & (t.stationary | (dJ.abs() <= opts.al_update_tolerance * (1 + J.abs())))
        update_al = active & ~s.rlb & inner_done
        # Algorithm 3's "if update": ψ, δ move once the barrier problem of this ψ is nearly solved
        update_rlb = active & s.rlb & moved & ~done & (t.decrease <= opts.barrier_update * s.psi)
        # eq. (16)'s penalty increase where the violation of the rows did not shrink enough
        grow = rows_violation > opts.penalty_trigger * last_violation
        new = _updated(objective, point, s, update_al, update_rlb, grow, opts, tol)
        last_violation = torch.where(update_al | update_rlb, rows_violation, last_violation)
        al_iterations = al_iterations + (active & ~s.rlb).long()
        handover = active & ~s.rlb & ((update_al & (violation <= opts.constraint_tolerance_al))
                                      | (al_iterations >= opts.al_iterations))
        new.rlb = s.rlb | handover
        defect_weight = torch.where(handover, opts.defect_weight, defect_weight)
        held_before = objective.equality_residual(X, U, params, point)
        objective = HybridObjective(constraints, new, opts.record)
        J = torch.where(active, objective.value(X, U, params, point), J)  # the objective of the new parameters
        # handed over: the goal joins the defects
        D = D - held_before + objective.equality_residual(X, U, params, point)
        status = torch.where(done, int(Status.CONVERGED), status)
        status = torch.where(failed & ~done, int(Status.MAX_REGULARIZATION), status)
        status = torch.where(stopped & ~done, int(Status.STALLED), status)
        rows.append({
            "cost": point.cost, "max_violation": violation, "step_size": t.alpha,
            "regularization": mu_V, "stage": s.rlb.long(), "defect_norm": D.sqrt(), "barrier": s.psi,
            "relaxation": s.delta, "penalty": s.mu, "stationarity": stationarity,
        })
        if opts.verbose:
            logger.info("hm-ilqr %4d  cost %.10g  violation %.2e  rlb %d  running %d", it,
                        float(rows[-1]["cost"].max()), float(violation.max()), int(s.rlb.sum()), int(active.sum()))
    status = torch.where(status == Status.RUNNING, int(Status.MAX_ITERATIONS), status)
    return _solution(problem, objective, constraints, segments, X, U, params, point, status, iterations, rows, mu_V,
                     method, opts.terminal_rows)


def _finite(new, old, active):
    """``new`` where finite and ``active (B,)``, else ``old`` (0 where there is none); ``None`` stays ``None``."""
    if new is None:
        return old
    if old is None:
        old = torch.zeros_like(new)
    keep = active.reshape(-1, *([1] * (new.dim() - 1))) & torch.isfinite(new)
    return torch.where(keep, new, old)


def _measures(objective: HybridObjective, constraints: Constraints, problem: Problem, segments: Segments, X: Tensor,
              U: Tensor, params) -> tuple:
    """``(point, rows_violation, violation)`` at ``(X, U)``: the objective's values and rows
    (:meth:`HybridObjective.point`), the largest violation of the rows ``(B,)`` and with the defects at the nodes."""
    point = objective.point(X, U, params)
    rows_violation = constraints.max_violation_of(point.h, point.g, point.hN, point.gN)
    return point, rows_violation, torch.maximum(rows_violation, _max_defect(X, U, problem, params, segments,
                                                                            objective.record))


def _max_defect(X, U, problem, params, segments, record) -> Tensor:
    """Largest defect ``|d_k|_∞`` ``(B,)`` at the nodes (the dynamics replayed from their record as ``record``,
    ``HMILQROptions.record``, says)."""
    k = segments.starts[1:] - 1
    if k.numel() == 0:
        return X.new_zeros(X.shape[0])
    f = recorded_map_stage(problem.dynamics, X[:, k], U[:, k], params, record)
    return (f - X[:, k + 1]).abs().flatten(1).amax(-1)


def _updated(objective, point, s: StageParameters, update_al, update_rlb, grow, opts, tol) -> StageParameters:
    """The stage parameters after an iteration at the iterate whose rows are ``point``'s
    (:meth:`HybridObjective.point`): eq. (15) and, where ``grow``, (16) where ``update_al``; (18) where
    ``update_rlb``."""
    lam, lamN = s.lam, s.lamN
    if objective.mi:
        cand = updated_multipliers(point.g * objective.knot_mask, lam, s.mu.reshape(-1, 1, 1), opts.dual_max)
        lam = torch.where(update_al.reshape(-1, 1, 1), cand, lam)
    if objective.miN:
        cand = updated_multipliers(point.gN, lamN, s.mu.reshape(-1, 1), opts.dual_max)
        lamN = torch.where(update_al.reshape(-1, 1), cand, lamN)
    lamE, lamEN = s.lamE, s.lamEN
    if objective.me:  # the equality rows' AL multipliers, λ ← λ + μ h
        lamE = torch.where(update_al.reshape(-1, 1, 1), s.lamE + s.mu.reshape(-1, 1, 1) * point.h,
                           s.lamE).clamp(-opts.dual_max, opts.dual_max)
    if objective.meN:
        lamEN = torch.where(update_al.reshape(-1, 1), s.lamEN + s.mu.reshape(-1, 1) * point.hN,
                            s.lamEN).clamp(-opts.dual_max, opts.dual_max)
    mu = torch.where(update_al & grow, increased_penalty(s.mu, opts.penalty_scaling, opts.penalty_max), s.mu)
    psi, delta = updated_barrier(s.psi, s.delta, opts, tol)
    return StageParameters(rlb=s.rlb, lam=lam, lamN=lamN, lamE=lamE, lamEN=lamEN, mu=mu,
                           psi=torch.where(update_rlb, psi, s.psi), delta=torch.where(update_rlb, delta, s.delta))


def _final_step(objective, X, U, params, segments, terminal_rows: str) -> tuple:
    """``(lqr, rhs, rows, factor, step, z, zN)`` at ``(X, U)``: the expansion, the unregularised LQR step with its
    multipliers and the inequality rows' multipliers ``z⁺`` corrected along it
    (:mod:`~torchtraj.solvers.hm_ilqr.multipliers`), what a solution reports."""
    lqr, rhs, f, rows = objective.expand(X, U, params)
    rhs.c = defects(f, X, segments)
    factor = factorized(lqr, X.new_zeros(X.shape[0]), terminal_rows)
    step = factor.solve(rhs, multipliers=True)
    z, zN = stepped_multipliers(rows, step.dx, step.du, objective.params.rlb)
    return lqr, rhs, rows, factor, step, z, zN


def _stepped_stationarity(objective, X, U, params, segments, terminal_rows: str) -> Tensor:
    """The stationarity residual ``(B,)`` at ``(X, U)`` with the multipliers a solution there reports: the last
    step of a converged instance is taken from a point that passed the test, and the Gauss-Newton model (no
    curvature of the dynamics) can leave the new point less stationary (quadrotor2d's ``sample_x0`` starts 38, 50
    and 53: 2.1e-7 before the step, 1.1e-6 after, above the certificate's 1e-6)."""
    lqr, rhs, rows, _, step, z, zN = _final_step(objective, X, U, params, segments, terminal_rows)
    return stationarity(lqr, with_multipliers(rhs, rows, X.shape[-1], z, zN), step.nu, step.nuN)


def _solution(problem, objective, constraints, segments, X, U, params, point, status, iterations, rows, mu_V, method,
              terminal_rows: str):
    """Gains, costates and multipliers at the final point (one more expansion and LQR solve; ``point`` its objective
    and rows, :meth:`HybridObjective.point`), and the :class:`Solution`."""
    # the equality rows' multipliers ν of the LQR step at the final point; the costates from the Lagrangian's
    # stationarity in the states, λ_N = q_N + C_Nᵀ ν_N, λ_k = q_k + A_kᵀ λ_{k+1} + C_kᵀ ν_k (q holds the inequality
    # rows' P'), which at a converged point is the Riccati costate without its step terms; the inequality rows'
    # multipliers corrected along that step
    lqr, rhs, ineq_rows, factor, step, z, zN = _final_step(objective, X, U, params, segments, terminal_rows)
    ineq, ineqN = objective.multipliers(X, U, params)
    ineq, ineqN = ineq if z is None else z, ineqN if zN is None else zN
    rhs = with_multipliers(rhs, ineq_rows, X.shape[-1], z, zN)
    B = X.shape[0]
    # the equality rows: the core's ν where they are held (RLB stage), the AL estimate λ + μ h elsewhere
    s = objective.params
    eq, eqN = X.new_zeros(B, problem.N, 0), X.new_zeros(B, 0)
    if constraints.me:
        eq = torch.where(s.rlb.reshape(-1, 1, 1), step.nu, s.lamE + s.mu.reshape(-1, 1, 1) * point.h)
    if constraints.meN:
        eqN = torch.where(s.rlb.reshape(-1, 1), step.nuN, s.lamEN + s.mu.reshape(-1, 1) * point.hN)
    violation = torch.maximum(constraints.max_violation_of(point.h, point.g, point.hN, point.gN),
                              _max_defect(X, U, problem, params, segments, objective.record))
    return Solution(
        X=X, U=U, K=factor.K, cost=point.cost, max_violation=violation, status=status,
        iterations=iterations, history=History.from_rows(rows),
        costate=_adjoint(lqr, rhs, eq if constraints.me else None, eqN if constraints.meN else None, s.rlb),
        multipliers=multiplier_blocks(constraints, torch.cat([ineq, eq], -1), torch.cat([ineqN, eqN], -1)),
        penalties={name: s.mu for name, rows_ in constraints.split_ineq(ineq).items()}, method=method,
    )


def _adjoint(lqr, rhs, nu, nuN, held) -> Tensor:
    """``λ (B, N+1, nx)``: ``λ_N = q_N + C_Nᵀ ν_N``, ``λ_k = q_k + A_kᵀ λ_{k+1} + C_kᵀ ν_k``, the ``ν`` terms where
    the rows are ``held (B,)`` (elsewhere their AL terms are inside ``q``)."""
    if nu is not None:
        nu = nu * held.reshape(-1, 1, 1).to(nu.dtype)
    if nuN is not None:
        nuN = nuN * held.reshape(-1, 1).to(nuN.dtype)
    def tmv(M, v):
        return (M.transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1)

    lam = rhs.qN if nuN is None else rhs.qN + tmv(lqr.CN, nuN)
    lams = [lam]
    for k in range(lqr.A.shape[1] - 1, -1, -1):
        lam = rhs.q[:, k] + tmv(lqr.A[:, k], lam)
        if nu is not None:
            lam = lam + tmv(lqr.C[:, k], nu[:, k])
        lams.append(lam)
    return torch.stack(lams[::-1], 1)
