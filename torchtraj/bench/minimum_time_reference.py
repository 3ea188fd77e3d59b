"""IPOPT and FATROP on a minimum-time problem, transcribed as FATROP's paper does (§V, "Minimum Total Time").

A :class:`~torchtraj.bench.minimum_time_problems.MinimumTimeSpec` becomes, by multiple shooting with the total
time as an auxiliary state ``T_k``, the NLP::

    minimize_w   w_T T_N + sum_{k<N} 0.5 R u_kᵀ u_k T_k / N
    w = (x_0, T_0, u_0, x_1, T_1, u_1, ..., x_{N-1}, T_{N-1}, u_{N-1}, x_N, T_N)
    subject to   stage k = 0..N-1:  x_{k+1} − F(x_k, u_k; T_k / N) = 0,  T_{k+1} − T_k = 0   (dynamics first)
                                    x_0 − x0 = 0,  T_min <= T_0 <= T_max                  (k = 0; T_0 free)
                                    u_lower <= u_k <= u_upper
                                    x_lower <= x_k <= x_upper                             (k >= 1)
                 stage N:           x_N[i] − goal[i] = 0, i in terminal

with ``F`` the RK4 step of the CasADi twin of the model (:mod:`torchtraj.bench.casadi_models`), the same
discretisation as :func:`torchtraj.minimum_time` (which chooses ``T`` through a stage-0 control instead of a
free ``T_0``; the optimum is the same). Rows are ordered stage by stage, so CasADi's ``fatrop`` plugin finds
the OCP structure (``structure_detection='auto'``). The guess is the rollout of ``u_init`` over ``T_g``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import casadi_models
from .casadi_models import import_casadi
from .minimum_time_problems import MinimumTimeSpec
from .minimum_time_problems import spec as get_spec
from .reference import SOLVERS, ReferenceResult, WarmStartable, _status


@dataclass
class MinimumTimeResult(ReferenceResult):
    """:class:`~torchtraj.bench.reference.ReferenceResult` with the total time ``duration`` (``X`` without T)."""

    duration: float = float("nan")


class MinimumTimeReference(WarmStartable):
    """IPOPT or FATROP on the NLP of the module docstring.

    Args:
        problem: a name of :mod:`torchtraj.bench.minimum_time_problems` or a spec.
        solver: ``"ipopt"`` or ``"fatrop"``; tol: its convergence tolerance.
    """

    def __init__(self, problem, solver: str = "ipopt", tol: float = 1e-8) -> None:
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        ca = import_casadi()
        s = problem if isinstance(problem, MinimumTimeSpec) else get_spec(problem)
        self.spec, self.solver_name = s, solver
        p = casadi_models.default_params(s.model)
        f = casadi_models.get(s.model)
        nx, nu, N = s.nx, s.nu, s.N
        x, u, T = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("T")
        self._step = ca.Function("F", [x, u, T], [casadi_models.rk4_step(f, T / N, p)(x, u)])
        width = nx + 1 + nu
        w = ca.SX.sym("w", N * width + nx + 1)
        X = [w[k * width: k * width + nx] for k in range(N + 1)]
        Ts = [w[k * width + nx] for k in range(N + 1)]
        U = [w[k * width + nx + 1: (k + 1) * width] for k in range(N)]
        rows, lower, upper = [], [], []

        def add(expr, lo, hi):
            rows.append(expr)
            lower.append(np.broadcast_to(lo, (expr.shape[0],)))
            upper.append(np.broadcast_to(hi, (expr.shape[0],)))

        u_lo, u_hi, x_lo, x_hi = (s.array(k) for k in ("u_lower", "u_upper", "x_lower", "x_upper"))
        u_idx = np.flatnonzero(np.isfinite(u_lo) | np.isfinite(u_hi)).tolist()
        x_idx = np.flatnonzero(np.isfinite(x_lo) | np.isfinite(x_hi)).tolist()
        cost = s.time_weight * Ts[N]
        for k in range(N):
            cost += 0.5 * s.control_weight * ca.dot(U[k], U[k]) * Ts[k] / N
            add(X[k + 1] - self._step(X[k], U[k], Ts[k]), 0.0, 0.0)
            add(Ts[k + 1] - Ts[k], 0.0, 0.0)
            if k == 0:
                add(X[0] - s.array("x0"), 0.0, 0.0)
                add(Ts[0], s.time_bounds[0], s.time_bounds[1])
            if u_idx:
                add(U[k][u_idx], u_lo[u_idx], u_hi[u_idx])
            if k >= 1 and x_idx:
                add(X[k][x_idx], x_lo[x_idx], x_hi[x_idx])
        terminal = list(s.terminal)
        add(X[N][terminal] - s.array("goal")[terminal], 0.0, 0.0)
        self._lbg, self._ubg = np.concatenate(lower), np.concatenate(upper)
        g = ca.vertcat(*rows)
        nlp = {"x": w, "f": cost, "g": g}
        self._nlp, self._tol, self._warm_solver = nlp, tol, None
        if solver == "ipopt":
            opts = self._ipopt_options()
        else:
            opts = {"fatrop": {"tol": tol, "print_level": 0}, "structure_detection": "auto",
                    "equality": (self._lbg == self._ubg).tolist(), "print_time": False}
        self._solver = ca.nlpsol(f"{s.name}_{solver}", solver, nlp, opts)
        self._g = ca.Function("g", [w], [g])

    def pack(self, X: np.ndarray, U: np.ndarray, duration: float) -> np.ndarray:
        """``w`` of states ``X (N+1, nx)``, controls ``U (N, nu)`` and total time ``duration``."""
        s = self.spec
        X, U = np.asarray(X, dtype=float), np.asarray(U, dtype=float)
        stages = [np.concatenate([X[k], [duration], U[k]]) for k in range(s.N)]
        return np.concatenate(stages + [X[-1], [duration]])

    def violation(self, w: np.ndarray) -> float:
        """Largest violation of any constraint row (bounds included) at ``w``."""
        g = np.asarray(self._g(w)).ravel()
        return float(np.maximum(np.maximum(self._lbg - g, g - self._ubg), 0.0).max(initial=0.0))

    def initial_guess(self) -> np.ndarray:
        """``w`` of the rollout of ``u_init`` from ``x0`` over the guessed total time ``T_g``."""
        s = self.spec
        U0 = np.broadcast_to(s.array("u_init"), (s.N, s.nu))
        X0 = [s.array("x0")]
        for k in range(s.N):
            X0.append(np.asarray(self._step(X0[-1], U0[k], s.time_guess)).ravel())
        return self.pack(np.stack(X0), U0, s.time_guess)

    def solve(self, guess=None, warm_start: bool = False) -> MinimumTimeResult:
        """Solve from ``guess = (X, U, T)`` (default: :meth:`initial_guess`); ``warm_start=True`` (IPOPT only)
        keeps a guess at a local optimum as :meth:`torchtraj.bench.reference.ReferenceSolver.solve` does."""
        s = self.spec
        w0 = self.initial_guess() if guess is None else self.pack(*guess)
        solver = self._solver_for(warm_start)
        start = time.perf_counter()
        sol = solver(x0=w0, lbg=self._lbg, ubg=self._ubg)
        seconds = time.perf_counter() - start
        stats = solver.stats()
        w = np.asarray(sol["x"]).ravel()
        width = s.nx + 1 + s.nu
        stages = w[: s.N * width].reshape(s.N, width)
        return MinimumTimeResult(
            ok=bool(stats.get("success", False)), cost=float(sol["f"]),
            iterations=int(stats.get("iter_count", -1)), max_violation=self.violation(w),
            seconds=seconds, X=np.vstack([stages[:, : s.nx], w[None, -s.nx - 1: -1]]),
            U=stages[:, s.nx + 1:].copy(), status=_status(stats), duration=float(w[-1]),
        )
