r"""The states an interior-point solve starts from (multiple shooting starts from any guess: its defects are
constraints like the others).

The caller's ``X0``; else the problem's own state guess ``Problem.X_init`` for the instances that start from the
problem's own controls ``u_init``; else the rollout of the controls ``U0``.
"""

from __future__ import annotations

import torch

from ...core.batch import Batch
from ...core.batching import rollout
from ...core.compiled import rollout_kernel
from ...core.masks import where_rows
from ...core.problem import Problem
from .options import IPOptions


def state_guess(problem: Problem, batch: Batch):
    """The states a solve starts from: the caller's ``X0``; else, where the problem has a state guess
    ``X_init``, that guess for the instances that start from the problem's own controls ``u_init`` (the two go
    together: a control step's shifted controls go with their rollout, not with the problem's waypoints) and the
    rollout of ``U0`` for the others; else ``None`` (the rollout of ``U0``)."""
    if batch.X0 is not None or problem.X_init is None:
        return batch.X0
    own = (batch.U0 == problem.u_init.to(batch.U0)).flatten(1).all(-1)
    guess = problem.X_init.to(batch.x0).expand(batch.B, *problem.X_init.shape)
    if bool(own.all()):
        return guess
    if not bool(own.any()):
        return None
    return where_rows(own, guess, rollout(problem.dynamics, batch.x0, batch.U0, batch.params))


def start_states(problem: Problem, batch: Batch, opts: IPOptions) -> torch.Tensor:
    """The states ``(B, N+1, nx)`` a solve starts from: :func:`state_guess`, else the rollout of ``U0``."""
    X0 = state_guess(problem, batch)
    if X0 is None:
        X0 = rollout_kernel(opts.compile)(problem.dynamics, batch.x0, batch.U0, batch.params)
    return X0
