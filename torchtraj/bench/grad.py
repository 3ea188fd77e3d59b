"""``python -m torchtraj.bench --grad``: forward and backward times of differentiable solves.

Protocol of the differentiable-MPC literature (Amos et al. 2018, §5.1): a random stable linear system
``x+ = A x + B u`` (``nx = 8``, ``nu = 4``, spectral radius 0.9, ``B ~ N(0, 1)``), horizon 30,
box-constrained controls ``|u| ≤ 0.5``, quadratic cost ``½ (x − g)ᵀ(x − g) + ½ 0.1 |u|²`` at every knot,
initial states ``x0 ~ N(0, 3²)`` so that a good share of the controls saturate; batches 16 / 64 / 256.
The loss is ``⟨X, X̄⟩ + ⟨U, Ū⟩`` with fixed random cotangents, differentiated with respect to ``x0``
(per instance), ``A`` and ``g`` (shared).

For every solver, on the same instances in the same run:

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
mass, length and damping.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Callable, Optional

import torch

from .. import problems
from ..problem import Problem
from ..solve import solve
from ..status import Status

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
                   params=dict(system), u_lower=-bound, u_upper=bound, name="linear_box")


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
        an = float((grads[key] * d).sum())
        worst = max(worst, abs(fd - an) / max(abs(fd), abs(an), 1e-12))
    return worst


def torchtraj_lq(problem: Problem, x0, Xbar, Ubar, dirs, method: str, options, fd: bool = True) -> tuple:
    """``(row fields, U)`` of torchtraj on the LQ protocol."""
    theta = {"x0": x0, "A": problem.params["A"], "goal": problem.params["goal"]}

    def forward(th):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in th.items()}
        sol = solve(problem.with_params(A=leaves["A"], goal=leaves["goal"]), leaves["x0"], method=method,
                    options=options)
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


def torchtraj_pendulum(problem: Problem, batch: int, seed: int, method: str, options) -> dict:
    """Loss ``⟨U, Ū⟩ + |X[:, -5:]|²`` over the converged instances; gradients with respect to ``x0`` and
    the model's mass, length and damping. The FD re-solves start from the same guess as the nominal
    solve (a warm start at its solution lets ALTRO, at its default tolerances, stop at other points)."""
    x0 = problems.sample_x0("pendulum", batch, seed).to(problem.dtype).to(problem.device)
    g = torch.Generator().manual_seed(seed + 7 * batch)
    Ubar = torch.randn(batch, problem.N, problem.nu, generator=g, dtype=torch.float64).to(x0)
    names = ("mass", "length", "damping")
    theta = {"x0": x0, **{k: problem.params[k] for k in names}}
    dirs = {"x0": torch.randn(batch, problem.nx, generator=g, dtype=torch.float64).to(x0),
            **{k: torch.ones((), dtype=x0.dtype, device=x0.device) for k in names}}
    state = {"weight": torch.ones(batch, dtype=x0.dtype, device=x0.device)}

    def forward(th):
        leaves = {k: v.detach().clone().requires_grad_(True) for k, v in th.items()}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # non-converged instances: weight 0 below
            sol = solve(problem.with_params(**{k: leaves[k] for k in names}), leaves["x0"], method=method,
                        options=options)
        per = (sol.U * Ubar).flatten(1).sum(-1) + sol.X[:, -5:].pow(2).flatten(1).sum(-1)
        return sol, (state["weight"] * per.nan_to_num()).sum(), leaves

    (sol, loss, leaves), t_fwd = _timed(lambda: forward(theta), x0.device)
    _, t_bwd = _timed(lambda: loss.backward(), x0.device)
    grads = {k: v.grad for k, v in leaves.items()}
    converged = sol.status == Status.CONVERGED
    state.update(weight=converged.to(x0.dtype))
    # the nominal loss weighted all instances; the FD check weighs the converged ones only
    grads = {k: (v * state["weight"].reshape(-1, *([1] * (v.dim() - 1))) if k == "x0" else v)
             for k, v in grads.items()}
    if not bool(converged.all()):
        _, loss_c, leaves_c = forward(theta)
        loss_c.backward()
        grads = {k: v.grad for k, v in leaves_c.items()}
    fd = _fd_agreement(lambda th: forward(th)[1].detach(), theta, grads, dirs)
    omega = sol.X.detach()[:, 1:-1, 1].abs().amax()
    note = f"max|ω| {float(omega):.4g} (bound {float(problem.x_upper[1]):g})"
    return dict(forward_s=t_fwd, backward_s=t_bwd, grad_vs_fd=fd, converged=f"{int(converged.sum())}/{batch}",
                note=note)


# --------------------------------------------------------------------------------- the report
COLUMNS = (("problem", 18, False), ("solver", 13, False), ("B", 5, True), ("forward s", 10, True),
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
        pendulum_batches: Optional[list] = None, options=None, with_mpc: bool = True) -> list:
    """Run the protocol, print one line per row through ``say``, return the rows."""
    system = linear_system(seed, dtype, device)
    problem = lq_problem(system)
    have_mpc, why = mpc_available() if with_mpc else (False, "mpc.pytorch off (--no-reference)")
    say(f"gradient benchmark: torchtraj method {method}, {dtype} on {device}, {torch.get_num_threads()} threads; "
        f"{why}")
    say(f"linear_box: nx={NX}, nu={NU}, N={HORIZON}, |u|<={U_MAX}; FD step {FD_STEP:g} (central, one random "
        "direction per input); times after an untimed warm-up, wall clock of the whole batch")
    say()
    say(header())
    rows = []
    speedups = []
    warm = _instances(2, seed, system)  # untimed: first calls build torch.func's and the solvers' machinery
    torchtraj_lq(problem, *warm, method, options, fd=False)
    if have_mpc:
        mpc_pytorch_lq(problem, *warm, fd=False)
    for batch in batches:
        x0, Xbar, Ubar, dirs = _instances(batch, seed, system)
        ours = GradRow("linear_box", f"torchtraj/{method}", batch)
        U_ours = None
        try:
            fields, U_ours = torchtraj_lq(problem, x0, Xbar, Ubar, dirs, method, options)
            for k, v in fields.items():
                setattr(ours, k, v)
            saturated = float((U_ours.abs() > U_MAX - 1e-6).to(torch.float64).mean())
            ours.note = f"{100 * saturated:.0f}% of controls at a bound"
        except Exception as exc:  # a row never stops the run
            ours.note = f"{type(exc).__name__}: {exc}"
        say(format_row(ours))
        rows.append(ours)
        theirs = GradRow("linear_box", "mpc.pytorch", batch)
        if have_mpc:
            try:
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
            row = GradRow(pend.name, f"torchtraj/{method}", batch)
            try:
                for k, v in torchtraj_pendulum(pend, batch, seed, method, options).items():
                    setattr(row, k, v)
            except Exception as exc:
                row.note = f"{type(exc).__name__}: {exc}"
            say(format_row(row))
            rows.append(row)
            say(format_row(GradRow(pend.name, "mpc.pytorch", batch, note="cannot express state constraints")))
    return rows
