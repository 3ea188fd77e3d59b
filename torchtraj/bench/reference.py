"""Reference optima from CasADi's IPOPT and FATROP, independent of torchtraj's solvers.

A :class:`~torchtraj.problems.ProblemSpec` is transcribed by multiple shooting into the NLP::

    minimize_w   sum_{k<N} 0.5 (x_k − x_g)ᵀ Q (x_k − x_g) + 0.5 u_kᵀ R u_k + 0.5 (x_N − x_g)ᵀ Q_f (x_N − x_g)
    w = (x_0, u_0, x_1, u_1, ..., x_{N-1}, u_{N-1}, x_N)
    subject to   stage k = 0..N-1:  x_{k+1} − F(x_k, u_k) = 0              (F: RK4 of the CasADi twin)
                                    x_0 − p = 0                          (k = 0; p = x0, an NLP parameter)
                                    u_lower <= u_k <= u_upper
                                    x_lower <= x_k <= x_upper, circles   (k >= 1)
                 stage N:           x_N − x_g = 0                        (goal constraint)

Every constraint is a row of ``g`` (bounds included), stage by stage with the dynamics first,
so that CasADi's ``fatrop`` plugin recovers the OCP structure with ``structure_detection='auto'``;
IPOPT solves the same NLP. The solver is built once and re-solved for new ``x0``.

A warm start (``solve(..., warm_start=True)``, IPOPT only) starts the barrier at ``mu_init = 1e-9``
and pushes the guess at most 1e-9 into the interior of its bounds. With IPOPT's defaults
(``mu_init = 0.1``, ``bound_push = bound_frac = 1e-2``) the first iterations solve a strongly
barrier-smoothed problem from a point moved off its active constraints, so a guess at a KKT point
is not kept: on car_3obs and car_escape, where the obstacles are constrained at the knots only and
neighbouring local optima differ in which knots touch an obstacle, IPOPT started at ALTRO's optimum
with its defaults moves to the neighbouring one (1.9e-4 and 1.5e-4 higher in cost).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from .. import problems
from ..problems import ProblemSpec
from . import casadi_models
from .casadi_models import import_casadi

SOLVERS = ("ipopt", "fatrop")

#: IPOPT options of a warm start (module docstring): a small initial barrier parameter, which alone keeps
#: ALTRO's car_3obs optimum, and no push of the guess off the bounds it is on.
IPOPT_WARM_START = {"mu_init": 1e-9, "bound_push": 1e-9, "bound_frac": 1e-9,
                    "slack_bound_push": 1e-9, "slack_bound_frac": 1e-9}


@dataclass
class ReferenceResult:
    """One reference solve.

    Attributes:
        ok: the solver reported success.
        cost: the objective at the returned point.
        iterations: solver iterations.
        max_violation: largest violation of any constraint row (bounds included) at the returned point.
        seconds: wall time of the solve call alone (the solver was built beforehand).
        X: ``(N+1, nx)`` states; U: ``(N, nu)`` controls.
        status: the solver's return status string.
    """

    ok: bool
    cost: float
    iterations: int
    max_violation: float
    seconds: float
    X: np.ndarray
    U: np.ndarray
    status: str


class WarmStartable:
    """The IPOPT options and the warm-started IPOPT solver of a CasADi reference (built on the first warm start),
    for a class that sets ``spec``, ``solver_name``, ``_solver``, ``_nlp``, ``_tol`` and ``_warm_solver``."""

    def _ipopt_options(self, **changes) -> dict:
        return {"ipopt": {"tol": self._tol, "print_level": 0, "sb": "yes", **changes}, "print_time": False}

    def _solver_for(self, warm_start: bool):
        if not warm_start:
            return self._solver
        if self.solver_name != "ipopt":
            raise ValueError(f"warm_start is implemented for IPOPT only, not {self.solver_name!r}")
        if self._warm_solver is None:
            ca = import_casadi()
            self._warm_solver = ca.nlpsol(f"{self.spec.name}_ipopt_warm", "ipopt", self._nlp,
                                          self._ipopt_options(**IPOPT_WARM_START))
        return self._warm_solver


class ReferenceSolver(WarmStartable):
    """IPOPT or FATROP on the multiple-shooting NLP of a benchmark problem (module docstring).

    Args:
        problem: a problem name of :mod:`torchtraj.problems` or a :class:`ProblemSpec`.
        solver: ``"ipopt"`` or ``"fatrop"``.
        tol: the solver's convergence tolerance.
        params: physical parameters of the model (floats); defaults to the model's.
    """

    def __init__(
        self,
        problem: Union[str, ProblemSpec],
        solver: str = "ipopt",
        tol: float = 1e-8,
        params: Optional[dict] = None,
    ) -> None:
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        ca = import_casadi()
        self.spec = problems.spec(problem) if isinstance(problem, str) else problem
        self.solver_name = solver
        s = self.spec
        p = casadi_models.default_params(s.model) if params is None else dict(params)
        nx, nu, N = s.nx, s.nu, s.N
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        self._step = ca.Function("F", [x, u], [casadi_models.rk4_step(casadi_models.get(s.model), s.dt, p)(x, u)])

        w = ca.SX.sym("w", N * (nx + nu) + nx)
        x0 = ca.SX.sym("x0", nx)
        X = [w[k * (nx + nu): k * (nx + nu) + nx] for k in range(N + 1)]
        U = [w[k * (nx + nu) + nx: (k + 1) * (nx + nu)] for k in range(N)]
        Q, R, Qf, goal = (ca.DM(a) for a in (s.Q, s.R, s.Qf, s.goal))

        cost = 0
        rows, lower, upper = [], [], []

        def add(expr, lo, hi):
            rows.append(expr)
            lower.append(np.broadcast_to(lo, (expr.shape[0],)))
            upper.append(np.broadcast_to(hi, (expr.shape[0],)))

        for k in range(N):
            e = X[k] - goal
            cost += 0.5 * ca.bilin(Q, e, e) + 0.5 * ca.bilin(R, U[k], U[k])
            add(X[k + 1] - self._step(X[k], U[k]), 0.0, 0.0)
            if k == 0:
                add(X[0] - x0, 0.0, 0.0)
            finite = np.isfinite(s.u_lower) | np.isfinite(s.u_upper)
            if finite.any():
                idx = np.flatnonzero(finite).tolist()
                add(U[k][idx], s.u_lower[idx], s.u_upper[idx])
            if k >= 1:
                finite = np.isfinite(s.x_lower) | np.isfinite(s.x_upper)
                if finite.any():
                    idx = np.flatnonzero(finite).tolist()
                    add(X[k][idx], s.x_lower[idx], s.x_upper[idx])
                if len(s.circles):
                    c = s.circles
                    add(c[:, 2] ** 2 - (X[k][0] - c[:, 0]) ** 2 - (X[k][1] - c[:, 1]) ** 2, -np.inf, 0.0)
        e = X[N] - goal
        cost += 0.5 * ca.bilin(Qf, e, e)
        if s.goal_constraint:
            add(X[N] - goal, 0.0, 0.0)

        self._lbg = np.concatenate(lower)
        self._ubg = np.concatenate(upper)
        g = ca.vertcat(*rows)
        nlp = {"x": w, "p": x0, "f": cost, "g": g}
        self._nlp, self._tol = nlp, tol
        self._warm_solver = None  # built on the first warm start
        equality = (self._lbg == self._ubg).tolist()
        if solver == "ipopt":
            opts = self._ipopt_options()
        else:
            opts = {
                "fatrop": {"tol": tol, "print_level": 0},
                "structure_detection": "auto",
                "equality": equality,
                "print_time": False,
            }
        self._solver = ca.nlpsol(f"{s.name}_{solver}", solver, nlp, opts)
        self._g = ca.Function("g", [w, x0], [g])

    def initial_guess(self, x0: np.ndarray, U0: Optional[np.ndarray] = None, X0: Optional[np.ndarray] = None):
        """The problem set's guess: ``u_init`` held constant, states rolled out from ``x0``, unless the spec
        (car_escape) or the caller gives states. Returns ``X0 (N+1, nx)``, ``U0 (N, nu)``."""
        s = self.spec
        U0 = np.broadcast_to(s.u_init, (s.N, s.nu)) if U0 is None else np.asarray(U0, dtype=float)
        if U0.shape != (s.N, s.nu):
            raise ValueError(f"U0 must have shape ({s.N}, {s.nu}), got {U0.shape}")
        if X0 is None and s.X_init is not None:
            X0 = s.X_init
        if X0 is None:
            rollout = self._step.mapaccum(s.N)(np.asarray(x0, dtype=float), U0.T)
            X0 = np.vstack([x0, np.asarray(rollout).T])
        X0 = np.asarray(X0, dtype=float)
        if X0.shape != (s.N + 1, s.nx):
            raise ValueError(f"X0 must have shape ({s.N + 1}, {s.nx}), got {X0.shape}")
        return X0, U0

    def solve(
        self,
        x0: Optional[np.ndarray] = None,
        U0: Optional[np.ndarray] = None,
        X0: Optional[np.ndarray] = None,
        warm_start: bool = False,
    ) -> ReferenceResult:
        """Solve from initial state ``x0 (nx,)`` (default: the problem's) and guess ``U0``, ``X0``.

        ``warm_start=True`` (IPOPT only) treats the guess as a point near a solution: small initial barrier
        parameter, no push off its bounds (module docstring), so a local optimum given as the guess is kept.
        """
        s = self.spec
        x0 = s.x0 if x0 is None else np.asarray(x0, dtype=float).reshape(-1)
        if x0.shape != (s.nx,):
            raise ValueError(f"x0 must have shape ({s.nx},), got {x0.shape}")
        X0, U0 = self.initial_guess(x0, U0, X0)
        w0 = np.concatenate([np.hstack([X0[:-1], U0]).ravel(), X0[-1]])
        solver = self._solver_for(warm_start)
        start = time.perf_counter()
        sol = solver(x0=w0, p=x0, lbg=self._lbg, ubg=self._ubg)
        seconds = time.perf_counter() - start
        stats = solver.stats()
        w = np.asarray(sol["x"]).ravel()
        g = np.asarray(self._g(w, x0)).ravel()
        violation = np.maximum(np.maximum(self._lbg - g, g - self._ubg), 0.0)
        stages = w[: s.N * (s.nx + s.nu)].reshape(s.N, s.nx + s.nu)
        return ReferenceResult(
            ok=bool(stats.get("success", False)),
            cost=float(sol["f"]),
            iterations=int(stats.get("iter_count", -1)),
            max_violation=float(violation.max(initial=0.0)),
            seconds=seconds,
            X=np.vstack([stages[:, : s.nx], w[None, -s.nx:]]),
            U=stages[:, s.nx:].copy(),
            status=_status(stats),
        )


def _status(stats: dict) -> str:
    """IPOPT's return status string; FATROP reports an int flag, so use CasADi's unified status."""
    status = stats.get("return_status", "")
    return status if isinstance(status, str) else str(stats.get("unified_return_status", status))
