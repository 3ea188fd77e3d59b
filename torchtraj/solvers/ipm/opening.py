r"""The start of an interior-point iteration (:func:`~torchtraj.solvers.ipm.solver.run`, steps 1 and 2): the
expansion at the iterate, the tests that end an instance, and the barrier update of those still running.

At the iterate ``w`` the expansion (:func:`~torchtraj.solvers.ipm.expansion.expand`) gives the model and the
scaled errors of the optimality conditions; an instance ends ``CONVERGED`` where the largest of them, ``E_0``
(Wächter & Biegler 2006 §2.1, eq. 5), is at most the tolerance (or where the caller's ``leave`` says so: a
restoration phase's return test), ``NON_FINITE`` where the model is not finite, ``MAX_ITERATIONS`` where its budget
is spent (a budget of the caller's, or one a restoration phase used), and ``DIVERGED`` where a state passed
``max_state``. The instances still running then update the barrier parameter
(:func:`~torchtraj.solvers.ipm.barrier.barrier_step`).

With compiled kernels and none of the iteration's other openings (the caller's ``leave`` test, the crossover), all
of it is one kernel call, :func:`opened`; the host then reads how many instances still run, and where the solve
leaves finished instances behind at that read, the barrier update is made again on the rows that stay (its values
for the others are not used). Eager, the same functions run in turn.
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor

from ...core.compiled import batched_options
from ...core.constraints import Constraints
from ...core.problem import Problem
from ...core.status import Status
from ...globalization.filter import Filter
from .barrier import barrier_step
from .expansion import Base, expand, kkt_error
from .iterate import Iterate, Model
from .options import IPOptions


def tested(model: Model, it: Iterate, status: Tensor, running: Tensor, tol: float, params=None,
           leave: Optional[Callable] = None) -> tuple:
    """The KKT error ``E_0 (B,)`` at the model's iterate, and ``status (B,)`` with the ``running (B,)`` instances
    that end there: ``NON_FINITE``, or ``CONVERGED`` where ``E_0 ≤ tol`` or ``leave(params, it, model)``."""
    error = kkt_error(model)
    status = torch.where(running & ~model.finite, int(Status.NON_FINITE), status)
    done = error <= tol if leave is None else (error <= tol) | leave(params, it, model)
    return error, torch.where(running & model.finite & done, int(Status.CONVERGED), status)


def checked(it: Iterate, status: Tensor, running: Tensor, iterations: Tensor, budget: Tensor, budgeted: bool,
            opts: IPOptions) -> Tensor:
    """``status (B,)`` with the ``running (B,)`` instances still ``RUNNING`` that end for their budget (where
    ``budgeted``: ``iterations (B,)`` reached ``budget (B,)``) or diverged (a state above ``max_state``)."""
    if budgeted:
        status = torch.where(running & (iterations >= budget) & (status == int(Status.RUNNING)),
                             int(Status.MAX_ITERATIONS), status)
    diverged = running & (it.X.abs().flatten(1).amax(-1) > opts.max_state)
    return torch.where(diverged & (status == int(Status.RUNNING)), int(Status.DIVERGED), status)


@batched_options(expand.batched_options)  # the expansion's loops are most of this kernel's
def opened(problem: Problem, cons: Constraints, params, it: Iterate, opts: IPOptions, base: Optional[Base],
           status: Tensor, iterations: Tensor, budget: Tensor, budgeted: bool, tol: float, mu: Tensor,
           tiny_steps: Tensor, filt: Filter) -> tuple:
    """:func:`~torchtraj.solvers.ipm.expansion.expand`, :func:`tested`, :func:`checked` and the barrier update of
    the instances still running in one function (a compiled solve's one kernel call). Returns ``(model, E_0,
    status, barrier)``: ``status`` after the tests, ``barrier`` the tuple of
    :func:`~torchtraj.solvers.ipm.barrier.barrier_step` (made with no host read)."""
    model = expand(problem, cons, params, it, opts, base)
    # compared with an int: traced, ``status == Status.RUNNING`` is a Python ``False`` (PyTorch 2.13)
    running = status == int(Status.RUNNING)
    error, status = tested(model, it, status, running, tol)
    status = checked(it, status, running, iterations, budget, budgeted, opts)
    running = status == int(Status.RUNNING)
    return model, error, status, barrier_step(cons, model, it, mu, status, running, tiny_steps, filt, tol, opts,
                                              False)
