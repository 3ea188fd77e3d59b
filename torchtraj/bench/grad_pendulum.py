"""The constrained pendulum's rows of the gradient benchmark, checked against central differences instance by instance.

The nonlinear pendulum of the benchmark problem set with a state constraint ``|ω| ≤ ω_max`` on knots 1..N-1 (active),
which mpc.pytorch cannot express: gradients with respect to ``x0`` and the model's mass, length and
damping. Its loss is a sum over instances, and its check is made instance by instance
(:func:`fd_by_instance`): the swing-up has many local solutions, and a cold re-solve at
``θ ± εd`` of an instance near the border of two basins reaches another one (seed 0, B = 256:
instances 65 and 212 at ``mass − 1e-6``, cost 0.1087 → 0.0768, ``|ΔU| = 1.4``), a jump of the loss
that no gradient describes and that alone made the summed check read 0.96. Its ``grad vs FD`` is
the largest relative difference instance by instance (:meth:`InstanceFD.agreement`: a relative
difference of sums over the batch divides by a total in which directional derivatives of random signs
cancel, and read 6.7e-6 at B = 16 where no instance differs by more than 6.5e-7), over the instances
whose re-solves all converged with the nominal active set; the note names the others, says what
their re-solves found and gives the agreement over all instances, and names the instances whose point
holds an inequality row with a negative multiplier (a KKT point of its active set, not a local minimum).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from .. import problems, solvers
from ..core.constraints import Constraints
from ..core.problem import Problem
from ..core.solution import Solution
from ..core.status import Status
from ..differentiation import implicit
from ..solve import solve
from .grad_linear import FD_STEP, _timed


def constrained_pendulum(dtype=torch.float64, device="cpu", omega_max: float = 5.0) -> Problem:
    """The problem set's pendulum with ``|τ| ≤ 3`` and its terminal cost, without the goal equality, and with
    ``|ω| ≤ omega_max`` on knots 1..N-1 (the unconstrained swing-up reaches ``|ω| ≈ 5.5``)."""
    p = problems.get("pendulum", dtype=dtype, device=device)
    lower = torch.tensor([-float("inf"), -omega_max], dtype=dtype, device=device)
    return p.replace(terminal_eq=None, x_lower=lower, x_upper=-lower, name="pendulum_|ω|≤%g" % omega_max)


@dataclass
class ByInstance:
    """A differentiable solve whose loss is kept by instance: ``loss (B,)`` (NaN set to 0), the
    ``solution``, the ``problem`` it solved (parameters in place) and the ``inputs`` whose ``.grad`` hold
    each instance's gradient after a backward pass: ``x0 (B, nx)`` and every parameter expanded to
    ``(B, *shape)``."""

    solution: Solution
    loss: Tensor
    problem: Problem
    inputs: dict


def solve_by_instance(problem: Problem, theta: dict, method: str, options, loss: Callable,
                      gradients: str = "implicit") -> ByInstance:
    """Solve from ``theta = {"x0": (B, nx), name: shared value}`` (fresh leaves) with ``loss(solution) -> (B,)``.

    Each parameter enters expanded to the batch with stride 0, which the solve still treats as one
    shared parameter; its gradient then arrives by instance, and the shared gradient is their sum."""
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in theta.items()}
    batch = leaves["x0"].shape[0]
    shares = {k: v.expand(batch, *v.shape) for k, v in leaves.items() if k != "x0"}
    for v in shares.values():
        v.retain_grad()
    solved = problem.with_params(**shares)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # non-converged instances: left out of the FD check
        sol = solve(solved, leaves["x0"], method=method, options=options, gradients=gradients)
    return ByInstance(sol, loss(sol).nan_to_num(), solved, {"x0": leaves["x0"], **shares})


def directional(inputs: dict, dirs: dict) -> dict:
    """Each instance's ``⟨∇loss, d⟩ (B,)`` per input, from the ``.grad`` of :class:`ByInstance` inputs."""
    return {k: (inputs[k].grad * d).reshape(inputs[k].shape[0], -1).sum(-1) for k, d in dirs.items()}


@dataclass
class Resolved:
    """What the check compares of one solve, by instance: ``loss``, ``status``, ``cost``, ``U`` and the
    active set ``(B, m)`` as :func:`torchtraj.differentiation.implicit.active_rows` identifies it (the set the implicit
    gradient holds fixed)."""

    loss: Tensor
    status: Tensor
    cost: Tensor
    U: Tensor
    active: Tensor


def resolved(run: ByInstance) -> Resolved:
    """The :class:`Resolved` of a solve (detached)."""
    sol, problem = run.solution, run.problem
    X, U = sol.X.detach(), sol.U.detach()
    batch = U.shape[0]
    params = {k: v.detach() for k, v in problem.batched_params(batch).items()}
    masks = implicit.active_rows(problem, X, U, params, solvers.get(sol.method).handles_constraints,
                                 multipliers={k: v.detach() for k, v in sol.multipliers.items()})
    parts = [m.reshape(batch, -1) > 0 for m in masks if m is not None]
    active = torch.cat(parts, -1) if parts else U.new_zeros(batch, 0, dtype=torch.bool)
    return Resolved(run.loss.detach(), sol.status, sol.cost.detach(), U, active)


@dataclass
class InstanceFD:
    """Central differences of re-solves by instance, next to the implicit gradient.

    ``fd`` and ``analytic`` map each input to ``(B,)`` directional derivatives; ``kept (B,)`` marks the
    instances on which they are comparable: converged in the nominal solve and in every re-solve,
    each time with the nominal active set. ``left_out`` maps the others to ``(what happened, detail)``:
    a changed active set means that the re-solve found another local solution or that a weakly active
    row switched; the loss has a jump or a kink there, and a central difference measures neither side.
    """

    fd: dict
    analytic: dict
    kept: Tensor
    left_out: dict

    def agreement(self, only_kept: bool = True) -> float:
        """Largest over inputs and (kept) instances of ``|fd − an| / max(|fd|, |an|, floor)``, where ``floor``
        is ``1e-6`` of the input's largest ``|an|`` over the instances (an instance whose derivative is
        zero to round-off is not divided by its round-off). Instance by instance, not of sums over the
        batch: directional derivatives of random signs cancel in a sum, which then divides the error
        of one instance by a small total."""
        keep = self.kept if only_kept else torch.ones_like(self.kept)
        if not bool(keep.any()):
            return float("nan")
        worst = 0.0
        for k in self.fd:
            fd, an = self.fd[k][keep], self.analytic[k][keep]
            floor = 1e-6 * float(an.abs().max())
            scale = torch.maximum(fd.abs(), an.abs()).clamp_min(max(floor, 1e-300))
            worst = max(worst, float(((fd - an).abs() / scale).max()))
        return worst

    def describe(self, limit: int = 3) -> str:
        """``FD over K/B instances`` and, when some are left out, which, why, and the agreement over all."""
        kept, batch = int(self.kept.sum()), self.kept.numel()
        text = f"FD over {kept}/{batch} instances"
        if kept == batch:
            return text
        groups: dict = {}
        for i, (why, detail) in self.left_out.items():
            groups.setdefault(why, []).append((i, detail))
        parts = []
        for why, members in list(groups.items())[:limit]:
            ids = ", ".join(f"#{i}" for i, _ in members[:8]) + (", …" if len(members) > 8 else "")
            first, detail = members[0]
            parts.append(f"{ids}: {why}" + (f" (#{first}: {detail})" if detail else ""))
        if len(groups) > limit:
            parts.append(f"{sum(len(m) for m in list(groups.values())[limit:])} more")
        return f"{text} (left out {'; '.join(parts)}; over all {batch}: {self.agreement(False):.1e})"


def fd_by_instance(resolve: Callable, theta: dict, dirs: dict, analytic: dict, nominal: Resolved,
                   step: float = FD_STEP) -> InstanceFD:
    """Re-solve at ``theta ± step d`` for each ``d`` of ``dirs`` (``resolve(theta) -> Resolved``) and
    set each instance's central difference next to its ``analytic`` derivative (:func:`directional`)."""
    converged = nominal.status == Status.CONVERGED
    kept = converged.clone()
    events: dict = {}  # instance -> [(what, where, |ΔU|, cost)]
    fd = {}
    for key, d in dirs.items():
        values = []
        for sign, mark in ((1.0, "+"), (-1.0, "−")):
            moved = dict(theta)
            moved[key] = theta[key] + sign * step * d
            out = resolve(moved)
            values.append(out.loss)
            failed = converged & (out.status != Status.CONVERGED)
            changed = converged & ~failed & (out.active != nominal.active).any(-1)
            jump = (out.U - nominal.U).flatten(1).abs().amax(-1)
            for i in torch.nonzero(failed | changed).reshape(-1).tolist():
                what = "not converged" if bool(failed[i]) else "another active set"
                events.setdefault(i, []).append((what, key + mark, float(jump[i]), float(out.cost[i])))
            kept &= ~(failed | changed)
        fd[key] = (values[0] - values[1]) / (2 * step)
    left_out = {i: ("not converged", "") for i in torch.nonzero(~converged).reshape(-1).tolist()}
    for i, happened in events.items():
        whats = " / ".join(sorted({what for what, *_ in happened}))
        where = ", ".join(at for _, at, _, _ in happened)
        # the re-solve that moved furthest (a NaN |ΔU|, of a failed one, counts as furthest)
        _, _, jump, cost = max(happened, key=lambda e: e[2] if e[2] == e[2] else float("inf"))
        detail = f"cost {float(nominal.cost[i]):.4g} → {cost:.4g}, |ΔU| {jump:.2g}"
        left_out[i] = (f"{whats} in the {where} re-solve{'s' if len(happened) > 1 else ''}", detail)
    return InstanceFD(fd, analytic, kept, dict(sorted(left_out.items())))


def not_minimal(run: ByInstance) -> dict:
    """``{instance: multiplier}`` of the converged instances that hold an inequality row active with a
    multiplier below ``−tol`` (:func:`torchtraj.differentiation.implicit.default_active_tolerance`): KKT points of their
    active set but not local minima (releasing the row lowers the cost). Their gradients are still those
    of the solver's map where its re-solves stop at the same active set."""
    sol, problem = run.solution, run.problem
    if not solvers.get(sol.method).handles_constraints:  # its gradients hold no rows (tt.solve: constrained=False)
        return {}
    cons = Constraints.of(problem)
    if not (cons.mi or cons.miN):
        return {}
    X, U = sol.X.detach(), sol.U.detach()
    batch = U.shape[0]
    params = {k: v.detach() for k, v in problem.batched_params(batch).items()}
    active = implicit.active_rows(problem, X, U, params,
                                  multipliers={k: v.detach() for k, v in sol.multipliers.items()})
    kkt = implicit.kkt_system(problem, X[:, 0], X, U, params, active=active)
    inf = float("inf")
    lowest = X.new_full((batch,), inf)
    if cons.mi:
        nu, held = kkt.multipliers.nu[..., cons.me:], active[0][..., cons.me:] > 0
        lowest = torch.minimum(lowest, torch.where(held, nu, torch.full_like(nu, inf)).flatten(1).amin(-1))
    if cons.miN:
        nu, held = kkt.multipliers.nuN[..., cons.meN:], active[1][..., cons.meN:] > 0
        lowest = torch.minimum(lowest, torch.where(held, nu, torch.full_like(nu, inf)).amin(-1))
    tol = implicit.default_active_tolerance(X.dtype)
    bad = (sol.status == Status.CONVERGED) & kkt.ok & (lowest < -tol)
    return {i: float(lowest[i]) for i in torch.nonzero(bad).reshape(-1).tolist()}


def torchtraj_pendulum(problem: Problem, batch: int, seed: int, method: str, options,
                       x0: Optional[Tensor] = None, gradients: str = "implicit") -> dict:
    """Loss ``⟨U, Ū⟩ + |X[:, -5:]|²``; gradients with respect to ``x0`` and the model's mass, length and
    damping, compared with central differences instance by instance (:func:`fd_by_instance`).

    The FD re-solves start from the same guess as the nominal solve (a warm start at its solution lets
    ALTRO, at its default tolerances, stop at other points). An instance whose cold re-solve reaches
    another local solution (another active set) has a jump in its loss, not a derivative: its central
    difference is ~1/ε off. ``grad vs FD`` is therefore taken over the instances whose re-solves all
    kept the nominal active set, and the note names the others, what their re-solves found, and the
    agreement over all instances. ``x0 (batch, nx)`` defaults to ``sample_x0("pendulum", batch, seed)``.
    ``gradients``: the nominal solve's mode (``tt.solve``); the re-solves are refined (implicit) either way,
    so that the differences are of the solution map itself."""
    if x0 is None:
        x0 = problems.sample_x0("pendulum", batch, seed)
    x0 = x0.to(dtype=problem.dtype, device=problem.device)
    if x0.shape != (batch, problem.nx):
        raise ValueError(f"x0 must have shape {(batch, problem.nx)}, got {tuple(x0.shape)}")
    g = torch.Generator().manual_seed(seed + 7 * batch)
    Ubar = torch.randn(batch, problem.N, problem.nu, generator=g, dtype=torch.float64).to(x0)
    names = ("mass", "length", "damping")
    theta = {"x0": x0, **{k: problem.params[k] for k in names}}
    dirs = {"x0": torch.randn(batch, problem.nx, generator=g, dtype=torch.float64).to(x0),
            **{k: torch.ones((), dtype=x0.dtype, device=x0.device) for k in names}}

    def loss(sol):
        return (sol.U * Ubar).flatten(1).sum(-1) + sol.X[:, -5:].pow(2).flatten(1).sum(-1)

    def resolve(th):  # differentiable like the nominal solve, so refined the same way
        return resolved(solve_by_instance(problem, th, method, options, loss))

    nominal, t_fwd = _timed(lambda: solve_by_instance(problem, theta, method, options, loss, gradients), x0.device)
    # non-converged instances get zero gradients, and are left out of the check below
    _, t_bwd = _timed(lambda: nominal.loss.sum().backward(), x0.device)
    check = fd_by_instance(resolve, theta, dirs, directional(nominal.inputs, dirs), resolved(nominal))
    sol = nominal.solution
    converged = sol.status == Status.CONVERGED
    notes = [check.describe()]
    odd = not_minimal(nominal)
    if odd:
        listed = ", ".join(f"#{i} ({v:.2g})" for i, v in list(odd.items())[:4]) + (", …" if len(odd) > 4 else "")
        notes.append(f"{len(odd)} not a minimum: an active row's multiplier < 0 at {listed}")
    omega = sol.X.detach()[:, 1:-1, 1].abs().amax()
    notes.append(f"max|ω| {float(omega):.4g} (bound {float(problem.x_upper[1]):g})")
    return dict(forward_s=t_fwd, backward_s=t_bwd, grad_vs_fd=check.agreement(),
                converged=f"{int(converged.sum())}/{batch}", note="; ".join(notes))
