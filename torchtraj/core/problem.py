"""The one problem representation every solver shares.

A :class:`Problem` states a discrete-time optimal control problem with per-instance
functions (no batch dimension; the library vmaps them over batch and time)::

    minimize    sum_{k=0}^{N-1} l(x_k, u_k, p) + l_N(x_N, p)
    subject to  x_{k+1} = f(x_k, u_k, p),                   k = 0..N-1,  x_0 given
                h(x_k, u_k, p) = 0,  g(x_k, u_k, p) <= 0,   k = 0..N-1   (path, mixed)
                s(x_k, p) <= 0,  x_lower <= x_k <= x_upper,  k = 1..N-1  (state path)
                u_lower <= u_k <= u_upper,                  k = 0..N-1
                h_N(x_N, p) = 0,  g_N(x_N, p) <= 0                      (terminal)

State-only path constraints start at knot 1 because x_0 is fixed;
put a state constraint on x_N in the terminal functions.

``p`` is a dict of tensors. Each entry has a per-instance shape and may carry one extra leading batch
dimension; gradients flow to these tensors in differentiable solves. The constructor takes *one instance's*
parameters: a shape not declared in ``param_shapes`` is the given value's. One value per instance is passed
with :meth:`Problem.with_params` (or declared: ``param_shapes={"goal": (2,)}`` with a ``(B, 2)`` value). The batch
dimension is never guessed: where a constructor's parameter of two or more dimensions has the solve's batch size as
its leading dimension and the functions accept one row of it too, the solve refuses it and says how to declare it
(:func:`torchtraj.core.batch.check_parameter_batch`).

The problem is checked at construction (:mod:`torchtraj.core.probe`): every function runs on copies of the
inputs and under ``torch.func.vmap`` / ``jacrev`` as the solvers run it; wrong output shapes or dtypes,
non-finite outputs, in-place writes into the inputs, code that torch.func cannot batch (``.item()``, numpy,
Python branches on tensors) and mismatched dimensions raise a ``ValueError`` naming the function and what to
change; a cut graph (a Jacobian identically zero where the value changes) is warned about. Bounds must not be
NaN, a lower bound ``+inf`` or an upper bound ``-inf`` is infeasible, and ``lower <= upper``.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field
from typing import Callable, Mapping, Optional

import torch
from torch import Tensor

from .describe import problem_repr
from .probe import probe

Params = Mapping[str, Tensor]
StageFn = Callable[[Tensor, Tensor, Params], Tensor]
StateFn = Callable[[Tensor, Params], Tensor]


@dataclass(frozen=True)
class Problem:
    """A trajectory optimisation problem; see the module docstring for its mathematics.

    Args:
        dynamics: ``f(x (nx,), u (nu,), p) -> x_next (nx,)``.
        stage_cost: ``l(x, u, p) -> ()``.
        terminal_cost: ``l_N(x, p) -> ()``.
        x0: default initial state ``(nx,)``.
        horizon: number of intervals N (N+1 knots), a positive integer (numpy integers accepted, bools not).
        nu: number of controls, a positive integer.
        params: ``p``, a dict of tensors: one instance's values (module docstring); batched ones through
            :meth:`with_params` or a declared ``param_shapes``.
        stage_eq / stage_ineq: ``(x, u, p) -> (m,)``, on knots 0..N-1 (``g <= 0``).
        state_ineq: ``(x, p) -> (m,)`` on knots 1..N-1.
        terminal_eq / terminal_ineq: ``(x, p) -> (m,)`` on knot N.
        u_lower, u_upper: ``(nu,)`` control bounds, ``±inf`` where unbounded.
        x_lower, x_upper: ``(nx,)`` state bounds on knots 1..N-1, ``±inf`` where unbounded.
        u_init: ``(nu,)`` or ``(N, nu)`` default initial control guess.
        X_init: optional ``(N+1, nx)`` default initial state guess.
        dt: duration of one interval, when the problem has one (for plots and time penalties).
        name: a label for reports.
        param_shapes: per-instance shape of some or all parameters; the others' are the given shapes. A value with
            one more leading dimension than its declared shape is batched.
        linear_quadratic: declares the dynamics and every constraint affine in ``(x, u)`` and the costs
            quadratic (parameters may enter any way). The interior-point method then expands the problem
            once and evaluates its derivatives at later iterates by products, and implicit differentiation
            factorises once and refines by one Newton step (the cost Hessian is the Lagrangian's). Checked at
            construction: the Jacobians and cost Hessians at a second probe point must equal those at the first.
    """

    dynamics: StageFn
    stage_cost: StageFn
    terminal_cost: StateFn
    x0: Tensor
    horizon: int
    nu: int
    params: dict = field(default_factory=dict)
    stage_eq: Optional[StageFn] = None
    stage_ineq: Optional[StageFn] = None
    state_ineq: Optional[StateFn] = None
    terminal_eq: Optional[StateFn] = None
    terminal_ineq: Optional[StateFn] = None
    u_lower: Optional[Tensor] = None
    u_upper: Optional[Tensor] = None
    x_lower: Optional[Tensor] = None
    x_upper: Optional[Tensor] = None
    u_init: Optional[Tensor] = None
    X_init: Optional[Tensor] = None
    dt: Optional[float] = None
    name: str = "problem"
    param_shapes: Optional[dict] = None
    linear_quadratic: bool = False

    def __post_init__(self) -> None:
        x0 = torch.as_tensor(self.x0)
        if not x0.is_floating_point():
            x0 = x0.to(torch.get_default_dtype())
        if x0.dim() != 1:
            raise ValueError(f"Problem.x0 must have shape (nx,), got {tuple(x0.shape)}")
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        set_("x0", x0)
        set_("horizon", _positive_int("horizon", self.horizon))
        set_("nu", _positive_int("nu", self.nu))
        params = {k: torch.as_tensor(v, dtype=x0.dtype, device=x0.device) for k, v in self.params.items()}
        set_("params", params)
        declared = dict(self.param_shapes or {})
        unknown = set(declared) - set(params)
        if unknown:
            raise ValueError(f"param_shapes names unknown parameters {sorted(unknown)}; "
                             f"the parameters are {sorted(params)}")
        # a shape not declared is the given value's: one instance's parameter (see Batch.build for the ambiguous case)
        set_("param_shapes", {k: tuple(declared.get(k, v.shape)) for k, v in params.items()})
        object.__setattr__(self, "_inferred_shapes", frozenset(k for k in params if k not in declared))
        for k, v in params.items():
            shape = tuple(self.param_shapes[k])
            if tuple(v.shape) != shape and tuple(v.shape[1:]) != shape:
                raise ValueError(
                    f"parameter {k!r} has shape {tuple(v.shape)}; expected {shape} or (B, *{shape})"
                )
        nx, nu = self.nx, self.nu
        for name, n in (("u_lower", nu), ("u_upper", nu), ("x_lower", nx), ("x_upper", nx)):
            value = getattr(self, name)
            if value is not None:
                value = torch.as_tensor(value, dtype=x0.dtype, device=x0.device)
                if value.shape != (n,):
                    raise ValueError(f"Problem.{name} must have shape ({n},), got {tuple(value.shape)}")
                if bool(torch.isnan(value).any()):
                    raise ValueError(f"Problem.{name} holds NaN at {_where(torch.isnan(value))}: "
                                     f"a bound must be a number, or ±inf where unbounded")
                set_(name, value)
        for lo, hi in (("u_lower", "u_upper"), ("x_lower", "x_upper")):
            a, b = getattr(self, lo), getattr(self, hi)
            # +inf below or -inf above is no absent bound but an impossible one (no value meets it)
            for name, bound, impossible in ((lo, a, float("inf")), (hi, b, -float("inf"))):
                if bound is not None and bool((bound == impossible).any()):
                    raise ValueError(f"Problem.{name} is {impossible} at {_where(bound == impossible)}: no value "
                                     f"satisfies it (infeasible); an absent bound is {-impossible}")
            if a is not None and b is not None and bool((a > b).any()):
                raise ValueError(f"Problem.{lo} exceeds Problem.{hi} at {_where(a > b)} (infeasible bounds): "
                                 f"{a.tolist()} > {b.tolist()}")
        u_init = self.u_init if self.u_init is not None else torch.zeros(nu)
        u_init = torch.as_tensor(u_init, dtype=x0.dtype, device=x0.device)
        if u_init.shape == (nu,):
            u_init = u_init.expand(self.horizon, nu).clone()
        if u_init.shape != (self.horizon, nu):
            raise ValueError(
                f"Problem.u_init must have shape ({nu},) or ({self.horizon}, {nu}), got {tuple(u_init.shape)}"
            )
        set_("u_init", u_init)
        if self.X_init is not None:
            X_init = torch.as_tensor(self.X_init, dtype=x0.dtype, device=x0.device)
            if X_init.shape != (self.horizon + 1, nx):
                raise ValueError(
                    f"Problem.X_init must have shape ({self.horizon + 1}, {nx}), got {tuple(X_init.shape)}"
                )
            set_("X_init", X_init)
        self._probe()

    # ----------------------------------------------------------------- sizes
    @property
    def nx(self) -> int:
        return int(self.x0.shape[0])

    @property
    def N(self) -> int:
        return self.horizon

    @property
    def dtype(self) -> torch.dtype:
        return self.x0.dtype

    @property
    def device(self) -> torch.device:
        return self.x0.device

    @property
    def has_constraints(self) -> bool:
        bounds = (self.u_lower, self.u_upper, self.x_lower, self.x_upper)
        funcs = (self.stage_eq, self.stage_ineq, self.state_ineq, self.terminal_eq, self.terminal_ineq)
        return any(f is not None for f in funcs) or any(
            b is not None and bool(torch.isfinite(b).any()) for b in bounds
        )

    # ------------------------------------------------------------ derived objects
    def derived(self, store: str, key, make: Callable[[], object]):
        """``make()``, made once per problem and ``key`` and kept on the problem in the dictionary ``store`` (the
        solvers' constraint layout, scaled and barrier problems). Made outside ``torch.inference_mode``, where
        ``tt.solve`` runs a method's iterations: a later differentiable solve of this problem may save its tensors
        for backward, which it could not save of inference tensors."""
        kept = self.__dict__.setdefault(store, {})
        if key not in kept:
            with torch.inference_mode(False):
                kept[key] = make()
        return kept[key]

    # ------------------------------------------------------------ transforms
    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed (validated again).

        A new ``horizon`` without a new ``u_init`` / ``X_init`` resizes the guesses: a guess that is the same at every
        step (the default zeros, or a ``(nu,)`` guess) stays that per-step value; a time-varying one is cut to the new
        horizon, or extended by repeating its last control (last state for ``X_init``). Parameters keep their
        declared or inferred per-instance shapes."""
        if "horizon" in changes:
            N = _positive_int("horizon", changes["horizon"])
            if "u_init" not in changes:
                constant = bool((self.u_init == self.u_init[:1]).all())
                changes["u_init"] = self.u_init[0] if constant else _resized(self.u_init, N)
            if "X_init" not in changes and self.X_init is not None:
                changes["X_init"] = _resized(self.X_init, N + 1)
        new = dataclasses.replace(self, **changes)
        if "param_shapes" not in changes:
            # the shapes passed on were the resolved ones: those inferred here stay inferred (Batch.build)
            object.__setattr__(new, "_inferred_shapes",
                               (self._inferred_shapes & set(new.params)) | (set(new.params) - set(self.params)))
        return new

    def with_params(self, **params: Tensor) -> "Problem":
        """A copy whose parameters ``params`` are replaced (per-instance or batched)."""
        unknown = set(params) - set(self.params)
        if unknown:
            raise ValueError(f"unknown parameters {sorted(unknown)}; this problem has {sorted(self.params)}")
        return self.replace(params={**self.params, **params})

    def to(self, *args, dtype: Optional[torch.dtype] = None, device=None) -> "Problem":
        """A copy with every tensor moved to ``dtype`` / ``device``, given as :meth:`torch.Tensor.to` takes them:
        ``problem.to("cuda")``, ``problem.to(torch.float32)``, ``problem.to("cuda", torch.float32)`` or by keyword.
        Tensors that the problem's functions hold themselves (a closure's constant) are not the problem's to move."""
        for arg in args:
            if isinstance(arg, torch.dtype) and dtype is None:
                dtype = arg
            elif isinstance(arg, (str, int, torch.device)) and not isinstance(arg, bool) and device is None:
                device = torch.device(arg)
            elif arg is not None:
                raise TypeError(f"Problem.to takes a dtype and a device (each at most once), not {arg!r}")

        def move(t):
            return None if t is None else t.to(dtype=dtype or t.dtype, device=device or t.device)

        return self.replace(
            x0=move(self.x0),
            params={k: move(v) for k, v in self.params.items()},
            u_lower=move(self.u_lower), u_upper=move(self.u_upper),
            x_lower=move(self.x_lower), x_upper=move(self.x_upper),
            u_init=move(self.u_init), X_init=move(self.X_init),
        )

    def instance_params(self) -> dict:
        """Parameters of one instance (the first along a batch dimension), for probes."""
        out = {}
        for k, v in self.params.items():
            out[k] = v[0] if tuple(v.shape) != tuple(self.param_shapes[k]) else v
        return out

    def param_batch_size(self) -> int:
        """The batch size carried by batched parameters (1 when none is batched)."""
        sizes = {
            int(v.shape[0]) for k, v in self.params.items() if tuple(v.shape) != tuple(self.param_shapes[k])
        }
        if len(sizes) > 1:
            raise ValueError(f"batched parameters disagree on the batch size: {sorted(sizes)}")
        return sizes.pop() if sizes else 1

    def batched_params(self, batch: int) -> dict:
        """Every parameter expanded to a leading batch dimension of size ``batch`` (no copy)."""
        out = {}
        for k, v in self.params.items():
            shape = tuple(self.param_shapes[k])
            if tuple(v.shape) == shape:
                v = v.expand(batch, *shape)
            elif v.shape[0] == 1 and batch != 1:
                v = v.expand(batch, *shape)
            elif v.shape[0] != batch:
                raise ValueError(f"parameter {k!r} has batch size {v.shape[0]}, but the solve has {batch}")
            out[k] = v
        return out

    # ---------------------------------------------------------------- probing
    def _probe(self) -> None:
        """Run every function as the solvers will (:mod:`torchtraj.core.probe`); raise ValueError on misuse."""
        # read once, here: the solvers' constraint layout (Constraints) never calls the user's functions for it again
        object.__setattr__(self, "_constraint_sizes", probe(self))
        if self.linear_quadratic:
            self._check_linear_quadratic(self.x0, self.u_init[0], self.instance_params())

    def _constant_derivatives(self, x: Tensor, u: Tensor, p: Params) -> dict:
        """The derivatives that a linear-quadratic problem has constant: Jacobians of the dynamics and
        constraints, Hessians of the costs, at ``(x, u)``."""
        from torch.func import hessian, jacrev

        z = torch.cat([x, u])
        nx = self.nx

        def on_z(fn):
            return lambda z_: fn(z_[:nx], z_[nx:], p)

        out = {"dynamics": jacrev(on_z(self.dynamics))(z),
               "stage_cost": hessian(on_z(self.stage_cost))(z),
               "terminal_cost": hessian(lambda x_: self.terminal_cost(x_, p))(x)}
        for name in ("stage_eq", "stage_ineq", "state_ineq", "terminal_eq", "terminal_ineq"):
            fn = getattr(self, name)
            if fn is not None:
                out[name] = jacrev(on_z(fn))(z) if name.startswith("stage") else jacrev(lambda x_: fn(x_, p))(x)
        return out

    def _check_linear_quadratic(self, x: Tensor, u: Tensor, p: Params) -> None:
        """Raise ValueError unless the derivatives of :meth:`_constant_derivatives` agree at ``(x, u)`` and at a
        second, pseudo-random point (a declaration check, not a proof: a function may be affine near both)."""
        x, u, p = x.detach(), u.detach(), {k: v.detach() for k, v in p.items()}
        g = torch.Generator().manual_seed(0)
        scale = 1.0 + float(torch.cat([x, u]).abs().max())
        dx = scale * torch.randn(x.shape, generator=g, dtype=torch.float64).to(x)
        du = scale * torch.randn(u.shape, generator=g, dtype=torch.float64).to(u)
        first, second = self._constant_derivatives(x, u, p), self._constant_derivatives(x + dx, u + du, p)
        tol = float(torch.finfo(x.dtype).eps) ** 0.5
        for name, a in first.items():
            b = second[name]
            gap = float((a - b).abs().max()) if a.numel() else 0.0
            if not gap <= tol * (1.0 + float(a.abs().max() if a.numel() else 0.0)):
                kind = "Hessian" if name.endswith("cost") else "Jacobian"
                shape = "quadratic" if name.endswith("cost") else "affine"
                raise ValueError(f"Problem declared linear_quadratic, but Problem.{name} is not {shape}: its {kind} "
                                 f"changes by {gap:.3g} between two probe points")

    def __repr__(self) -> str:
        return problem_repr(self)  # sizes, dtype, constraints present, parameter shapes; never whole tensors

    def constraint_sizes(self) -> dict:
        """Number of rows of each constraint function (0 when absent), as the probe call found them."""
        return dict(self._constraint_sizes)


def _positive_int(name: str, value) -> int:
    """``value`` as a Python int (numpy integers accepted); a bool, a float or a value below 1 is a ValueError."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < 1:
        kind = " (a bool)" if isinstance(value, bool) else f" ({type(value).__name__})"
        raise ValueError(f"Problem.{name} must be a positive int, got {value!r}{kind}")
    return int(value)


def _where(mask: Tensor) -> list:
    """The indices where ``mask`` holds, for an error message."""
    return torch.nonzero(mask).reshape(-1).tolist()


def _resized(guess: Tensor, length: int) -> Tensor:
    """``guess (L, n)`` cut to ``length`` rows, or extended by repeating its last row."""
    if guess.shape[0] >= length:
        return guess[:length]
    return torch.cat([guess, guess[-1:].expand(length - guess.shape[0], guess.shape[1])])
