"""``python -m torchtraj.bench --grad``: forward and backward times of differentiable solves.

Protocol of the differentiable-MPC literature (Amos et al. 2018, §5.1): a random stable linear system
``x+ = A x + B u`` (``nx = 8``, ``nu = 4``, spectral radius 0.9, ``B ~ N(0, 1)``), horizon 30,
box-constrained controls ``|u| ≤ 0.5``, quadratic cost ``½ (x − g)ᵀ(x − g) + ½ 0.1 |u|²`` at every knot,
initial states ``x0 ~ N(0, 3²)`` so that a good share of the controls saturate; batches 16 / 64 / 256.
The loss is ``⟨X, X̄⟩ + ⟨U, Ū⟩`` with fixed random cotangents, differentiated with respect to ``x0``
(per instance), ``A`` and ``g`` (shared).

For every solver, on the same instances in the same run, each timed solve after an untimed one of the same
solver on the same instances (the steady state of repeated solves, as in a training loop: the first solve at a
new batch size also pays for its new buffers, about 0.2 s more for torchtraj at B = 256 on one CPU core):

* forward: wall time of the solve (torchtraj: ``tt.solve(..., method)`` with ``x0``, ``A``, ``g``
  requiring grad, which includes the Newton refinement; mpc.pytorch: ``mpc.MPC(...)(x0, QuadCost, LinDx)``);
* backward: wall time of ``loss.backward()``;
* grad vs FD: the largest relative difference between ``⟨∇loss, d⟩`` and the central difference
  ``(loss(θ + εd) − loss(θ − εd)) / 2ε`` of re-solves, ``ε = 1e-6``, over one random direction ``d``
  of each of ``x0``, ``A``, ``g``;
* vs torchtraj: ``max |U − U_torchtraj|`` (both solve the same QP).

mpc.pytorch's horizon ``T = 31`` covers the same 31 states and 30 controls (its 31st control only
costs ``½ 0.1 |u|²`` and is 0). It is the optional extra ``mpc`` (``pip install mpc``; its metadata
asks for ``numpy<2``, ``pip install --no-deps mpc`` keeps a newer numpy, with which it runs).
Then the nonlinear pendulum of PROBLEMS.md with a state constraint ``|ω| ≤ ω_max`` on knots
1..N-1 (active), which mpc.pytorch cannot express: gradients with respect to ``x0`` and the model's
mass, length and damping. Its loss is a sum over instances, and its check is made instance by
instance (:func:`fd_by_instance`): the swing-up has many local solutions, and a cold re-solve at
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

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from .. import problems
from ..core.constraints import Constraints
from ..core.problem import Problem
from ..core.solution import Solution
from ..core.status import Status
from ..differentiation import implicit
from ..solve import solve
from .runs import compiled as is_compiled

NX, NU, HORIZON, U_MAX = 8, 4, 30, 0.5
FD_STEP = 1e-6


@dataclass
class GradRow:
    problem: str
    solver: str
    batch: int
    forward_s: float = float("nan")
    backward_s: float = float("nan")
    grad_vs_fd: float = float("nan")
    vs_torchtraj: float = float("nan")
    converged: str = ""
    note: str = ""

    @property
    def total_s(self) -> float:
        return self.forward_s + self.backward_s


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _timed(fn: Callable, device):
    _sync(device)
    start = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - start


# ----------------------------------------------------------------------------- the LQ protocol
def linear_system(seed: int, dtype=torch.float64, device="cpu") -> dict:
    """The random stable system, goal, and the instances' generator seed (same for every solver)."""
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(NX, NX, generator=g, dtype=torch.float64)
    A = 0.9 * A / torch.linalg.eigvals(A).abs().max()
    B = torch.randn(NX, NU, generator=g, dtype=torch.float64)
    goal = 0.5 * torch.randn(NX, generator=g, dtype=torch.float64)
    return {k: v.to(dtype=dtype, device=device) for k, v in {"A": A, "B": B, "goal": goal}.items()}


def lq_problem(system: dict) -> Problem:
    def dynamics(x, u, p):
        return p["A"] @ x + p["B"] @ u

    def stage_cost(x, u, p):
        e = x - p["goal"]
        return 0.5 * (e @ e) + 0.05 * (u @ u)

    def terminal_cost(x, p):
        e = x - p["goal"]
        return 0.5 * (e @ e)

    A = system["A"]
    bound = torch.full((NU,), U_MAX, dtype=A.dtype, device=A.device)
    return Problem(dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost,
                   x0=torch.zeros(NX, dtype=A.dtype, device=A.device), horizon=HORIZON, nu=NU,
                   params=dict(system), u_lower=-bound, u_upper=bound, name="linear_box", linear_quadratic=True)


def _instances(batch: int, seed: int, system: dict):
    A = system["A"]
    g = torch.Generator().manual_seed(seed + batch)
    x0 = 3.0 * torch.randn(batch, NX, generator=g, dtype=torch.float64)
    Xbar = torch.randn(batch, HORIZON + 1, NX, generator=g, dtype=torch.float64)
    Ubar = torch.randn(batch, HORIZON, NU, generator=g, dtype=torch.float64)
    dirs = {"x0": torch.randn(batch, NX, generator=g, dtype=torch.float64),
            "A": torch.randn(NX, NX, generator=g, dtype=torch.float64),
            "goal": torch.randn(NX, generator=g, dtype=torch.float64)}
    to = dict(dtype=A.dtype, device=A.device)
    return x0.to(**to), Xbar.to(**to), Ubar.to(**to), {k: v.to(**to) for k, v in dirs.items()}


def _relative(fd: float, an: float) -> float:
    return abs(fd - an) / max(abs(fd), abs(an), 1e-12)


def _fd_agreement(run: Callable, theta: dict, grads: dict, dirs: dict) -> float:
    """Largest relative difference between ``⟨grad, d⟩`` and central differences of ``run``."""
    worst = 0.0
    for key, d in dirs.items():
        values = []
        for sign in (1.0, -1.0):
            moved = dict(theta)
            moved[key] = theta[key] + sign * FD_STEP * d
            values.append(float(run(moved)))
        fd = (values[0] - values[1]) / (2 * FD_STEP)
        worst = max(worst, _relative(fd, float((grads[key] * d).sum())))
    return worst


def torchtraj_lq(problem: Problem, x0, Xbar, Ubar, dirs, method: str, options, fd: bool = True,
                 gradients: str = "implicit") -> tuple:
    """``(row fields, U)`` of torchtraj on the LQ protocol."""
    theta = {"x0": x0, "A": problem.params["A"], "goal": problem.params["goal"]}

    def forward(th):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in th.items()}
        sol = solve(problem.with_params(A=leaves["A"], goal=leaves["goal"]), leaves["x0"], method=method,
                    options=options, gradients=gradients)
        loss = (sol.X * Xbar).sum() + (sol.U * Ubar).sum()
        return sol, loss, leaves

    device = x0.device
    (sol, loss, leaves), t_fwd = _timed(lambda: forward(theta), device)
    _, t_bwd = _timed(lambda: loss.backward(), device)
    grads = {k: v.grad for k, v in leaves.items()}
    fd = _fd_agreement(lambda th: forward(th)[1].detach(), theta, grads, dirs) if fd else float("nan")
    converged = f"{int((sol.status == Status.CONVERGED).sum())}/{x0.shape[0]}"
    return dict(forward_s=t_fwd, backward_s=t_bwd, grad_vs_fd=fd, converged=converged), sol.U.detach()


def mpc_pytorch_lq(problem: Problem, x0, Xbar, Ubar, dirs, lqr_iter: int = 20, fd: bool = True) -> tuple:
    """``(row fields, U)`` of mpc.pytorch's ``MPC`` on the same instances (time-major inside)."""
    from mpc import mpc as mpc_module  # the optional extra

    B, T = x0.shape[0], HORIZON + 1
    theta = {"x0": x0, "A": problem.params["A"], "goal": problem.params["goal"]}
    Bm = problem.params["B"]
    dtype, device = x0.dtype, x0.device
    C = torch.diag(torch.cat([torch.ones(NX, dtype=dtype, device=device),
                              0.1 * torch.ones(NU, dtype=dtype, device=device)])).expand(T, B, NX + NU, NX + NU)
    bound = torch.full((T, B, NU), U_MAX, dtype=dtype, device=device)

    def forward(th):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in th.items()}
        F = torch.cat([leaves["A"], Bm], 1).expand(T - 1, B, NX, NX + NU)
        c = torch.cat([-leaves["goal"], torch.zeros(NU, dtype=dtype, device=device)]).expand(T, B, NX + NU)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its deprecated torch.lu calls
            ctrl = mpc_module.MPC(NX, NU, T, u_lower=-bound, u_upper=bound, lqr_iter=lqr_iter, verbose=-1,
                                  exit_unconverged=False, eps=1e-10, n_batch=B)
            xs, us, _ = ctrl(leaves["x0"], mpc_module.QuadCost(C, c), mpc_module.LinDx(F))
        X, U = xs.transpose(0, 1), us.transpose(0, 1)[:, :HORIZON]
        loss = (X * Xbar).sum() + (U * Ubar).sum()
        return U, loss, leaves

    (U, loss, leaves), t_fwd = _timed(lambda: forward(theta), device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, t_bwd = _timed(lambda: loss.backward(), device)
    grads = {k: (v.grad if v.grad is not None else torch.zeros_like(v)) for k, v in leaves.items()}
    fd = _fd_agreement(lambda th: forward(th)[1].detach(), theta, grads, dirs) if fd else float("nan")
    return dict(forward_s=t_fwd, backward_s=t_bwd, grad_vs_fd=fd, converged="n/a"), U.detach()


def mpc_available() -> tuple:
    try:
        import mpc  # noqa: F401
        from mpc import mpc as _  # noqa: F401
        return True, "mpc.pytorch importable"
    except Exception as exc:  # ImportError, or a failure of the package with this torch
        return False, f"mpc.pytorch not available ({type(exc).__name__}: {exc}); pip install --no-deps mpc"


# ---------------------------------------------------------------- the constrained pendulum
def constrained_pendulum(dtype=torch.float64, device="cpu", omega_max: float = 5.0) -> Problem:
    """PROBLEMS.md's pendulum with ``|τ| ≤ 3`` and its terminal cost, without the goal equality, and with
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
    masks = implicit.active_rows(problem, X, U, params, sol.method not in implicit.UNCONSTRAINED_METHODS,
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
    if sol.method in implicit.UNCONSTRAINED_METHODS:
        return {}
    cons = Constraints(problem)
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


# --------------------------------------------------------------------------------- the report
COLUMNS = (("problem", 18, False), ("solver", 23, False), ("B", 5, True), ("forward s", 10, True),
           ("backward s", 11, True), ("total s", 9, True), ("grad vs FD", 11, True),
           ("|U - U_tt|", 11, True), ("converged", 10, True), ("note", 0, False))


def _fmt(value: float, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def format_row(row: GradRow) -> str:
    cells = [row.problem, row.solver, str(row.batch), _fmt(row.forward_s, ".3f"), _fmt(row.backward_s, ".3f"),
             _fmt(row.total_s, ".3f"), _fmt(row.grad_vs_fd, ".1e"), _fmt(row.vs_torchtraj, ".1e"),
             row.converged, row.note]
    parts = [c.rjust(w) if right else c.ljust(w) for (_, w, right), c in zip(COLUMNS, cells)]
    return "  ".join(parts).rstrip()


def header() -> str:
    titles = "  ".join(t.rjust(w) if right else t.ljust(w) for t, w, right in COLUMNS).rstrip()
    return titles + "\n" + "-" * len(titles)


def run(batches, seed: int, method: str, say: Callable, dtype=torch.float64, device="cpu",
        pendulum_batches: Optional[list] = None, options=None, with_mpc: bool = True,
        gradients: str = "implicit", lq_options=None) -> list:
    """Run the protocol, print one line per row through ``say``, return the rows. ``lq_options`` (default
    ``options``) are those of the linear_box rows: a convex problem, for which the IPM's Mehrotra mode is made."""
    system = linear_system(seed, dtype, device)
    problem = lq_problem(system)
    have_mpc, why = mpc_available() if with_mpc else (False, "mpc.pytorch off (--no-reference)")
    say(f"gradient benchmark: torchtraj method {method}, {gradients} gradients, {dtype} on {device}, "
        f"{torch.get_num_threads()} threads; {why}")
    say(f"linear_box: nx={NX}, nu={NU}, N={HORIZON}, |u|<={U_MAX}; FD step {FD_STEP:g} (central, one random "
        "direction per input); times after an untimed run of the same solver at the same batch size, wall clock of "
        "the whole batch")
    say()
    say(header())
    rows = []
    speedups = []
    compiled = is_compiled(options)
    graphs = getattr(options, "cuda_graphs", False) and torch.device(device).type == "cuda"
    label = f"torchtraj/{method}" + ("+compile" if compiled else "") + ("+graphs" if graphs else "") \
        + ("+unrolled" if gradients == "unrolled" else "")
    lq_label = label + ("+mehrotra" if getattr(lq_options, "barrier_strategy", None) == "mehrotra" else "")
    lq_options = lq_options or options
    for batch in batches:
        x0, Xbar, Ubar, dirs = _instances(batch, seed, system)
        ours = GradRow("linear_box", lq_label, batch)
        U_ours = None
        try:
            # untimed at this batch size: first buffers of a new size (and compiled kernels) are built once
            _, seconds = _timed(lambda: torchtraj_lq(problem, x0, Xbar, Ubar, dirs, method, lq_options, fd=False,
                                                     gradients=gradients),
                                device)
            warm_up = f"; untimed compiling run {seconds:.0f} s" if compiled else ""
            fields, U_ours = torchtraj_lq(problem, x0, Xbar, Ubar, dirs, method, lq_options, gradients=gradients)
            for k, v in fields.items():
                setattr(ours, k, v)
            saturated = float((U_ours.abs() > U_MAX - 1e-6).to(torch.float64).mean())
            ours.note = f"{100 * saturated:.0f}% of controls at a bound" + warm_up
        except Exception as exc:  # a row never stops the run
            ours.note = f"{type(exc).__name__}: {exc}"
        say(format_row(ours))
        rows.append(ours)
        theirs = GradRow("linear_box", "mpc.pytorch", batch)
        if have_mpc:
            try:
                mpc_pytorch_lq(problem, x0, Xbar, Ubar, dirs, fd=False)  # untimed at this batch size, as ours
                fields, U_theirs = mpc_pytorch_lq(problem, x0, Xbar, Ubar, dirs)
                for k, v in fields.items():
                    setattr(theirs, k, v)
                if U_ours is not None:
                    theirs.vs_torchtraj = float((U_theirs - U_ours).abs().max())
                    speedups.append((batch, theirs.total_s / ours.total_s))
            except Exception as exc:
                theirs.note = f"{type(exc).__name__}: {exc}"
        else:
            theirs.note = why
        say(format_row(theirs))
        rows.append(theirs)
    for batch, ratio in speedups:
        say(f"speed-up B={batch}: mpc.pytorch total / torchtraj total = {ratio:.3g}")
    if pendulum_batches:
        say()
        pend = constrained_pendulum(dtype, device)
        for batch in pendulum_batches:
            row = GradRow(pend.name, label, batch)
            try:
                # untimed at this batch size (and compiling)
                x0 = problems.sample_x0("pendulum", batch, seed).to(dtype=dtype, device=device)
                _, seconds = _timed(lambda: solve(pend, x0, method=method, options=options), device)
                warm_up = f"; untimed compiling run {seconds:.0f} s" if compiled else ""
                for k, v in torchtraj_pendulum(pend, batch, seed, method, options, gradients=gradients).items():
                    setattr(row, k, v)
                row.note += warm_up
            except Exception as exc:
                row.note = f"{type(exc).__name__}: {exc}"
            say(format_row(row))
            rows.append(row)
            say(format_row(GradRow(pend.name, "mpc.pytorch", batch, note="cannot express state constraints")))
    return rows
