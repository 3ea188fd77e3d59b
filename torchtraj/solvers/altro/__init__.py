r"""ALTRO (method ``"altro"``) and AL-iLQR (method ``"al-ilqr"``: ALTRO without its projection stage) as
:class:`~torchtraj.solvers.base.Solver` objects; the algorithm is :mod:`torchtraj.solvers.altro.solver`.

A control step (:mod:`torchtraj.control.mpc`) with a budget of ``n`` iterations runs one inner AL-iLQR solve of at
most ``n`` iLQR iterations (``iterations_inner = n``, ``iterations_outer = 1``). The multipliers it hands the next
step have had one update by eq. (17) with ``μ = penalty_initial``,

.. math::

    \lambda \leftarrow \Pi_{\mathcal K}\big(\lambda + \mu\, c(x, u)\big),

which ALTRO makes itself where the inner solve ended short of its tolerances, and which is the multiplier estimate
it reports where it met them (:func:`~torchtraj.solvers.altro.stages.finish`): either way the multipliers improve by
one update per control step. Without that update an over-estimated multiplier of a bound that is no longer active
stays frozen for good: held by it, a pendulum can come to rest 0.64 rad from upright at τ = 2.94 under a bound of
3, and every later step converges there again.
"""

from __future__ import annotations

import dataclasses

from ...core.batch import Batch
from ...core.problem import Problem
from ...core.solution import Solution
from ..base import Solver
from .options import ALTROOptions
from .solver import solve_altro

#: ALTRO's settings for MPC: no projection (the applied control is clamped to its bounds anyway, and the projection
#: adds 12 % (median) to 26 % (mean) to a pendulum step at B = 1) and Altro.jl's stopping tolerances
#: (:meth:`ALTROOptions.fast`): a control step is a few warm-started iterations, not a solve to the optimum. The
#: expansion is replayed from its recorded graph (``ILQROptions.record``), on the whole batch (``compact_below=0``):
#: a controller's steps then repeat the same shapes, where the running instances' count varies from step to step.
MPC_OPTIONS = ALTROOptions.fast(projection=False, problem_state_guess=False)
MPC_OPTIONS = dataclasses.replace(MPC_OPTIONS, ilqr=dataclasses.replace(MPC_OPTIONS.ilqr, record=True,
                                                                        compact_below=0.0))


class ALTRO(Solver):
    """Method ``"altro"``: :func:`~torchtraj.solvers.altro.solver.solve_altro`. ``X0``, or without one the problem's
    ``X_init``, switches to the infeasible start (§III-B); ``duals`` warm-start the multipliers and penalties."""

    name = "altro"
    options_class = ALTROOptions
    handles_constraints = True
    records = True
    compiles = True
    takes_state_guess = True
    takes_duals = True
    dual_entries = ("multipliers", "penalties", "costate")

    def solve(self, problem: Problem, batch: Batch, options: ALTROOptions) -> Solution:
        return solve_altro(problem, batch, options, method=self.name)

    def step_defaults(self) -> ALTROOptions:
        return MPC_OPTIONS

    def kernel_options(self, options: ALTROOptions):
        return options.ilqr

    def with_kernels(self, options: ALTROOptions, **fields) -> ALTROOptions:
        return dataclasses.replace(options, ilqr=dataclasses.replace(options.ilqr, **fields))

    def step_options(self, options, iterations, compile=False) -> ALTROOptions:
        """One inner solve of at most ``iterations`` iLQR iterations and no further dual update (module docstring);
        ``compile`` compiles the inner iLQR's kernels."""
        opts = self.options(self.step_defaults() if options is None else options)
        # a control step starts from the shifted controls of the last one, never from the problem's cold guess
        opts = dataclasses.replace(opts, problem_state_guess=False)
        if compile:
            opts = self.with_kernels(opts, compile=True)
        if iterations is None:
            return opts
        return dataclasses.replace(opts, iterations_inner=int(iterations), iterations_outer=1)

    # warm_start: the base's. Not the shifted states: ALTRO's X0 means its infeasible start, another problem.


class ALILQR(ALTRO):
    """Method ``"al-ilqr"``: ALTRO's augmented-Lagrangian stage alone (``projection=False`` whatever the options
    say); otherwise as :class:`ALTRO`."""

    name = "al-ilqr"

    def solve(self, problem: Problem, batch: Batch, options: ALTROOptions) -> Solution:
        return super().solve(problem, batch, dataclasses.replace(options, projection=False))


__all__ = ["ALILQR", "ALTRO", "MPC_OPTIONS"]
