r"""ALTRO for batches of constrained problems (Howell et al. 2019, Algorithm 4).

1. **AL-iLQR** (§II-A, Algorithm 1): iLQR on the augmented Lagrangian
   (:mod:`torchtraj.solvers.altro.augmented_lagrangian`) for fixed multipliers ``λ`` and penalties ``μ``; when an
   instance's inner solve converges (or reaches ``iterations_inner``), and its largest violation is still
   above ``constraint_tolerance``, its duals are updated by eqs. (17)-(18) and the inner solve goes on.
   The outer and inner loops are flattened into one batched loop: every instance takes one iLQR
   iteration per pass and is at its own place in its own outer loop, so a fast instance never waits for
   a slow one's inner solve; instances that finished are frozen by masks.
2. **Projection** (§III-D, :mod:`torchtraj.solvers.altro.projection`) of the coarse solution onto the active
   constraints to ``projection.tolerance`` (1e-8, or ten rounding errors of the trajectory where that is larger:
   float32 resolves defects of 6e-8 on states of order one). It also takes the instances whose inner solve converged
   but which spent ``iterations_outer`` dual updates above ``constraint_tolerance``: at large penalties
   iLQR's steps on the ill-conditioned augmented Lagrangian barely move the last violations, which is the
   case the projection's Newton steps are made for (a minimum-time parallel park stalls at 2e-5). Such
   an instance is ``CONVERGED`` if the projection meets its tolerance, ``MAX_ITERATIONS`` otherwise.

In float32 every tolerance is met at the dtype's resolution, the penalty is capped where its product with the
rounding of the constraints would spoil the multipliers, and AL-iLQR's multipliers are the least-squares ones of the
held rows (:func:`~torchtraj.solvers.altro.stages.finish`); the inner iLQR takes steps below the cost's resolution
(:mod:`torchtraj.iterations.ilqr`).

**The start.** From an ``X0``, or, without one, from the problem's own state guess ``Problem.X_init`` where it
carries one (``problem_state_guess``), ALTRO takes its infeasible start (§III-B): the states of the guess, held by
slack controls that the AL stage drives to zero. A problem that carries a state guess says where its trajectory
should go, and the paper's infeasible start is the way ALTRO follows such a guess: the rollout of the control guess
alone can lead elsewhere (``car_escape``: a car in a room, its exit through a gap in the walls; from the rollout
of its controls AL-iLQR stays in the first room or cuts through a wall). HM-iLQR starts from ``X_init`` likewise.
The start alone did not make ``car_escape`` converge: with Altro.jl's slack cost 1 it ended ``MAX_REGULARIZATION``
after 2519 iterations from its ``X_init`` (2302 from the rollout); with the default slack cost 0.1 (the ALTRO
sources' value for it; :attr:`ALTROOptions.slack_cost` says why) it converges in 234. Without a state guess, the
start is the rollout of ``U0``. A control step (MPC) never takes ``X_init``: it
starts from the previous step's shifted controls, and ``X_init`` belongs to the problem's own ``x0``.

Infeasible state initialisation (§III-B) and time penalties (§III-C) are transforms of the problem
(:mod:`torchtraj.solvers.altro.infeasible`, :mod:`torchtraj.time_penalty`); the square-root backward pass (§III-A)
is :func:`torchtraj.riccati.square_root.factorize_sqrt`, chosen by ``square_root=True``.
"""

from __future__ import annotations

from typing import Optional

from torch import Tensor

from ...core.batch import Batch
from ...core.compiled import rollout_kernel
from ...core.problem import Problem
from ...core.solution import Solution
from .infeasible import solve_infeasible
from .options import ALTROOptions
from .stages import al_stage, finish


def solve_altro(problem: Problem, batch: Batch, options: Optional[ALTROOptions] = None,
                method: str = "altro") -> Solution:
    """Solve the ``batch`` of instances of ``problem`` by ALTRO: from ``x0 (B, nx)``, ``U0 (B, N, nu)`` (and, for an
    infeasible start, states ``X0 (B, N+1, nx)``, else the problem's ``X_init`` where it has one and
    ``problem_state_guess`` is on), with the parameters batched to B and ``duals`` an optional warm start of the
    multipliers and penalties (see :func:`torchtraj.solve`)."""
    opts = options or ALTROOptions()
    x0, U0, X0, params, duals = batch.x0, batch.U0, batch.X0, batch.params, batch.duals
    if X0 is None and opts.problem_state_guess and problem.X_init is not None:
        X0 = problem.X_init.expand(batch.B, *problem.X_init.shape)
    if X0 is not None:
        return solve_infeasible(problem, x0, U0, X0, params, opts, method, duals)
    X = rollout_kernel(opts.ilqr.compile)(problem.dynamics, x0, U0, params, opts.ilqr.record)
    return run_altro(problem, x0, X, U0, params, opts, method, duals)


def run_altro(problem: Problem, x0: Tensor, X: Tensor, U: Tensor, params, opts: ALTROOptions,
              method: str, duals: Optional[dict] = None) -> Solution:
    """The AL stage from a dynamically consistent ``(X, U)`` of ``problem``, then the projection."""
    stage = al_stage(problem, x0, X, U, params, opts, method, duals)
    return finish(stage, x0, params, opts, method)
