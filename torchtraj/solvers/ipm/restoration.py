r"""Feasibility restoration (Wächter & Biegler 2006 §3.3), batched, on the same interior-point iteration.

Where the filter line search finds no acceptable step (``IPOptions.restoration``), the instance leaves the main
iteration for the minimum-ℓ1-infeasibility problem, started at its iterate ``w_R = (X_R, U_R)`` with slacks ``s_R``:

.. math::

    \min_{w, p, n}\; ρ \sum (p + n) + \tfrac{ζ}{2} ‖D_R (w − w_R)‖_2^2 \quad\text{s.t.}\quad
    c(w) − p + n = 0,\; p, n ≥ 0,

for every row ``c`` that can be violated: the defects ``f(x_k, u_k) − x_{k+1}``, the stage equalities ``h`` and the
general and state inequality rows, written ``g − p + n ≤ 0`` (their interior-point slack plays IPOPT's ``s``). The
bounds on ``x`` and ``u`` stay hard rows, as IPOPT keeps its variable bounds; so do the terminal rows, which the
free ``x_N`` of multiple shooting satisfies whenever they are consistent on their own (IPOPT relaxes them too: a
difference). ``ρ`` (``IPOptions.restoration_penalty``: 10, not IPOPT's 1000, see there), ``ζ = √μ_R`` and
``D_R = diag(min(1, 1/|w_R|))``.

**Same stage structure, extra controls.** The pairs ``(p, n)`` of a stage are further controls of that stage with
the bounds ``≥ 0``: the dynamics become ``x_{k+1} = f(x_k, u_k) − p_k + n_k``, which the Riccati core factorises as
before. The proximity term needs the knot of each stage: the state carries a clock ``t_{k+1} = t_k + 1`` (its
Newton step is zero; it picks ``w_R`` at its knot by a one-hot weight, whose derivative is zero). So the restoration
problem is a :class:`~torchtraj.core.problem.Problem` of its own (made once per problem), solved by
:func:`~torchtraj.solvers.ipm.solver.run` on the instances that need it, gathered; the others never see it (their
answers are unchanged; they wait for it). Its cost: each relaxed row adds two controls, so a problem with many
path rows pays for them in every restoration iteration (car_escape's 170 circles: 346 extra controls, so that
from the rollout of its controls, which runs through the walls, a restoration iteration costs some twenty main
ones; from its waypoint guess, the start the IPM takes, it needs no restoration phase). W&B eliminate ``p, n``
from the linear system instead, which would make a restoration iteration cost a main one: not done here (for the
defects it needs a dynamics row with a diagonal ``(2,2)`` block in the Riccati core).

**Start** (W&B §3.3): ``μ_R = max(μ, ‖c(w_R)‖_∞)``; ``p, n`` at the minimiser of the penalty and barrier along
``p − n = c`` (W&B eq. 33), ``n = (μ_R − ρc)/(2ρ) + \sqrt{((μ_R − ρc)/(2ρ))^2 + μ_R c/(2ρ)}``, ``p = c + n``; the
main slacks, their multipliers capped at ``ρ``, and ``μ_R / p`` for those of ``p, n``. Before it starts, the main
filter is augmented with the point it leaves, ``((1 − γ_θ) θ, φ − γ_φ θ)``.

**Return**: at every restoration iterate the main problem's ``(θ, φ)`` is evaluated at its ``(w, s)``; the
restoration ends as soon as that point is acceptable to the augmented filter, below ``θ_max``, and
``θ ≤ κ_resto θ_R`` (``required_infeasibility_reduction`` 0.9). The main iteration then resumes there with its own
``μ``; inequality multipliers above 1000 are reset to 1, costates and equality multipliers to zero (IPOPT's
``bound_mult_reset_threshold``, ``constr_mult_reset_threshold``). **Local infeasibility**: where the restoration
problem converges (its own ``E_0 ≤ tol``) at a point the filter does not accept, the instance is a stationary point
of the infeasibility: :attr:`~torchtraj.core.status.Status.LOCALLY_INFEASIBLE`, reported at that point (where its
largest residual ``‖c‖_∞`` is above the tolerance, as in the convergence test: ``θ = ‖c‖₁`` sums the round-off of
every row; else the main iteration resumes there; an iterate already that feasible takes no restoration phase, its
failed line search being one at round-off). Any other ending of the restoration
(iterations, regularisation) is the instance's status. A restoration phase does not enter one of its own (a failed
line search there raises ``δ_w``); Mehrotra's steps (no filter) take none; and ``ζ`` is fixed for the phase at its start
(IPOPT lets it follow ``μ``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ...core.batch import Batch
from ...core.batching import concat, map_stage, param_rows
from ...core.constraints import STATE_BLOCKS, Constraints
from ...core.problem import Problem
from ...core.status import Status
from ...globalization.filter import Filter
from ...kkt.model import total_cost
from .compaction import gather_rows, pick
from .expansion import constraint_parts, flat_abs
from .iterate import Hooks, Iterate, Model
from .line_search import log_barrier
from .options import IPOptions

#: The restoration problem's own parameters (per instance): reference ``w_R``, scaling ``D_R``, ``ζ``, ``ρ``, and
#: what its return test needs: the main ``μ``, ``θ_R``, ``θ_max`` and the augmented filter's entries.
_P = {name: f"_restoration_{name}" for name in ("XR", "UR", "XD", "UD", "zeta", "rho", "mu", "theta", "theta_max",
                                                "filter")}


@dataclass
class Layout:
    """Where the restoration problem keeps what: the main sizes, the relaxed inequality rows ``relaxed``, and the
    number ``nv`` of slack controls ``(p, n)`` (defects, stage equalities, relaxed rows)."""

    nx: int
    nu: int
    me: int
    mi: int
    relaxed: list
    nv: int


def _relaxed_rows(cons: Constraints) -> list:
    """The general and state inequality rows (the bounds stay hard)."""
    return [i for name in ("stage_ineq", "state_ineq") for i in range(cons.ineq_blocks[name].start,
                                                                        cons.ineq_blocks[name].stop)]


def restoration_problem(problem: Problem, cons: Constraints, filter_size: int) -> tuple:
    """The restoration problem of ``problem`` (module docstring) and its :class:`Layout`, made once per problem."""
    return problem.derived("_restoration", filter_size, lambda: _restoration_problem(problem, cons, filter_size))


def _restoration_problem(problem: Problem, cons: Constraints, filter_size: int) -> tuple:
    nx, nu, N, me, mi = problem.nx, problem.nu, problem.N, cons.me, cons.mi
    relaxed = _relaxed_rows(cons)
    r = len(relaxed)
    lay = Layout(nx=nx, nu=nu, me=me, mi=mi, relaxed=relaxed, nv=2 * (nx + me + r))
    dtype, device = problem.dtype, problem.device
    state_rows = torch.zeros(mi, dtype=torch.bool, device=device)
    for name in STATE_BLOCKS:
        state_rows[cons.ineq_blocks[name]] = True
    spread = torch.zeros(mi, r, dtype=dtype, device=device)  # the relaxed rows' slacks into the stacked rows
    spread[relaxed, torch.arange(r)] = 1.0
    cut = [nu, nu + nx, nu + 2 * nx, nu + 2 * nx + me, nu + 2 * nx + 2 * me, nu + 2 * nx + 2 * me + r]

    def parts(xt, ut):
        return xt[:nx], xt[nx], ut[:nu], ut[cut[0]:cut[1]], ut[cut[1]:cut[2]], ut[cut[2]:cut[3]], \
            ut[cut[3]:cut[4]], ut[cut[4]:cut[5]], ut[cut[5]:]

    def at_knot(clock, n):  # one-hot weights of the clock's knot; no derivative
        return (torch.arange(n, dtype=clock.dtype, device=clock.device) == torch.round(clock)).to(clock.dtype)

    def dynamics(xt, ut, p):
        x, clock, u, pd, nd = parts(xt, ut)[:5]
        return concat([problem.dynamics(x, u, p) - pd + nd, (clock + 1).reshape(1)])  # traced: no batch size read

    def stage_eq(xt, ut, p):
        x, _, u, _, _, ph, nh, _, _ = parts(xt, ut)
        return cons.stage_eq(x, u, p) - ph + nh

    def stage_ineq(xt, ut, p):
        x, clock, u, _, _, _, _, pg, ng = parts(xt, ut)
        g = torch.where(state_rows & (clock < 0.5), -1.0, cons.stage_ineq(x, u, p))  # state rows: knots ≥ 1
        return g + spread @ (ng - pg)

    def stage_cost(xt, ut, p):
        x, clock, u = parts(xt, ut)[:3]
        w = at_knot(clock, N + 1)
        dx = (w @ p[_P["XD"]]) * (x - w @ p[_P["XR"]])
        du = (w[:N] @ p[_P["UD"]]) * (u - w[:N] @ p[_P["UR"]])
        return p[_P["rho"]] * ut[nu:].sum() + 0.5 * p[_P["zeta"]] * (dx @ dx + du @ du)

    def terminal_cost(xt, p):
        dx = p[_P["XD"]][-1] * (xt[:nx] - p[_P["XR"]][-1])
        return 0.5 * p[_P["zeta"]] * (dx @ dx)

    own = {"XR": (N + 1, nx), "UR": (N, nu), "XD": (N + 1, nx), "UD": (N, nu), "zeta": (), "rho": (), "mu": (),
           "theta": (), "theta_max": (), "filter": (filter_size, 2)}
    params = {**problem.params, **{_P[k]: torch.ones(shape, dtype=dtype, device=device) for k, shape in own.items()}}
    lower = torch.cat([torch.full((nu,), -float("inf"), dtype=dtype, device=device),
                       torch.zeros(lay.nv, dtype=dtype, device=device)])
    resto = Problem(
        dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost,
        x0=torch.cat([problem.x0, problem.x0.new_zeros(1)]), horizon=N, nu=nu + lay.nv, params=params,
        stage_eq=stage_eq if me else None, stage_ineq=stage_ineq if mi else None,
        terminal_eq=(lambda xt, p: cons.terminal_eq(xt[:nx], p)) if cons.meN else None,
        terminal_ineq=(lambda xt, p: cons.terminal_ineq(xt[:nx], p)) if cons.miN else None,
        u_lower=lower, name=f"{problem.name}_restoration",
        param_shapes={**problem.param_shapes, **{_P[k]: shape for k, shape in own.items()}},
    )
    return resto, lay


def main_measures(problem: Problem, cons: Constraints, params, X: Tensor, U: Tensor, s: Tensor, sN: Tensor,
                  mu: Tensor) -> tuple:
    """The main problem's ``θ = ‖c‖₁``, ``φ = J − μ Σ log s`` and ``‖c‖_∞`` ``(B,)`` at ``X``, ``U`` with slacks
    ``s``, ``sN``."""
    knots = cons.ineq_knot_mask
    defects = map_stage(problem.dynamics, X[:, :-1], U, params) - X[:, 1:]
    rows = constraint_parts(cons, X, U, params, jacobians=False)
    residuals = flat_abs(defects, rows.h, rows.hN, (rows.g + s) * knots, rows.gN + sN)
    return residuals.sum(-1), total_cost(problem, X, U, params) - mu * log_barrier(s, sN, knots), \
        residuals.amax(-1)


def _scatter(full, index: Tensor, rows):
    """``full`` (a batch-first tensor or dataclass) with its rows ``index`` replaced by ``rows``."""
    if isinstance(full, Tensor):
        return full.index_copy(0, index, rows)
    return type(full)(**{f.name: _scatter(getattr(full, f.name), index, getattr(rows, f.name)) for f in fields(full)})


@dataclass
class Restored:
    """The outcome of the restoration phases of one iteration, full batch: the iterate (restored rows replaced),
    the filter (augmented rows), ``returned (B,)``: back in the main iteration, their ``status (B,)`` otherwise,
    and the ``iterations (B,)`` they took."""

    it: Iterate
    filter: Filter
    returned: Tensor
    status: Tensor
    iterations: Tensor


def restore(problem: Problem, cons: Constraints, params, x0: Tensor, it: Iterate, model: Model, mu: Tensor,
            filt: Filter, theta_max: Tensor, entering: Tensor, budget: Tensor, tol: float, opts: IPOptions,
            run) -> Restored:
    """The restoration phase (module docstring) of the instances ``entering (B,)``, solved together by ``run``
    (:func:`~torchtraj.solvers.ipm.solver.run`) with at most ``budget (B,)`` iterations each."""
    index = entering.nonzero().squeeze(-1)
    resto, lay = restoration_problem(problem, cons, opts.filter_size)
    nx, nu, mi, rho = lay.nx, lay.nu, lay.mi, opts.restoration_penalty
    its, ms, mus = gather_rows(it, index), gather_rows(model, index), mu[index]
    knots = cons.ineq_knot_mask
    phi = ms.J - mus * log_barrier(its.s, its.sN, knots)
    augmented = gather_rows(filt, index).add(torch.ones_like(entering[index]), (1.0 - opts.filter_theta) * ms.theta,
                                             phi - opts.filter_phi * ms.theta)
    relaxed = (ms.f - its.X[:, 1:], ms.h, ((ms.g + its.s) * knots)[..., lay.relaxed])
    size = flat_abs(*relaxed, ms.hN, ms.gN + its.sN).amax(-1)
    mu_r = torch.maximum(mus, size)
    m3 = mu_r.reshape(-1, 1, 1)
    slacks = []
    for c in relaxed:  # W&B eq. 33
        a = (m3 - rho * c) / (2 * rho)
        n = a + torch.sqrt(a * a + m3 * c / (2 * rho))
        slacks += [c + n, n]
    p_r = {**param_rows(params, index), _P["XR"]: its.X, _P["UR"]: its.U,
           _P["XD"]: torch.clamp(1.0 / its.X.abs(), max=1.0), _P["UD"]: torch.clamp(1.0 / its.U.abs(), max=1.0),
           _P["zeta"]: opts.restoration_proximity * torch.sqrt(mu_r), _P["rho"]: torch.full_like(mu_r, rho),
           _P["mu"]: mus, _P["theta"]: ms.theta, _P["theta_max"]: theta_max[index], _P["filter"]: augmented.entries}
    clock = torch.arange(problem.N + 1, dtype=x0.dtype, device=x0.device).expand(index.shape[0], -1).unsqueeze(-1)
    U_r = torch.cat([its.U] + slacks, -1)
    batch = Batch(x0=torch.cat([x0[index], x0.new_zeros(index.shape[0], 1)], -1), U0=U_r,
                  X0=torch.cat([its.X, clock], -1), params=p_r, duals=None, B=int(index.shape[0]))

    def start(first: Iterate) -> Iterate:  # the main slacks; the multipliers of p, n at μ_R / p
        s = torch.cat([torch.where(knots > 0, its.s, 1.0), U_r[..., nu:]], -1)
        z = torch.cat([torch.where(knots > 0, torch.clamp(its.z, max=rho), 1.0), m3 / U_r[..., nu:]], -1)
        return dataclasses.replace(first, s=s, z=z, sN=its.sN.clone(), zN=torch.clamp(its.zN, max=rho))

    def back(p, X, U, s, sN):  # acceptable to the augmented main filter, with θ reduced enough
        theta, phi_main, _ = main_measures(problem, cons, p, X, U, s, sN, p[_P["mu"]])
        ok = Filter(p[_P["filter"]], torch.zeros_like(theta, dtype=torch.long)).acceptable(
            theta.unsqueeze(1), phi_main.unsqueeze(1)).squeeze(1)
        return ok & (theta <= opts.restoration_reduction * p[_P["theta"]]) & (theta <= p[_P["theta_max"]])

    def leave(p, itr: Iterate, _model) -> Tensor:
        return back(p, itr.X[..., :nx], itr.U[..., :nu], itr.s[..., :mi], itr.sN)

    inner = dataclasses.replace(opts, restoration=False, crossover=False)
    final, _, _ = run(resto, batch, inner, Hooks(barrier=mu_r, budget=budget[index], start=start, leave=leave),
                        method="restoration")
    X, U, s = final.X[..., :nx], final.U[..., :nu], torch.where(knots > 0, final.s[..., :mi], 1.0)
    converged = final.status == Status.CONVERGED
    largest = main_measures(problem, cons, p_r, X, U, s, final.sN, mus)[2]
    # converged at a point the filter refuses: infeasible, unless feasible to the tolerance (then resume there);
    # the largest residual, as the convergence test has it: ‖c‖₁ sums the round-off of every row (in float32, 120
    # rows at 3e-8 each are above tol = 1e-6)
    returned = converged & (back(p_r, X, U, s, final.sN) | (largest <= tol))
    reset = opts.restoration_multiplier_reset
    z = torch.where(final.z[..., :mi] > reset, 1.0, final.z[..., :mi]) * knots
    zN = torch.where(final.zN > reset, 1.0, final.zN)
    rows = Iterate(X=X, U=U, s=s, sN=final.sN, z=z, zN=zN, y=torch.zeros_like(s), yN=torch.zeros_like(zN),
                   lam=torch.zeros_like(its.lam), nu=torch.zeros_like(its.nu), nuN=torch.zeros_like(its.nuN))
    status = torch.where(converged, int(Status.LOCALLY_INFEASIBLE), final.status)
    zeros = torch.zeros_like(entering, dtype=torch.long)
    return Restored(it=_scatter(it, index, pick(converged, rows, its)), filter=_scatter(filt, index, augmented),
                    returned=zeros.bool().index_copy(0, index, returned),
                    status=zeros.index_copy(0, index, status), iterations=zeros.index_copy(0, index, final.iterations))

