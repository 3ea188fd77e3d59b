"""The linear-quadratic rows of the gradient benchmark: torchtraj against mpc.pytorch on the same instances.

Protocol of the differentiable-MPC literature (Amos et al. 2018, §5.1): a random stable linear system
``x+ = A x + B u`` (``nx = 8``, ``nu = 4``, spectral radius 0.9, ``B ~ N(0, 1)``), horizon 30,
box-constrained controls ``|u| ≤ 0.5``, quadratic cost ``½ (x − g)ᵀ(x − g) + ½ 0.1 |u|²`` at every knot,
initial states ``x0 ~ N(0, 3²)`` so that a good share of the controls saturate; batches 16 / 64 / 256.
The loss is ``⟨X, X̄⟩ + ⟨U, Ū⟩`` with fixed random cotangents, differentiated with respect to ``x0``
(per instance), ``A`` and ``g`` (shared).

Each run returns its row's fields: the forward time (torchtraj: ``tt.solve(..., method)`` with ``x0``, ``A``,
``g`` requiring grad, which includes the Newton refinement; mpc.pytorch: ``mpc.MPC(...)(x0, QuadCost, LinDx)``),
the backward time (``loss.backward()``), and ``grad vs FD``: the largest relative difference between
``⟨∇loss, d⟩`` and the central difference ``(loss(θ + εd) − loss(θ − εd)) / 2ε`` of re-solves, ``ε = 1e-6``,
over one random direction ``d`` of each of ``x0``, ``A``, ``g``; and the controls ``U``, which the report
compares (both solve the same QP).

mpc.pytorch's horizon ``T = 31`` covers the same 31 states and 30 controls (its 31st control only
costs ``½ 0.1 |u|²`` and is 0). It is the optional extra ``mpc`` (``pip install mpc``; its metadata
asks for ``numpy<2``, ``pip install --no-deps mpc`` keeps a newer numpy, with which it runs).
"""

from __future__ import annotations

import time
import warnings
from typing import Callable

import torch

from ..core.problem import Problem
from ..core.status import Status
from ..solve import solve

NX, NU, HORIZON, U_MAX = 8, 4, 30, 0.5
FD_STEP = 1e-6


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def _timed(fn: Callable, device):
    """``(fn(), seconds)``, synchronised on CUDA so that the time is of the work and not of its launch."""
    _sync(device)
    start = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - start


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
