r"""ALTRO (method ``"altro"``) and AL-iLQR (method ``"al-ilqr"``: ALTRO without its projection stage) as
:class:`~torchtraj.solvers.base.Solver` objects; the algorithm is :mod:`torchtraj.solvers.altro.solver`.

A control step (:mod:`torchtraj.control.mpc`) with a budget of ``n`` iterations runs one inner AL-iLQR solve of at
most ``n`` iLQR iterations (``iterations_inner = n``, ``iterations_outer = 1``). The multipliers it hands the next
step have had one update by eq. (17) with ``μ = penalty_initial``,

.. math::

    \lambda \leftarrow \Pi_{\mathcal K}\big(\lambda + \mu\, c(x, u)\big),

which ALTRO makes itself unless the instance met its tolerances (``CONVERGED``); :meth:`ALTRO.carried_duals` makes
it for those, so that the multipliers improve by one update per control step.
"""

from __future__ import annotations

import dataclasses

import torch

from ...core.batch import Batch
from ...core.compiled import kernel
from ...core.constraints import Constraints, multiplier_blocks, stack_blocks
from ...core.masks import where_rows
from ...core.problem import Problem
from ...core.solution import Solution
from ...core.status import Status
from ..base import Solver
from .augmented_lagrangian import AugmentedLagrangian, Duals
from .options import ALTROOptions
from .solver import solve_altro

#: ALTRO's settings for MPC: no projection (the applied control is clamped to its bounds anyway, and the projection
#: adds 12 % (median) to 26 % (mean) to a pendulum step at B = 1) and Altro.jl's stopping tolerances
#: (:meth:`ALTROOptions.fast`): a control step is a few warm-started iterations, not a solve to the optimum.
MPC_OPTIONS = ALTROOptions.fast(projection=False)


class ALTRO(Solver):
    """Method ``"altro"``: :func:`~torchtraj.solvers.altro.solver.solve_altro`. ``X0`` switches to the infeasible
    start (§III-B); ``duals`` warm-start the multipliers and penalties."""

    name = "altro"
    options_class = ALTROOptions
    handles_constraints = True
    takes_state_guess = True
    takes_duals = True

    def solve(self, problem: Problem, batch: Batch, options: ALTROOptions) -> Solution:
        return solve_altro(problem, batch, options, method=self.name)

    def step_defaults(self) -> ALTROOptions:
        return MPC_OPTIONS

    def step_options(self, options, iterations, compile=False) -> ALTROOptions:
        """One inner solve of at most ``iterations`` iLQR iterations and no further dual update (module docstring);
        ``compile`` compiles the inner iLQR's kernels."""
        opts = self.options(self.step_defaults() if options is None else options)
        if compile:
            opts = dataclasses.replace(opts, ilqr=dataclasses.replace(opts.ilqr, compile=True))
        if iterations is None:
            return opts
        return dataclasses.replace(opts, iterations_inner=int(iterations), iterations_outer=1)

    # warm_start: the base's. Not the shifted states: ALTRO's X0 means its infeasible start, another problem.

    def carried_duals(self, constraints: Constraints, solution: Solution, options: ALTROOptions) -> dict:
        """``solution.multipliers``, updated once by eq. (17) with ``μ = penalty_initial`` where ALTRO stopped
        without an update (``CONVERGED``: met its tolerances). Else an over-estimated multiplier of a bound that is
        no longer active stays frozen for good: held by it, a pendulum can come to rest 0.64 rad from upright at
        τ = 2.94 under a bound of 3, and every later step converges there again."""
        if not solution.multipliers:
            return {}
        c, mu = constraints, options.penalty_initial
        lam, lamN = stack_blocks(c, solution.multipliers, 0.0, solution.X)
        duals = Duals(lam, lamN, torch.full_like(lam, mu), torch.full_like(lamN, mu))
        params = c.problem.batched_params(solution.batch_size)
        update = kernel(AugmentedLagrangian.updated_duals, options.ilqr.compile)
        new = update(AugmentedLagrangian(c, duals), solution.X, solution.U, params, 1.0, options.penalty_max,
                     options.dual_max)
        updated = multiplier_blocks(c, new.stage, new.terminal)
        # STALLED: ALTRO's own test passed (no update made) at a point the KKT certificate did not accept
        done = (solution.status == Status.CONVERGED) | (solution.status == Status.STALLED)
        return {k: where_rows(done, updated[k], v) for k, v in solution.multipliers.items()}


class ALILQR(ALTRO):
    """Method ``"al-ilqr"``: ALTRO's augmented-Lagrangian stage alone (``projection=False`` whatever the options
    say); otherwise as :class:`ALTRO`."""

    name = "al-ilqr"

    def solve(self, problem: Problem, batch: Batch, options: ALTROOptions) -> Solution:
        return super().solve(problem, batch, dataclasses.replace(options, projection=False))


__all__ = ["ALILQR", "ALTRO", "MPC_OPTIONS"]
