"""The benchmark problem set (the standard problems of the ALTRO, HM-iLQR and FATROP papers), every number once.

Each problem is, with ``dt = tf / N`` and ``F = rk4(f, dt)`` of a model in :mod:`torchtraj.models`::

    minimize    sum_{k<N} 0.5 (x_k − x_g)ᵀ Q (x_k − x_g) + 0.5 u_kᵀ R u_k  +  0.5 (x_N − x_g)ᵀ Q_f (x_N − x_g)
    subject to  x_{k+1} = F(x_k, u_k),  x_0 = x0,
                u_lower <= u_k <= u_upper                         k = 0..N-1
                x_lower <= x_k <= x_upper                         k = 1..N-1
                r_i² − (x_k[0] − cx_i)² − (x_k[1] − cy_i)² <= 0   k = 1..N-1  (circles)
                x_N = x_g                                         (where goal_constraint)

Q and R are stored as used (the problem set's "·dt" already applied). ``pendulum_unconstrained`` and
``cartpole_unconstrained`` are ``pendulum`` / ``cartpole`` without control bounds and goal constraint.

* :func:`spec` gives the numbers as a :class:`ProblemSpec` (numpy, for independent references such as
  :mod:`torchtraj.bench.reference`);
* :func:`get` builds a :class:`torchtraj.Problem` whose ``params`` hold the model's physical parameters
  and ``goal`` (nx,), ``Q`` (nx, nx), ``R`` (nu, nu), ``Qf`` (nx, nx) and, with circles,
  ``obstacles`` (n, 3) rows ``(cx, cy, r)``, so gradients can flow to all of them;
* :func:`sample_x0` draws the problem set's batches ``x0 + U(−1, 1) * spread``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from . import models
from .core.problem import Problem

_ARRAY_FIELDS = ("x0", "goal", "Q", "R", "Qf", "u_lower", "u_upper", "x_lower", "x_upper", "circles", "u_init")


@dataclass(frozen=True, eq=False)
class ProblemSpec:
    """The numbers of one benchmark problem (read-only float64 numpy arrays).

    Args:
        name: problem name.
        model: name of the model in :mod:`torchtraj.models` (default physical parameters).
        N: number of intervals; ``tf``: horizon length in seconds (``dt = tf / N``).
        x0, goal: ``(nx,)`` initial and goal state.
        Q, R, Qf: ``(nx, nx)``, ``(nu, nu)``, ``(nx, nx)`` cost weights as used (Q, R include the problem set's dt).
        u_lower, u_upper: ``(nu,)`` control bounds (±inf where unbounded).
        x_lower, x_upper: ``(nx,)`` state bounds on knots 1..N-1 (±inf where unbounded).
        circles: ``(n, 3)`` circle obstacles ``(cx, cy, r)`` on knots 1..N-1 (n may be 0).
        goal_constraint: whether ``x_N = goal`` is imposed.
        u_init: ``(nu,)`` constant initial control guess.
        X_init: optional ``(N+1, nx)`` initial state guess (else the rollout of ``u_init``).
        spread: optional ``(nx,)`` half-width of the batch of initial states (:func:`sample_x0`).
        altro: per-problem ALTRO option overrides (as in the ALTRO benchmarks), see :func:`altro_options`.

    Properties ``nx``, ``nu`` and ``dt = tf / N`` follow from these.
    """

    name: str
    model: str
    N: int
    tf: float
    x0: np.ndarray
    goal: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    Qf: np.ndarray
    u_lower: np.ndarray
    u_upper: np.ndarray
    x_lower: np.ndarray
    x_upper: np.ndarray
    circles: np.ndarray
    goal_constraint: bool
    u_init: np.ndarray
    X_init: Optional[np.ndarray] = None
    spread: Optional[np.ndarray] = None
    altro: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        for key in _ARRAY_FIELDS + ("X_init", "spread"):
            value = getattr(self, key)
            if value is not None:
                value = np.array(value, dtype=np.float64)
                value.setflags(write=False)
                object.__setattr__(self, key, value)
        nx, nu = self.nx, self.nu
        shapes = {
            "goal": (nx,), "Q": (nx, nx), "R": (nu, nu), "Qf": (nx, nx), "u_upper": (nu,),
            "x_lower": (nx,), "x_upper": (nx,), "u_init": (nu,), "X_init": (self.N + 1, nx), "spread": (nx,),
        }
        for key, shape in shapes.items():
            value = getattr(self, key)
            if value is not None and value.shape != shape:
                raise ValueError(f"ProblemSpec {self.name!r}: {key} must have shape {shape}, got {value.shape}")
        if self.circles.shape[1:] != (3,):
            raise ValueError(f"ProblemSpec {self.name!r}: circles must have shape (n, 3), got {self.circles.shape}")

    @property
    def nx(self) -> int:
        return int(self.x0.shape[0])

    @property
    def nu(self) -> int:
        return int(self.u_lower.shape[0])

    @property
    def dt(self) -> float:
        return self.tf / self.N


def _spec(name, model, N, tf, x0, goal, Q, R, Qf, u_bound=None, u_init=0.0, x_bound=None, circles=(),
          goal_constraint=True, X_init=None, spread=None, altro=None) -> ProblemSpec:
    """The problem set's row: ``Q``, ``R`` are per unit time (multiplied by dt here, as its "·dt");
    ``u_bound`` / ``x_bound`` are ``(lower, upper)`` pairs; scalars broadcast."""
    nx, nu, dt = len(x0), models.get(model).nu, tf / N
    inf = np.full(nu, np.inf)
    u_lower, u_upper = (-inf, inf) if u_bound is None else u_bound
    x_lower, x_upper = (np.full(nx, -np.inf), np.full(nx, np.inf)) if x_bound is None else x_bound
    return ProblemSpec(
        name=name, model=model, N=N, tf=tf, x0=x0, goal=goal, Q=np.asarray(Q) * dt, R=np.asarray(R) * dt, Qf=Qf,
        u_lower=np.broadcast_to(u_lower, (nu,)), u_upper=np.broadcast_to(u_upper, (nu,)),
        x_lower=x_lower, x_upper=x_upper, circles=np.reshape(np.asarray(circles, float), (-1, 3)),
        goal_constraint=goal_constraint, u_init=np.broadcast_to(u_init, (nu,)), X_init=X_init, spread=spread,
        altro=dict(altro or {}),
    )


def _car_escape_walls() -> np.ndarray:
    """170 circles of radius 0.5: three vertical walls, the floor, and the ceiling with a gap."""
    y = np.linspace(0.0, 5.0, 30)
    centres = [np.stack([np.full(30, cx), y], 1) for cx in (0.0, 5.0, 10.0)]
    centres.append(np.stack([np.linspace(0.0, 10.0, 50), np.zeros(50)], 1))
    centres.append(np.stack([np.linspace(0.0, 3.0, 15), np.full(15, 5.0)], 1))
    centres.append(np.stack([np.linspace(5.0, 8.0, 15), np.full(15, 5.0)], 1))
    centres = np.concatenate(centres)
    return np.concatenate([centres, np.full((len(centres), 1), 0.5)], 1)


def _car_escape_X_init(N: int) -> np.ndarray:
    """Piecewise-linear state guess through the waypoints, evenly spaced in knot index."""
    waypoints = np.array([
        [2.5, 2.5, 0.0], [4.0, 5.0, 0.785], [5.0, 6.25, 0.0],
        [7.5, 6.25, -0.261], [9.0, 5.0, -1.57], [7.5, 2.5, 0.0],
    ])
    at = np.linspace(0.0, N, len(waypoints))
    knots = np.arange(N + 1, dtype=np.float64)
    return np.stack([np.interp(knots, at, waypoints[:, i]) for i in range(waypoints.shape[1])], 1)


def _build_specs() -> dict[str, ProblemSpec]:
    pi, eye = np.pi, np.eye
    specs = [
        _spec("double_integrator", "double_integrator", 20, 2.0, [0.0, 0.0], [1.0, 0.0],
              eye(2), 0.1 * eye(1), eye(2), u_bound=(-3.0, 3.0),
              x_bound=([-np.inf, -0.6], [np.inf, 0.6]), spread=[0.3, 0.2]),
        _spec("pendulum", "pendulum", 50, 3.0, [0.0, 0.0], [pi, 0.0],
              1e-3 * eye(2), 1e-3 * eye(1), eye(2), u_bound=(-3.0, 3.0), u_init=0.1,
              spread=[0.5, 0.5]),
        _spec("cartpole", "cartpole", 100, 5.0, [0.0] * 4, [0.0, pi, 0.0, 0.0],
              1e-2 * eye(4), 0.1 * eye(1), 100.0 * eye(4), u_bound=(-3.0, 3.0), u_init=0.01,
              spread=[0.2, 0.3, 0.2, 0.3]),
        _spec("car_3obs", "unicycle", 100, 5.0, [0.0, 0.0, 0.0], [3.0, 3.0, 0.0],
              eye(3), 0.5 * eye(2), 10.0 * eye(3), u_bound=([0.0, -3.0], [3.0, 3.0]),
              circles=[[0.75, 0.75, 0.425], [1.5, 1.5, 0.425], [2.25, 2.25, 0.425]], u_init=0.01,
              spread=[0.2, 0.2, 0.3]),
        _spec("parallel_park", "unicycle", 100, 3.0, [0.0, 0.0, 0.0], [0.0, 1.5, 0.0],
              1e-2 * eye(3), 1e-2 * eye(2), 100.0 * eye(3), u_bound=(-2.0, 2.0),
              x_bound=([-0.25, -0.001, -np.inf], [0.25, 1.501, np.inf]), u_init=0.1,
              spread=[0.05, 0.05, 0.1]),
        _spec("car_escape", "unicycle", 100, 3.0, [2.5, 2.5, 0.0], [7.5, 2.5, 0.0],
              1e-3 * eye(3), 1e-2 * eye(2), 100.0 * eye(3), u_bound=(-5.0, 5.0),
              circles=_car_escape_walls(), u_init=1.0, X_init=_car_escape_X_init(100),
              # the escape benchmark's settings in the ALTRO sources: slack cost R_inf = 0.1, a stiffer
              # penalty schedule and loose intermediate solves while the slacks are driven to zero
              altro=dict(slack_cost=0.1, penalty_initial=10.0, penalty_scaling=50.0,
                         cost_tolerance_intermediate=1e-2)),
        _spec("quadrotor2d", "quadrotor2d", 200, 6.0, [4.5, 2.5, 0.2, 0.0, 0.0, 0.0], [1.0, 1.5, 0.0, 0.0, 0.0, 0.0],
              np.diag([1.0, 1.0, 1.0, 0.1, 0.1, 0.1]), 0.1 * eye(2), 100.0 * eye(6),
              u_bound=(0.0, 15.0), x_bound=([-np.inf, -np.inf, -pi / 6] + [-np.inf] * 3,
                                            [np.inf, np.inf, pi / 6] + [np.inf] * 3),
              circles=[[2.75, 2.0, 0.5]], u_init=1.0 * 9.81 / 2.0, spread=[0.3, 0.3, 0.1, 0.1, 0.1, 0.1]),
    ]
    specs = {s.name: s for s in specs}
    for twin in ("pendulum", "cartpole"):
        s = specs[twin]
        specs[f"{twin}_unconstrained"] = dataclasses.replace(
            s, name=f"{twin}_unconstrained", u_lower=np.full(s.nu, -np.inf), u_upper=np.full(s.nu, np.inf),
            goal_constraint=False,
        )
    return specs


_SPECS = _build_specs()


def names() -> list[str]:
    """Names of all benchmark problems, in the problem set's order, then the two unconstrained twins."""
    return list(_SPECS)


def spec(name: str) -> ProblemSpec:
    """The numbers of problem ``name``."""
    if not isinstance(name, str):
        raise TypeError(f"a problem's name is expected (one of {names()}), got {type(name).__name__}; "
                        "for a problem from problems.get(name), pass that name")
    if name not in _SPECS:
        raise ValueError(f"unknown problem {name!r}; known problems are {names()}")
    return _SPECS[name]


# ---------------------------------------------------------------------- cost and constraints
def _stage_cost(x: Tensor, u: Tensor, p) -> Tensor:
    e = x - p["goal"]
    return 0.5 * (e @ p["Q"] @ e) + 0.5 * (u @ p["R"] @ u)


def _terminal_cost(x: Tensor, p) -> Tensor:
    e = x - p["goal"]
    return 0.5 * (e @ p["Qf"] @ e)


def _outside_circles(x: Tensor, p) -> Tensor:
    c = p["obstacles"]
    return c[:, 2] ** 2 - (x[0] - c[:, 0]) ** 2 - (x[1] - c[:, 1]) ** 2


def _at_goal(x: Tensor, p) -> Tensor:
    return x - p["goal"]


def get(name, dtype: torch.dtype = torch.float64, device=None) -> Problem:
    """Problem ``name`` (or a :class:`ProblemSpec`, e.g. of :func:`at_horizon`) as a :class:`torchtraj.Problem` in
    ``dtype`` on ``device``.

    Bounds that are infinite everywhere are left out (``None``); state bounds apply on knots 1..N-1.
    """
    s = name if isinstance(name, ProblemSpec) else spec(name)
    model = models.get(s.model)

    def tensor(a) -> Tensor:
        return torch.tensor(np.array(a), dtype=dtype, device=device)

    def bound(a: np.ndarray) -> Optional[Tensor]:
        return tensor(a) if np.isfinite(a).any() else None

    params = {k: v.to(dtype=dtype, device=device) for k, v in model.params.items()}
    params.update(goal=tensor(s.goal), Q=tensor(s.Q), R=tensor(s.R), Qf=tensor(s.Qf))
    if len(s.circles):
        params["obstacles"] = tensor(s.circles)
    return Problem(
        dynamics=model.discrete(s.dt, "rk4"),
        stage_cost=_stage_cost,
        terminal_cost=_terminal_cost,
        x0=tensor(s.x0),
        horizon=s.N,
        nu=s.nu,
        params=params,
        state_ineq=_outside_circles if len(s.circles) else None,
        terminal_eq=_at_goal if s.goal_constraint else None,
        u_lower=bound(s.u_lower), u_upper=bound(s.u_upper),
        x_lower=bound(s.x_lower), x_upper=bound(s.x_upper),
        u_init=tensor(s.u_init),
        X_init=None if s.X_init is None else tensor(s.X_init),
        dt=s.dt,
        name=s.name,
    )


#: The references are solved to a tolerance of 1e-8 (IPOPT's and FATROP's tol). ALTRO's defaults
#: (:class:`~torchtraj.ALTROOptions`) stop where the KKT certificate of ``tt.solve`` holds, so the problem set asks
#: for nothing beyond them (Altro.jl's own tolerances leave the pendulum 30 % above its optimum); the problems' own
#: overrides (``ProblemSpec.altro``: the ALTRO sources' settings of car_escape) still apply.
REFERENCE_ACCURACY: dict = {}


def altro_options(name: str, **changes):
    """:class:`~torchtraj.ALTROOptions` for problem ``name``: :data:`REFERENCE_ACCURACY`, the problem's
    own overrides (``ProblemSpec.altro``), then ``changes``. ``gradient_tolerance`` and other
    :class:`~torchtraj.ILQROptions` fields go to the inner iLQR."""
    from .iterations.ilqr import ILQROptions
    from .solvers.altro.options import ALTROOptions

    fields = {**REFERENCE_ACCURACY, **spec(name).altro, **changes}
    inner_names = set(ILQROptions.__dataclass_fields__) - {"cost_tolerance", "verbose"}
    inner = {k: fields.pop(k) for k in list(fields) if k in inner_names}
    return ALTROOptions(ilqr=ILQROptions(**inner), **fields)


def at_horizon(name: str, N: int) -> ProblemSpec:
    """Problem ``name`` over the same ``tf`` with ``N`` intervals: ``dt = tf / N``, the weights' "·dt" redone,
    ``X_init`` resampled at the new knots (the HM-iLQR paper's comparisons at two resolutions). Pass it to
    :func:`get` or to :class:`~torchtraj.bench.reference.ReferenceSolver`."""
    s = spec(name)
    ratio = (s.tf / N) / s.dt
    X_init = None
    if s.X_init is not None:
        old, new = np.linspace(0.0, 1.0, s.N + 1), np.linspace(0.0, 1.0, N + 1)
        X_init = np.stack([np.interp(new, old, s.X_init[:, i]) for i in range(s.nx)], 1)
    return dataclasses.replace(s, name=f"{name}_N{N}", N=N, Q=s.Q * ratio, R=s.R * ratio, X_init=X_init)


def sample_x0(name: str, count: int, seed: int) -> Tensor:
    """``(count, nx)`` float64 initial states ``x0 + U(−1, 1) * spread`` (the problem set's rule, bit for bit).

    The draw is ``numpy.random.default_rng(seed).uniform(-1, 1, (count, nx))``. The unconstrained twins
    use the spread of ``pendulum`` / ``cartpole``; ``car_escape`` has no spread (its initial state is
    boxed in by walls) and raises ``ValueError``.
    """
    s = spec(name)
    if s.spread is None:
        raise ValueError(f"problem {name!r} has no batch spread in the problem set; sample_x0 is undefined for it")
    if not isinstance(count, int) or count < 1:
        raise ValueError(f"count must be a positive int, got {count!r}")
    draw = np.random.default_rng(seed).uniform(-1.0, 1.0, (count, s.nx))
    return torch.from_numpy(s.x0 + draw * s.spread)
