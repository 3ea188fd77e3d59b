r"""The crossover's rounds over the batch: which instances try it, on which rows, and which candidates are kept.

For linear-quadratic problems (``IPOptions.crossover``; the Newton pieces are :mod:`torchtraj.solvers.ipm.crossover`):
once an instance's ``E_0 ≤ crossover_from``, the rows with ``z > s`` are held as equalities and one Riccati solve
gives the KKT point of that set exactly; it ends the instance where it passes the convergence test, else up to
``crossover_rounds`` primal-dual active-set updates are tried. Where every row is a control bound, up to
``crossover_start_rounds`` sets are tried before the first iteration, from the unconstrained optimum. On the
bench's box-constrained linear system (B = 256) every instance ends there, after 3.8 rounds on average (at most
6), at its KKT point to round-off (``|U − U*| ≤ 4e-10`` against ``1e-5`` at the tolerance), in less than half the
time of the iterations alone.

Two drivers give the same answers: :func:`cross_over` gathers the instances still going at every round (eager),
:func:`_cross_over_masked` keeps the batch's shapes and masks the rows it is done with, so that CUDA graphs
replay one graph per kernel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import fields
from typing import Optional

import torch
from torch import Tensor

from ...core.batching import param_rows
from ...core.constraints import Constraints
from ...core.masks import where_rows
from ...core.problem import Problem
from . import crossover
from .compaction import gather_rows, pick
from .expansion import VALUE_FIELDS, Base, expand, kkt_error, with_values
from .iterate import Iterate, Model
from .kernels import kernel_of, uses_graphs
from .options import IPOptions


def cross_over(problem: Problem, cons: Constraints, params, model: Model, it: Iterate, x0: Tensor,
               base: Optional[Base], opts: IPOptions, tol: float, error: Tensor, K: Tensor, trying: Tensor,
               rounds: int, start: bool = False) -> tuple:
    """The crossover (:mod:`torchtraj.solvers.ipm.crossover`) of the instances ``trying``, gathered: up to ``rounds``
    active sets, the first proposed by the iterate (``start``: none held, the unconstrained optimum), each next one the
    primal-dual active-set update of the last candidate. An instance's rounds end where its set stops changing (the
    candidate is then the KKT point of its set), where its system fails, or with the last round; the candidates
    they end with are then checked together, and accepted where they pass the convergence test ``E_0 ≤ tol``.
    Returns ``(iterate, model, E_0, gains K, rounds (B,))``: the accepted candidates' values, the given ones
    elsewhere, and the rounds each instance took part in, negative where none was accepted."""
    if uses_graphs(opts, x0.device) and not cons.back_propagated:
        return _cross_over_masked(problem, cons, params, model, it, x0, base, opts, tol, error, K, trying, rounds,
                                  start)
    B = trying.shape[0]
    index = trying.nonzero().squeeze(-1)  # the rows still tried
    whole = index.numel() == B
    sub_model, sub_it = (model, it) if whole else (gather_rows(model, index), gather_rows(it, index))
    sub_x0 = x0 if whole else x0[index]
    knots = model.knots
    active = crossover.first_active_set(sub_it, knots, start)
    taken = torch.zeros(B, dtype=torch.long, device=index.device)
    ended = []  # per round: the rows it ended, their candidates' iterates, gains and factorisations' success
    for r in range(rounds):
        c = crossover.candidate(sub_model, cons, sub_it, sub_x0, active)
        taken = taken.index_add(0, index, torch.ones_like(index))
        following = crossover.next_active_set(c, active, knots)
        going = c.ok & crossover.changed(active, following)
        if r == rounds - 1:
            going = torch.zeros_like(going)
        rows = (~going).nonzero().squeeze(-1)
        ended.append((index[rows], gather_rows(c.point, rows), c.K[rows], c.ok[rows]))
        on = going.nonzero().squeeze(-1)
        if on.numel() == 0:
            break
        index, sub_model, sub_it, sub_x0 = index[on], gather_rows(sub_model, on), gather_rows(sub_it, on), sub_x0[on]
        active = tuple(a[on] for a in following)
    done = torch.cat([e[0] for e in ended])
    new = Iterate(**{f.name: torch.cat([getattr(e[1], f.name) for e in ended]) for f in fields(Iterate)})
    # one expansion checks them all (eager: the gathered batch changes from call to call)
    new_model = expand(problem, cons, param_rows(params, done), new, opts,
                       None if base is None else gather_rows(base, done))
    new_error = kkt_error(new_model)
    accept = torch.cat([e[3] for e in ended]) & new_model.finite & (new_error <= tol)
    rows = accept.nonzero().squeeze(-1)
    done, new = done[rows], gather_rows(new, rows)
    it = Iterate(**{f.name: getattr(it, f.name).index_copy(0, done, getattr(new, f.name)) for f in fields(Iterate)})
    values = {name: getattr(model, name).index_copy(0, done, getattr(new_model, name)[rows]) for name in VALUE_FIELDS}
    accepted = torch.zeros_like(trying).index_fill(0, done, True)
    return (it, dataclasses.replace(model, **values), error.index_copy(0, done, new_error[rows]),
            K.index_copy(0, done, torch.cat([e[2] for e in ended])[rows]), torch.where(accepted, taken, -taken))


def _cross_over_masked(problem: Problem, cons: Constraints, params, model: Model, it: Iterate, x0: Tensor,
                       base: Optional[Base], opts: IPOptions, tol: float, error: Tensor, K: Tensor, trying: Tensor,
                       rounds: int, start: bool) -> tuple:
    """:func:`cross_over` on the whole batch, for CUDA graphs: the rows not tried, or whose rounds have ended, are
    masked instead of gathered, so that every round's candidate, and the expansion that checks them, keep the
    batch's shapes and replay one graph each. Each row keeps the candidate its rounds ended with. Where the held
    rows are control bounds alone (general rows take the core's SVD, which cannot be captured)."""
    knots = model.knots
    active = crossover.first_active_set(it, knots, start)
    candidate = kernel_of(crossover.candidate, opts, x0.device)
    going, taken, ended = trying, torch.zeros_like(trying, dtype=torch.long), None
    for r in range(rounds):
        c = candidate(model, cons, it, x0, active)
        ended = c if ended is None else crossover.Candidate(
            point=pick(going, c.point, ended.point), K=where_rows(going, c.K, ended.K),
            ok=torch.where(going, c.ok, ended.ok))
        taken = taken + going.long()
        following = crossover.next_active_set(c, active, knots)
        going = going & c.ok & crossover.changed(active, following)
        if r == rounds - 1 or not bool(going.any()):
            break
        active = following  # the rows no longer going ignore theirs
    new_model = kernel_of(expand, opts, x0.device)(problem, cons, params, ended.point, opts, base)
    new_error = kkt_error(new_model)
    accept = trying & ended.ok & new_model.finite & (new_error <= tol)
    return (pick(accept, ended.point, it), with_values(accept, new_model, model), torch.where(accept, new_error, error),
            where_rows(accept, ended.K, K), torch.where(accept, taken, -taken))
