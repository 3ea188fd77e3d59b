"""``tt.solve``: one entry point for every method.

It finds the method in the registry (:mod:`torchtraj.solvers`), checks the options against its options class and
the arguments against its declarations (:mod:`torchtraj.solvers.base`), builds the batch once
(:class:`~torchtraj.core.batch.Batch`: ``x0 (B, nx)``, ``U0 (B, N, nu)``, ``X0 (B, N+1, nx)``, batched parameters,
in the problem's dtype and device) and hands it to the method's solver. A differentiable solve gets its gradients
from the implicit layer at the solver's KKT point (of the constrained problem where the method handles the
constraints, else of the unconstrained one).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import logging
import warnings
from typing import Optional, Union

import torch
from torch.utils import _python_dispatch

from . import solvers
from .core import compiled
from .core.batch import Batch
from .core.constraints import Constraints, check_duals, map_duals
from .core.derivatives import differentiates_in_inference_mode
from .core.graphs import graphs_used
from .core.problem import Problem
from .core.solution import Solution, without_inference_tensors
from .core.status import Status
from .differentiation import implicit
from .kkt import certificate
from .solvers.base import Solver

#: The registered methods as an enum, a convenience for ``method=`` (strings do as well); nothing branches on it.
Method = enum.Enum("Method", {name.upper().replace("-", "_"): name for name in solvers.names()}, type=str,
                   module=__name__)
Method.__doc__ = "The registered methods (:func:`torchtraj.solvers.names`); strings do too (``method=\"ilqr\"``)."


def solve(
    problem: Problem,
    x0=None,
    method: Union[str, Method, Solver, None] = None,
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
        method: a registered method's name (:func:`torchtraj.solvers.names`), a :class:`Method`, or a
            :class:`~torchtraj.solvers.base.Solver` object. ``None`` picks one that respects the problem
            (:func:`default_method`): the method of ``options``' class where an options object is given (the first
            registered: ``"altro"`` for :class:`~torchtraj.ALTROOptions`); else ``"ilqr"`` where the problem has no
            constraints (no constraint function, no finite bound) and ``"ipm"`` where it has some. The interior
            point is the constrained default because, with its default options and each problem's own guesses, it
            reaches IPOPT's optimum (or a lower local optimum IPOPT keeps) on every problem of the set measured (all
            but ``car_escape``), the obstacle problems through its restoration phase, in 13 to 143 iterations;
            ALTRO's defaults take up to 902 (the cart-pole) (``docs/benchmarks.md``, "Default options"). Name a
            method to choose otherwise.
        U0: initial control guess ``(N, nu)`` or ``(B, N, nu)``; ``None`` uses ``problem.u_init``.
        X0: initial state guess ``(N+1, nx)`` or ``(B, N+1, nx)`` for methods that take one
            (``takes_state_guess``); for ``"altro"`` it triggers the infeasible start (slack controls, ALTRO §III-B),
            which the problem's own ``X_init`` triggers where no ``X0`` is given.
        options: the method's options dataclass (or a dict of its fields).
        duals: warm start of the methods that take one (``takes_duals``; each method's ``dual_entries``).
            The augmented-Lagrangian methods take ``{"multipliers": ..., "penalties": ...}``, each a dict of
            per-block tensors laid out like :attr:`Solution.multipliers` (a previous solution's, shifted by MPC
            for instance); missing blocks start at 0 and ``penalty_initial``. With ``X0``, an optional
            ``"costate": (B, N+1, nx)`` (:attr:`Solution.costate`) starts the multipliers of the slack rows
            ``s_k = 0`` at ``−λ_{k+1}``, their value at a KKT point.
            The interior point takes ``"multipliers"``, ``"costate"`` and ``"barrier": (B,)`` (the last entry of
            a solution's ``history.extra["barrier"]``; an instance whose barrier is 0 starts cold), its start
            from the primal-dual point of a solution near this one
            (:mod:`torchtraj.solvers.ipm.warm_start`): pass that solution's ``U0`` and ``X0`` with them.
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
    solver = check_problem_and_method(problem, default_method(problem, options) if method is None else method)
    implicit.check_gradients_mode(gradients)
    opts = solver.options(options)
    batch = Batch.build(problem, x0, U0, X0, duals)
    _check_declarations(solver, problem, batch)
    if eager_despite_compile(solver, opts):
        warnings.warn(f"method {solver.name!r} has no compiled kernels: compile=True runs it eager", stacklevel=2)
        opts = solver.with_kernels(opts, compile=False)
    with _verbose_logging(getattr(opts, "verbose", False)), compiled.batch_of(batch.B):
        return _solve(solver, problem, batch, opts, gradients)


def _solve(solver: Solver, problem: Problem, batch: Batch, opts, gradients: str) -> Solution:
    declared = solver.kkt_problem(problem, opts)  # the problem whose KKT point it is, where that is another one
    graphed = graphs_used(opts, batch.x0.device)
    kept = graphed or solver.kernel_setting(opts, "compile", False)
    if not implicit.requires_gradients(batch.x0, batch.params):
        return _without_autograd(lambda: _certified(solver, problem if declared is None else declared, batch, opts,
                                                    solver.solve(problem, batch.for_solver(), opts)), kept)
    if not solver.kkt_point:
        raise ValueError(f"method {solver.name!r} returns no KKT point to differentiate; solve without gradients "
                         f"(torch.no_grad, or detached x0 and params) or use {_declaring('kkt_point')}")
    if not solver.fixes_initial_state(opts):
        raise ValueError(f"{solver.name}: a solution with a free initial state is not differentiated (the implicit "
                         "layer holds x0 fixed); solve it without gradients")
    # a differentiable solve: the method runs on detached inputs, gradients come from its KKT point
    solution = _without_autograd(lambda: _certified(solver, problem if declared is None else declared, batch, opts,
                                                    solver.solve(problem, batch.for_solver(detach=True), opts)), kept)
    out = implicit.attach_gradients(problem if declared is None else declared, batch.x0, batch.params, solution,
                                    gradients=gradients, cuda_graphs=graphed,
                                    constrained=solver.handles_constraints)
    if declared is None:
        return out
    # the cost reported is the problem's own (eILQR's barriers are not part of it); gradients only where converged
    cost = implicit.masked_cost(problem, out.status == Status.CONVERGED, out.X, out.U, batch.params)
    return dataclasses.replace(out, cost=cost)


# whether a dispatch mode is active (torch's private API, looked up softly: without it, a solve under a mode runs in
# inference mode like any other)
_IN_DISPATCH_MODE = getattr(_python_dispatch, "is_in_torch_dispatch_mode", lambda: False)


def _without_autograd(run, kept: bool) -> Solution:
    """``run()``, a solve that autograd does not record (the method's iterations: a differentiable solve's gradients
    come after, from its KKT point), under ``torch.inference_mode``: its operators skip autograd's bookkeeping (the
    same operators on the same data, the same results to the last bit, each call cheaper), and the solution's tensors
    are returned as normal ones (:func:`~torchtraj.core.solution.without_inference_tensors`), which a caller may
    change in place or use in a differentiated computation. Inside the caller's own inference mode they stay as made.
    Not where kernels are ``kept`` across solves: CUDA graphs, whose static buffers are written in place at every
    replay, and compiled kernels, whose guards tell inference tensors from normal ones (a kernel would be captured
    again for each kind). Nor under a dispatch mode (``torchtraj.bench.ops.OperatorCounter``, a trace), which sees
    other calls in inference mode (composite operators whole, an ``unbind`` replayed by TorchScript as its
    ``select``s): a count of calls is the same solve's, whichever mode it runs in.

    Where this PyTorch's ``torch.func`` returns zero derivatives in inference mode
    (:func:`~torchtraj.core.derivatives.differentiates_in_inference_mode`), the iterations run under
    ``torch.no_grad`` instead, outside the caller's inference mode too (its inference tensors can be read there)."""
    if not differentiates_in_inference_mode():
        with torch.inference_mode(False), torch.no_grad():
            return run()
    if kept or torch.is_inference_mode_enabled() or _IN_DISPATCH_MODE():
        return run()
    with torch.inference_mode():
        solution = run()
    return without_inference_tensors(solution)


def _certified(solver: Solver, problem: Problem, batch: Batch, opts, solution: Solution) -> Solution:
    """``solution`` with its KKT residuals, and ``CONVERGED`` only where they are within the certificate's
    tolerances (:mod:`torchtraj.kkt.certificate`): the KKT conditions of ``problem`` with its constraints where the
    method handles them, without them where it ignores them."""
    if not solver.kkt_point:
        return solution
    constraints = Constraints.of(problem, ignored=not solver.handles_constraints)
    params = {k: v.detach() for k, v in batch.params.items()}
    # a free start (eILQR's free_initial_state) has no initial defect; its own rows are the method's to meet
    x0 = batch.x0.detach() if solver.fixes_initial_state(opts) else None
    record = solver.kernel_setting(opts, "record", False)  # replayed residuals where the expansion is replayed
    compile = bool(solver.kernel_setting(opts, "compile", False)) and not graphs_used(opts, batch.x0.device)
    status, residuals = certificate.certify(problem, solution.status, solution.X, solution.U, solution.multipliers,
                                            params, x0, constraints, record=record, compile=compile)
    return dataclasses.replace(solution, status=status, kkt=residuals.as_dict())


def default_method(problem: Problem, options=None) -> str:
    """The method ``tt.solve`` uses when none is named (:func:`solve`'s ``method``): the first registered method
    whose options class ``options`` is an instance of; else ``"ilqr"`` for a problem without constraints and
    ``"ipm"`` for one with some."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a torchtraj.Problem, got {type(problem).__name__}")
    named = [n for n in solvers.names() if options is not None and type(options) is solvers.get(n).options_class]
    if named:
        return named[0]
    return "ipm" if problem.has_constraints else "ilqr"


def check_problem_and_method(problem, method: Union[str, Method, Solver]) -> Solver:
    """The registered :class:`~torchtraj.solvers.base.Solver` of ``method``, or a clear error for a non-Problem
    or an unknown method name."""
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a torchtraj.Problem, got {type(problem).__name__}")
    return solvers.get(method)


def _check_declarations(solver: Solver, problem: Problem, batch: Batch) -> None:
    """Refuse the arguments the method does not declare it takes; warn where it ignores the constraints."""
    if batch.duals is not None and not solver.takes_duals:
        raise ValueError(f"method {solver.name!r} takes no warm-started duals; duals is for "
                         f"{_declaring('takes_duals')}")
    if batch.duals is not None:
        check_duals(Constraints.of(problem), batch.duals, batch.B, solver.dual_entries, solver.name)
    if batch.X0 is not None and not solver.takes_state_guess:
        raise ValueError(f"method {solver.name!r} simulates its states from x0 and cannot take X0; use a method "
                         f"that accepts a state guess: {_declaring('takes_state_guess')}")
    if problem.has_constraints and not solver.handles_constraints:
        warnings.warn(f"method {solver.name!r} ignores the constraints of problem {problem.name!r}; "
                      "Solution.max_violation reports them", stacklevel=3)


def eager_despite_compile(solver: Solver, opts) -> bool:
    """Whether ``opts`` ask for compiled kernels (:meth:`Solver.kernel_options`) that the method does not have
    (:attr:`Solver.compiles`): the field is accepted, for the control-step interface, and the method runs eager (the
    solve passes it options with ``compile=False``)."""
    return not solver.compiles and bool(solver.kernel_setting(opts, "compile"))


def _declaring(flag: str) -> str:
    """The registered methods that declare ``flag``, for an error message."""
    return " / ".join(repr(n) for n in solvers.names() if getattr(solvers.get(n), flag))


@contextlib.contextmanager
def _verbose_logging(verbose: bool):
    """With ``verbose``, the ``torchtraj`` logger prints INFO lines for the solve (a stream handler added where it
    has none); its level and handlers are restored afterwards, so the caller's logging setup is left as found."""
    if not verbose:
        yield
        return
    logger = logging.getLogger("torchtraj")
    level, handler = logger.level, None
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(message)s"))
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.setLevel(level)
        if handler is not None:
            logger.removeHandler(handler)


def warm_start(solution: Solution) -> dict:
    """``tt.solve``'s keyword arguments that start a solve of a nearby problem (another ``x0``, other parameters)
    from ``solution``: its controls ``U0``; its states ``X0`` where its method starts from states (multiple
    shooting: :attr:`~torchtraj.solvers.base.Solver.starts_from_shifted_states`); its duals where the method takes
    them, as a controller carries them (:meth:`~torchtraj.solvers.base.Solver.carried_duals`: ALTRO's multipliers,
    the interior point's multipliers, costates and last barrier parameter). Every tensor is detached.
    ``tt.solve(problem, x1, method=solution.method, **tt.warm_start(solution))``."""
    solver = solvers.get(solution.method)
    duals = solver.carried_duals(None, solution, solver.default_options()) if solver.takes_duals else {}
    duals = map_duals(duals, torch.Tensor.detach)
    return solver.warm_start(solution.U.detach(), duals or None, solution.X.detach())
