r"""One M-iLQR iteration with its globalisation: plain line search, or CRLS (§III-C, Algorithm 5).

**Regularisation** (eq. 21). ``μ_V I`` is added to the next state's value Hessian where the gains are formed,
``Q̃_uu = ℓ_uu + f_uᵀ (V_xx + μ_V I) f_u``, ``Q̃_ux = ℓ_ux + f_uᵀ (V_xx + μ_V I) f_x``. The shared Riccati core
(:func:`~torchtraj.riccati.factorize`) takes it as the stage term ``μ_V W_kᵀ W_k`` with ``W_k = [A_k B_k]``, i.e.
``μ_V/2 ‖A_k δx_k + B_k δu_k‖²``, a proximal term on the change of the next state: its ``Q_uu`` and ``Q_ux`` are
exactly eq. (21a-b), and the value function it propagates is that of the regularised model (its ``Q_xx`` also gains
``μ_V A_kᵀ A_k``), which keeps every stage's Hessian positive semidefinite. A larger ``μ_V`` gives the feedback
term more weight and the step in the states less: the lagged effect the paper exploits.

**Plain LS** (the AL stage, and the RLB stage with ``crls=False``): one backward pass and one backtracking line
search ``α ∈ {1, γ, γ², …}`` (eq. 20); a failure raises ``μ_V ← min(σ μ_V, μ_V^max)`` for the next iteration and the
iteration takes no step, a success lowers it, ``μ_V ← max(μ_V / σ, μ_V^0)``. With ``failed_search_stops`` a failed
search of the RLB stage ends the solve instead: the paper's pure LS, against which its Fig. 5 measures CRLS.

**CRLS** (the RLB stage): each iteration starts from ``μ_V^0``; where the backward pass fails (a reduced Hessian
not positive definite) or the line search finds no step down to ``α_min``, the iteration returns to the backward
pass with ``μ_V ← min(σ μ_V, μ_V^max)`` (eq. 22) instead of ending, until a step is accepted or ``μ_V^max`` is
reached. The expansion is not repeated: only the factorisation and the line search. On a batch each instance
leaves the loop on its own (masks); a further round runs while any instance is still searching.

**Newton steps** (with the dynamics' curvature, :mod:`~torchtraj.solvers.hm_ilqr.objective`). Where the model is
nearly singular its step is long and the line search would cut it to ``α`` of 1e-3 for hundreds of iterations
(measured on a cart-pole start); a step of the curvature's model is accepted only down to ``α ≥
curvature_step_min``, below which CRLS raises ``μ_V`` as after a failed search (a Levenberg-Marquardt-like
damping of the long direction instead of a shorter step along it).

**Second-order correction** (an extension beyond the paper, ``second_order_correction``; Wächter & Biegler 2006,
§2.4; Nocedal & Wright 2006, §15.5). The full step meets the linearised defects; the rollout leaves defects of second
order at the nodes, which the merit's weight ``w`` (raised as the defects close, ``w ≥ (ΔV_1 + ΔV_2/2) / Σ dᵀd``) can
charge more than the step gains: measured on the cart-pole, ``w = 7.8e4`` and a full step whose defects of
``Σ dᵀd = 3e-10`` cost ``2.6e-5`` against a predicted decrease of ``7e-7`` (the Maratos effect). Where the ratio test
refuses ``α = 1``, the same factorisation solves again with the defects ``c + c⁺`` (and held rows ``e + e⁺``), ``c⁺``
those of the refused trial point, and that corrected step is tried at ``α = 1`` against the same predicted change
before the search shortens the step. With the Gauss-Newton model alone it converged none of the six failing
cart-pole starts of issue 23 (the full steps there also raise the objective itself); what it adds to the
curvature's model has not been measured on its own.

**Round-off.** The ratio test compares the actual change of the merit with the model's; where both lie below
``10 ε |merit|`` (``ε`` the dtype's resolution) the actual change is rounding noise and the ratio says nothing, so
the step is accepted as the model predicts it (Wächter & Biegler 2006, §3.9, relax IPOPT's Armijo test by the same
amount). Without this, a step whose decrease float32 cannot resolve (an AL subproblem nearly solved, a barrier
problem whose active rows have curvature ``ψ/z²``) is refused at every ``α``: plain LS raises ``μ_V`` to its
maximum (``MAX_REGULARIZATION``), and the last Newton steps that make the barrier's multipliers consistent, which
change the objective by ``|r|²/(ψ/z²)`` for a stationarity residual ``r``, are never taken even in float64.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...core.batching import param_rows, rows_of
from ...core.compiled import kernel
from ...core.masks import where_rows
from ...globalization.line_search import Accepted, backtrack
from ...riccati import factorize
from .objective import HybridObjective
from .trials import corrected_step, ratio_test, round_model, start_residual


@dataclass
class Trial:
    """The outcome of an iteration (all ``(B, ...)``): the accepted point ``X``, ``U``, its objective ``J``, its
    infeasibility ``D = Σ dᵀd + Σ hᵀh`` (defects and equality rows); ``took`` a step; ``stationary`` (the model predicts
    no decrease); ``failed`` (no step and no regularisation left); the step size ``alpha``, the final ``mu_V`` and the
    gains ``K``."""

    X: Tensor
    U: Tensor
    J: Tensor
    D: Tensor
    took: Tensor
    stationary: Tensor
    failed: Tensor
    alpha: Tensor
    mu_V: Tensor
    K: Tensor
    decrease: Tensor  # the model's predicted decrease of the merit at α = 1 (B,)
    residual: Tensor  # the stationarity residual at the start point (B,), :func:`~.shooting.stationarity`
    weight: Tensor  # the defect weight of the accepted step (B,); 0 where none was accepted
    nu: object  # the held rows' multipliers ν (B, N, me) of the first (least regularised) LQR step, or None
    nuN: object  # ν_N (B, meN), or None


def regularized(lqr, mu_V: Tensor):
    """The LQR with ``μ_V W_kᵀ W_k`` added to every stage (eq. 21, module docstring); its rows kept."""
    A, Bm = lqr.A, lqr.B
    m = mu_V.reshape(-1, 1, 1, 1)
    At, Bt = A.transpose(-1, -2), Bm.transpose(-1, -2)
    return dataclasses.replace(lqr, Q=lqr.Q + m * (At @ A), R=lqr.R + m * (Bt @ Bm), S=lqr.S + m * (Bt @ A),
                               W=None, H=None)


def factorized(lqr, mu_V: Tensor, terminal_rows: str):
    """The backward pass of :func:`regularized` ``(lqr, mu_V)``, its terminal rows held as ``terminal_rows`` says
    (:attr:`~torchtraj.solvers.hm_ilqr.options.HMILQROptions.terminal_rows`)."""
    return factorize(regularized(lqr, mu_V), terminal_rows=terminal_rows)


def _solve_rhs(factor, rhs, multipliers: bool):
    return factor.solve(rhs, multipliers=multipliers)


def solved(factor, rhs, multipliers: bool, compiled: bool):
    """``factor.solve(rhs, multipliers)`` (a :class:`~torchtraj.riccati.RiccatiFactor` or a range-space one),
    compiled where ``compiled`` (``HMILQROptions.compile``)."""
    return kernel(_solve_rhs, compiled)(factor, rhs, multipliers)


def with_curvature(lqr, curvature: Tensor, curved: Tensor, mu_V: Tensor, terminal_rows: str,
                   shifts: tuple = (), compiled: bool = False) -> tuple:
    """``lqr`` with the stage Hessians' ``curvature (B, N, nz, nz)`` added where ``curved (B,)``: as it is where the
    backward pass at ``mu_V (B,)`` succeeds with it; elsewhere with the stage Hessians shifted by ``δ I``, the
    smallest ``δ = s δ*`` for ``s`` in ``shifts`` (increasing) with which it succeeds, ``δ*`` the largest negative
    eigenvalue of the curvature blocks in magnitude (objective module docstring, "Dynamics curvature"); the
    Gauss-Newton model where none does. Returns the LQR, the instances that took the curvature, and, where every
    curved instance took it (shifted or not), the factorisation of the returned LQR at ``mu_V`` (else ``None``):
    the iteration's first backward pass, which :func:`iterate` need not repeat. Each attempt factorises the LQR it
    would return if every instance still pending succeeded (the others' rows as they are: each row on its own);
    ``compiled``: each attempt's backward pass a compiled kernel (``HMILQROptions.compile``)."""
    nx = lqr.A.shape[-1]
    full = dataclasses.replace(lqr, Q=lqr.Q + curvature[..., :nx, :nx], R=lqr.R + curvature[..., nx:, nx:],
                               S=lqr.S + curvature[..., nx:, :nx])
    tried = _taking(lqr, full, curved)
    factorize_k = kernel(factorized, compiled)
    factor = factorize_k(tried, mu_V, terminal_rows)
    use = curved & factor.ok
    if not bool((curved & ~use).any()):  # a host synchronisation; every curved instance took its curvature
        return tried, use, factor
    shift = torch.zeros_like(mu_V)
    if shifts:
        worst = -torch.linalg.eigvalsh(0.5 * (curvature + curvature.transpose(-1, -2)))[..., 0].amin(-1)
        for s in shifts:
            pending = curved & ~use
            if not bool(pending.any()):
                break
            candidate = torch.where(pending, s * worst.clamp_min(0), shift)
            tried = _taking(lqr, shifted(full, candidate), use | pending)
            factor = factorize_k(tried, mu_V, terminal_rows)
            ok = pending & factor.ok
            shift = torch.where(ok, candidate, shift)
            use = use | ok
        if bool((curved & ~use).any()):  # some fall back to Gauss-Newton: the last attempt's LQR is not theirs
            factor = None
    else:
        factor = None
    return _taking(lqr, shifted(full, shift), use), use, factor


def _taking(lqr, full, take: Tensor):
    """``lqr`` with the stage Hessians of ``full`` where ``take (B,)``."""
    m = take.reshape(-1, 1, 1, 1)
    return dataclasses.replace(lqr, Q=torch.where(m, full.Q, lqr.Q), R=torch.where(m, full.R, lqr.R),
                               S=torch.where(m, full.S, lqr.S))


def shifted(lqr, delta: Tensor):
    """``lqr`` with ``δ I`` added to every stage Hessian, ``delta (B,)``."""
    d = delta.reshape(-1, 1, 1, 1)
    eye_x = torch.eye(lqr.Q.shape[-1], dtype=lqr.Q.dtype, device=lqr.Q.device)
    eye_u = torch.eye(lqr.R.shape[-1], dtype=lqr.R.dtype, device=lqr.R.device)
    return dataclasses.replace(lqr, Q=lqr.Q + d * eye_x, R=lqr.R + d * eye_u)


def iterate(problem, objective, params, segments, X, U, J, D, lqr, rhs, rows, mu_V, active, retry, opts,
            weight_floor=None, curved=None, factor=None) -> Trial:
    """One iteration on the instances of ``active (B,)`` from the expansion ``(lqr, rhs, rows)`` at ``(X, U)``; those of
    ``retry (B,)`` use CRLS (their ``mu_V`` is the start ``μ_V^0``), the others plain LS. ``factor``: the
    factorisation of ``lqr`` at ``mu_V`` where already made (:func:`with_curvature`), the first round's. A round after
    the first factorises and searches for the instances still pending alone (one read of their count by the host): in
    a large batch a few need a larger ``μ_V``, and the others' factorisations and trial points would be made again to
    be thrown away. Each instance's arithmetic is the same."""
    B = X.shape[0]
    steps = opts.line_search_decrease ** torch.arange(opts.line_search_steps, dtype=X.dtype, device=X.device)
    rounds = 1 + max(0, math.ceil(math.log(opts.regularization_max / opts.regularization_initial)
                                  / math.log(opts.regularization_increase)))
    zero = torch.zeros(B, dtype=torch.bool, device=X.device)
    accepted = Accepted(found=zero, alpha=torch.zeros_like(J), values=(X, U, J, D))
    stationary, searched = zero, zero
    decrease = torch.zeros_like(J)
    used = torch.zeros_like(J)
    K = lqr.A.new_zeros(B, *lqr.B.shape[1:2], lqr.B.shape[-1], lqr.A.shape[-1])
    whole = _Instances(problem, objective, params, segments, X, U, J, D, lqr, rhs, weight_floor, curved)
    per_round = max(1, min(len(steps), 8192 // max(B, 1)))  # step sizes simulated together, as iLQR's search
    factorize_k = kernel(factorized, opts.compile)
    for r in range(rounds):
        pending = active & ~accepted.found & ~stationary & (retry | ~searched)
        if not bool(pending.any()):  # the round's host synchronisation
            break
        index = None if r == 0 else _pending_rows(pending)
        if index is None:  # the whole batch
            factor = factor if r == 0 and factor is not None else factorize_k(lqr, mu_V, opts.terminal_rows)
            sol = solved(factor, rhs, r == 0, opts.compile)
            if r == 0:  # the KKT residual at the start point, with the multipliers of the first (least regularised)
                # step
                residual = kernel(start_residual, opts.compile)(lqr, rhs, rows, sol, objective.params.rlb)
                nu, nuN = sol.nu, sol.nuN
            out = _search_round(whole, factor, sol, pending, accepted, steps, per_round, opts)
        else:  # the pending instances alone, written into a round of the whole batch (the others not searched)
            sub = whole.rows(index)
            sub_factor = factorize_k(sub.lqr, mu_V[index], opts.terminal_rows)
            sub_accepted = Accepted(found=accepted.found[index], alpha=accepted.alpha[index],
                                    values=tuple(v[index] for v in accepted.values))
            out = _search_round(sub, sub_factor, solved(sub_factor, sub.rhs, False, opts.compile),
                                torch.ones_like(index, dtype=torch.bool),
                                sub_accepted, steps, per_round, opts)
            out = out.on_batch(index, _Round(ok=zero, full=decrease, still=zero, search=zero, K=K, weight=used,
                                             step=Accepted(found=zero, alpha=accepted.alpha, values=accepted.values)))
        decrease = torch.where(pending, out.full, decrease)
        K = where_rows(pending, out.K, K)
        new = out.step.found & out.search
        used = torch.where(new, out.weight, used)
        stationary = stationary | (pending & out.ok & out.still & ~new)
        accepted = Accepted(found=accepted.found | new, alpha=torch.where(new, out.step.alpha, accepted.alpha),
                            values=tuple(where_rows(new, a, b) for a, b in zip(out.step.values, accepted.values)))
        searched = searched | pending
        grow = pending & ~new & ~stationary & retry & (mu_V < opts.regularization_max)
        mu_V = torch.where(grow, (mu_V * opts.regularization_increase).clamp_max(opts.regularization_max), mu_V)
        retry = retry & grow | retry & ~pending
    Xa, Ua, Ja, Da = accepted.values
    took = active & accepted.found
    failed = active & ~took & ~stationary
    return Trial(Xa, Ua, Ja, Da, took, active & stationary, failed, accepted.alpha, mu_V, K, decrease, residual, used,
                 nu, nuN)


def _pending_rows(pending: Tensor):
    """The indices of the ``pending (B,)`` instances, ``None`` where they are the whole batch (no gathering)."""
    index = pending.nonzero().squeeze(-1)
    return None if index.numel() == pending.shape[0] else index


@dataclass
class _Instances:
    """What a round of :func:`iterate` reads per instance: the problem, its objective and parameters, the segments,
    the point ``X``, ``U``, ``J``, ``D``, the LQR model ``lqr``, ``rhs``, the defect weight's floor and the curved
    instances (``None``: none)."""

    problem: object
    objective: HybridObjective
    params: dict
    segments: object
    X: Tensor
    U: Tensor
    J: Tensor
    D: Tensor
    lqr: object
    rhs: object
    weight_floor: object
    curved: object

    def rows(self, index: Tensor) -> "_Instances":
        """The instances ``index (R,)`` alone."""
        return _Instances(self.problem, self.objective.rows(index), param_rows(self.params, index), self.segments,
                          self.X[index], self.U[index], self.J[index], self.D[index], self.lqr.rows(index),
                          rows_of(self.rhs, index), rows_of(self.weight_floor, index), rows_of(self.curved, index))


@dataclass
class _Round:
    """A round's outcome per instance: the factorisation's ``ok``, the model's decrease at ``α = 1`` ``full`` and
    whether it is below the tolerance ``still``, the instances searched ``search``, the gains ``K``, the defect
    weight ``weight`` and the line search's ``step``."""

    ok: Tensor
    full: Tensor
    still: Tensor
    search: Tensor
    K: Tensor
    weight: Tensor
    step: Accepted

    def on_batch(self, index: Tensor, fill: "_Round") -> "_Round":
        """This round of the instances ``index (R,)`` as a round of the whole batch, ``fill``'s values elsewhere."""
        def put(base: Tensor, rows: Tensor) -> Tensor:
            return base.index_copy(0, index, rows)

        step = Accepted(found=put(fill.step.found, self.step.found), alpha=put(fill.step.alpha, self.step.alpha),
                        values=tuple(put(b, v) for b, v in zip(fill.step.values, self.step.values)))
        return _Round(ok=put(fill.ok, self.ok), full=put(fill.full, self.full), still=put(fill.still, self.still),
                      search=put(fill.search, self.search), K=put(fill.K, self.K),
                      weight=put(fill.weight, self.weight), step=step)


def _search_round(at: _Instances, factor, sol, pending: Tensor, accepted: Accepted, steps: Tensor, per_round: int,
                  opts) -> _Round:
    """One round of :func:`iterate` on the instances ``at``: the step ``sol`` of ``factor``, its merit, and the line
    search of the ``pending`` instances from ``accepted``, ``per_round`` step sizes a batched rollout."""
    dV1, dV2, weight, merit, rounding, ok, full, K = kernel(round_model, opts.compile)(
        at.lqr, at.rhs, factor, sol, at.J, at.D, at.weight_floor, steps[:1], opts)
    still = ok & (full < opts.expected_decrease_tolerance)
    search = pending & ok
    ratio_test_k = kernel(ratio_test, opts.compile)

    def test(alphas, sol=sol):
        return ratio_test_k(at.problem, at.objective, at.params, at.segments, at.X, at.U, factor, sol, alphas, dV1,
                            dV2, at.D, weight, merit, rounding, at.curved, opts)

    start = Accepted(found=accepted.found | ~search, alpha=accepted.alpha, values=accepted.values)
    if opts.second_order_correction:
        start = full_step_or_correction(at.problem, at.objective, at.params, at.segments, at.rhs, factor, sol, test,
                                        steps[:1], search, start, opts.compile)
        # a round only where an instance still searches (one host read): after an accepted full step or correction
        # the first round's candidates would be simulated to be thrown away
        step = backtrack(steps[1:], per_round, test, search, start, sync_first=True)
    else:
        step = backtrack(steps, per_round, test, search, start)
    return _Round(ok=ok, full=full, still=still, search=search, K=K, weight=weight, step=step)


def full_step_or_correction(problem, objective, params, segments, rhs, factor, sol, test, one, search,
                            start: Accepted, compiled: bool = False) -> Accepted:
    """The full step ``α = 1`` where the ratio test accepts it, else its second-order correction where that is
    accepted (module docstring, "Second-order correction"); ``start`` elsewhere. ``one`` is ``α = 1`` as ``(1,)``,
    ``test`` the round's ratio test (``test(alphas, sol=...)``), ``compiled`` whether the correction's step is a
    compiled kernel."""
    accept, values = test(one)
    full = accept[:, 0] & search & ~start.found
    if not bool((search & ~start.found & ~full).any()):  # no correction needed (one host read)
        return Accepted(found=start.found | full, alpha=torch.where(full, torch.ones_like(start.alpha), start.alpha),
                        values=tuple(where_rows(full, a[:, 0], c) for a, c in zip(values, start.values)))
    Xc, Uc = values[0][:, 0], values[1][:, 0]
    sol_c = kernel(corrected_step, compiled)(problem, objective, params, segments, rhs, factor, Xc, Uc)
    soc_accept, soc_values = test(one, sol=sol_c)
    soc = soc_accept[:, 0] & search & ~start.found & ~full
    take = full | soc
    values = tuple(where_rows(full, a[:, 0], where_rows(soc, b[:, 0], c))
                   for a, b, c in zip(values, soc_values, start.values))
    return Accepted(found=start.found | take, alpha=torch.where(take, torch.ones_like(start.alpha), start.alpha),
                    values=values)
