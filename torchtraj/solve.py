"""``tt.solve``: one entry point for every method.

It checks and broadcasts the user's inputs to the batch (``x0 (B, nx)``, ``U0 (B, N, nu)``,
``X0 (B, N+1, nx)``, batched parameters), moves them to the problem's dtype and device,
and hands them to the method's solver.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import warnings
from typing import Optional, Union

import torch
from torch import Tensor

from .core.graphs import graphs_used
from .core.problem import Problem
from .core.solution import Solution
from .differentiation import implicit
from .iterations.ilqr import ILQROptions
from .solvers.altro.options import ALTROOptions
from .solvers.altro.solver import solve_altro
from .solvers.ilqr import solve_ilqr
from .solvers.ipm.options import IPOptions
from .solvers.ipm.solver import solve_interior_point


class Method(str, enum.Enum):
    """Solver methods; strings are accepted too (``method="ilqr"``)."""

    ILQR = "ilqr"
    ALTRO = "altro"
    AL_ILQR = "al-ilqr"
    IPM = "ipm"


OPTIONS = {Method.ILQR: ILQROptions, Method.ALTRO: ALTROOptions, Method.AL_ILQR: ALTROOptions, Method.IPM: IPOptions}


def _batched(value, name: str, shape: tuple, problem: Problem) -> Optional[Tensor]:
    """``value`` as a tensor of shape ``(B, *shape)`` (B = 1 when it had no batch dimension)."""
    if value is None:
        return None
    t = torch.as_tensor(value, dtype=problem.dtype, device=problem.device)
    if tuple(t.shape) == shape:
        return t.unsqueeze(0)
    if t.dim() == len(shape) + 1 and tuple(t.shape[1:]) == shape:
        return t
    raise ValueError(f"{name} must have shape {shape} or (B, *{shape}), got {tuple(t.shape)}")


def _batch_size(named: dict) -> int:
    sizes = {name: int(t.shape[0]) for name, t in named.items() if t is not None and t.shape[0] != 1}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"batch sizes disagree: {sizes}")
    return next(iter(sizes.values()), 1)


def _options(method: Method, options):
    cls = OPTIONS[method]
    if options is None:
        return cls()
    if isinstance(options, dict):
        return cls(**options)
    if not isinstance(options, cls):
        raise TypeError(f"options for method {method.value!r} must be {cls.__name__} or a dict, got {type(options).__name__}")
    return options


def solve(
    problem: Problem,
    x0=None,
    method: Union[str, Method] = "ilqr",
    U0=None,
    X0=None,
    options=None,
    duals: Optional[dict] = None,
    gradients: str = "implicit",
) -> Solution:
    """Solve a batch of instances of ``problem``.

    Args:
        problem: the :class:`~torchtraj.Problem`.
        x0: initial states ``(nx,)`` or ``(B, nx)``; ``None`` uses ``problem.x0``.
        method: a :class:`Method` or its name.
        U0: initial control guess ``(N, nu)`` or ``(B, N, nu)``; ``None`` uses ``problem.u_init``.
        X0: initial state guess ``(N+1, nx)`` or ``(B, N+1, nx)`` for methods that take one; for
            ``"altro"`` it triggers the infeasible start (slack controls, ALTRO §III-B).
        options: the method's options dataclass (or a dict of its fields).
        duals: warm start of the augmented-Lagrangian methods: ``{"multipliers": ..., "penalties": ...}``,
            each a dict of per-block tensors laid out like :attr:`Solution.multipliers` (a previous
            solution's, shifted by MPC for instance); missing blocks start at 0 and ``penalty_initial``.
            With ``X0``, an optional ``"costate": (B, N+1, nx)`` (:attr:`Solution.costate`) starts the
            multipliers of the slack rows ``s_k = 0`` at ``−λ_{k+1}``, their value at a KKT point.
        gradients: how a differentiable solve (below) differentiates: ``"implicit"`` (exact: the
            implicit function theorem at the refined KKT point) or ``"unrolled"`` (cheaper, approximate:
            the derivative of one final iLQR step at the solver's point, :mod:`torchtraj.differentiation.implicit`).

    Returns:
        A :class:`~torchtraj.Solution` with per-instance status. The batch size B is the common
        leading dimension of ``x0``, ``U0``, ``X0`` and the batched parameters (1 if none has one).
        When grad is enabled and ``x0`` or a tensor of ``problem.params`` requires grad, ``X``, ``U``
        and ``cost`` are differentiable with respect to them by implicit differentiation of the KKT
        conditions, at the solution refined by Newton steps (:mod:`torchtraj.differentiation.implicit`; instances
        that did not converge get zero gradients and a warning).
    """
    method = check_problem_and_method(problem, method)
    implicit.check_gradients_mode(gradients)
    opts = _options(method, options)
    N, nx, nu = problem.N, problem.nx, problem.nu
    x0 = _batched(problem.x0 if x0 is None else x0, "x0", (nx,), problem)
    U0 = _batched(problem.u_init if U0 is None else U0, "U0", (N, nu), problem)
    X0 = _batched(X0, "X0", (N + 1, nx), problem)
    pb = problem.param_batch_size()
    B = _batch_size({"x0": x0, "U0": U0, "X0": X0, "params": torch.empty(pb)})
    x0, U0 = x0.expand(B, nx), U0.expand(B, N, nu)
    params = problem.batched_params(B)
    if getattr(opts, "verbose", False):
        _ensure_log_handler()
    if duals is not None and method in (Method.ILQR, Method.IPM):
        raise ValueError(f"method {method.value!r} takes no warm-started duals; duals is for 'altro' / 'al-ilqr'")
    if not implicit.requires_gradients(x0, params):
        return _dispatch(problem, method, opts, x0.contiguous(), U0.contiguous(), X0, params, B, duals)
    # a differentiable solve: the method runs on detached inputs, gradients come from its KKT point
    detached = {k: v.detach() for k, v in params.items()}
    solution = _dispatch(problem, method, opts, x0.detach().contiguous(), U0.detach().contiguous(),
                         None if X0 is None else X0.detach(), detached, B, duals)
    return implicit.attach_gradients(problem, x0, params, solution, gradients=gradients,
                                     cuda_graphs=graphs_used(opts, x0.device), constrained=method is not Method.ILQR)


def check_problem_and_method(problem, method: Union[str, Method]) -> Method:
    """``method`` as a :class:`Method`, or a clear error for a non-Problem or an unknown method name."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a torchtraj.Problem, got {type(problem).__name__}")
    try:
        return Method(method)
    except ValueError:
        raise ValueError(f"unknown method {method!r}; choose one of {[m.value for m in Method]}") from None


def _dispatch(problem: Problem, method: Method, opts, x0: Tensor, U0: Tensor, X0: Optional[Tensor], params,
              B: int, duals: Optional[dict] = None) -> Solution:
    """Run the method's solver on the checked, batched inputs."""
    if method in (Method.ALTRO, Method.AL_ILQR):
        if method is Method.AL_ILQR:
            opts = dataclasses.replace(opts, projection=False)
        X0 = None if X0 is None else X0.expand(B, *X0.shape[1:]).contiguous()
        return solve_altro(problem, x0, U0, params, opts, X0=X0, method=method.value, duals=duals)
    if method is Method.IPM:
        X0 = None if X0 is None else X0.expand(B, *X0.shape[1:]).contiguous()
        return solve_interior_point(problem, x0, U0, params, opts, X0=X0, method=method.value)
    if method is Method.ILQR:
        if X0 is not None:
            raise ValueError("method 'ilqr' simulates its states from x0 and cannot take X0; use a method that "
                             "accepts an infeasible state guess")
        if problem.has_constraints:
            warnings.warn(f"method 'ilqr' ignores the constraints of problem {problem.name!r}; "
                          "Solution.max_violation reports them", stacklevel=3)
        return solve_ilqr(problem, x0, U0, params, opts)
    raise AssertionError(method)  # pragma: no cover - every Method is handled above


def _ensure_log_handler() -> None:
    logger = logging.getLogger("torchtraj")
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)
