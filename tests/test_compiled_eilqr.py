"""eILQR's compiled kernels (``EILQROptions(compile=True)``, torchtraj.core.compiled).

Default run: Dynamo's capture alone (its ``"eager"`` backend, no inductor): each kernel of a solve (the expansion with
its tests, the Newton step with the merit's weight, the step's bound and the first trial point, and each of these
alone where the inertia correction attempts a step again, the second-order correction with its merit and the choice
of a step, and each of these alone where some instances are corrected, the move with its bookkeeping, the next
expansion and the next Newton step with its first trial point, the initial rollout, the answer's cost and
violation) is one graph with no break, and the solve is the eager one; which guard sources count as library globals.
``-m slow``: a later batch size captures none of them again; kernels captured for one problem are captured again for
another, and a later trial's kernel is one graph; the control steps' untested last iterate; no guards on library
globals but on a user's module constant; the solve compiled by inductor against eager.
"""

import dataclasses

import pytest
from same_solutions import (
    assert_close_solutions,
    assert_compiled_matches_eager,
    assert_compiled_steps_apply_eager_controls,
    assert_one_graph_per_kernel,
    needs_compiler,
)

import torchtraj as tt
from torchtraj.core import compiled
from torchtraj.core.batching import rollout
from torchtraj.kkt import certificate
from torchtraj.kkt import merit as answer
from torchtraj.solvers.eilqr import globalization, merit, model, newton, verdicts

pytest.importorskip("torch._inductor")


def pendulum():
    return tt.problems.get("pendulum").replace(horizon=30)


def test_each_compiled_kernel_of_eilqr_is_one_graph(dynamo_capture):
    x0 = tt.problems.sample_x0("pendulum", 2, seed=2)
    solution = tt.solve(pendulum(), x0, "eilqr", options=tt.EILQROptions(compile=True))
    # the corrections ran in their kernel, not eager
    assert_one_graph_per_kernel(dynamo_capture, {
        verdicts.expanded, newton.direction_alone, merit.merit_at, globalization.corrected_step, rollout,
        globalization.first_tried, globalization.direction_and_first_trial, globalization.chosen_step,
        verdicts.advanced, verdicts.advanced_ahead, answer.cost_and_violation, certificate._residuals})
    assert bool((solution.status == tt.Status.CONVERGED).all())
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "eilqr"), tol=1e-9, costate_rtol=1e-9)


@pytest.mark.slow  # two problems captured, two minutes
def test_the_kernels_compile_again_for_another_problem_and_a_later_trial_is_one_graph(dynamo_capture):
    """Kernels compiled for the car (its parameters hold obstacles) serve the cart-pole after it, compiled again
    (Dynamo's reason for compiling again once failed on a kernel given one tensor twice), and with two corrected
    trials the second one's kernel (the cart-pole's) is one graph too; the answers are the eager ones.

    Neither goal is in reach in so few stages (the IPM ends both problems' instances locally infeasible): eILQR's
    solves end stalled or at the most regularisation after 45 to 77 iterations, by which the captured graphs'
    round-off has moved them apart (the car: 76 iterations against 77; the cart-pole: controls 1.9e-9 apart). So the
    solves stop after 20 iterations, which capture every kernel, the cart-pole's second trial among them."""
    opts = tt.EILQROptions(second_order_trials=2, iterations=20)
    for name in ("car_3obs", "cartpole"):
        problem = tt.problems.get(name).replace(horizon=8 if name == "car_3obs" else 10)
        x0 = tt.problems.sample_x0(name, 2, seed=2)
        solution = tt.solve(problem, x0, "eilqr", options=dataclasses.replace(opts, compile=True))
        assert_close_solutions(solution, tt.solve(problem, x0, "eilqr", options=opts), tol=1e-9, costate_rtol=1e-9)
    assert globalization.tried in compiled._KERNELS
    assert not dict(dynamo_capture["graph_break"]), dict(dynamo_capture["graph_break"])


@pytest.mark.slow  # Dynamo traces for a minute; the default run keeps the interior point's control steps
def test_a_control_steps_untested_last_iterate_is_a_kernel_of_its_own(dynamo_capture):
    """The control steps' options (``EILQR.step_defaults``: the last iterate untested) compiled: the barrier
    multipliers of that iterate are one more kernel, one graph with no break, and each step applies the eager
    controller's control."""
    short = pendulum().replace(horizon=10)  # the capture unrolls the stages: a short horizon
    assert_compiled_steps_apply_eager_controls(short, tt.problems.sample_x0("pendulum", 2, seed=2), "eilqr")
    assert_one_graph_per_kernel(dynamo_capture, {
        verdicts.expanded, model.last_multipliers, newton.direction_alone, merit.merit_at,
        globalization.corrected_choice, globalization.direction_and_first_trial, verdicts.advanced,
        verdicts.advanced_ahead, rollout, answer.cost_and_violation, certificate._residuals})


@pytest.mark.slow  # two batch sizes captured, a minute; the default run keeps the test above
def test_a_later_batch_size_captures_no_kernel_again(dynamo_capture):
    """The batch dimension is dynamic in every kernel: after a batch of 3 (whose corrections and attempts on a
    subset of the instances see subsets of one and of two), a batch of 4 captures no graph, with the eager answers."""
    graphs = {}
    for B in (3, 4):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        before = dynamo_capture["stats"]["unique_graphs"]
        solution = tt.solve(pendulum(), x0, "eilqr", options=tt.EILQROptions(compile=True))
        graphs[B] = dynamo_capture["stats"]["unique_graphs"] - before
        assert_close_solutions(solution, tt.solve(pendulum(), x0, "eilqr"), tol=1e-9, costate_rtol=1e-9)
    assert graphs[3] >= 5 and graphs[4] == 0, graphs


@pytest.mark.slow  # compiling the kernels takes minutes on two cores
@needs_compiler
def test_compiled_eilqr_matches_eager():
    x0 = tt.problems.sample_x0("pendulum", 2, seed=2)
    assert_compiled_matches_eager(pendulum(), x0, "eilqr", tt.EILQROptions(), tol=1e-7, costate_rtol=1e-7)


#: a constant of this module that a test problem's cost reads (a user's module global)
SCALE = 1.0


@pytest.mark.slow  # two captures, a minute and more; the default run keeps the guard filter's unit tests
def test_library_globals_are_not_guarded_but_a_user_modules_constant_is(dynamo_capture, monkeypatch):
    """The kernels keep no guards on torch's and torchtraj's globals (``compiled.kept_guards``: their checks are a
    share of a call at B = 1), but a constant of another module that a problem's cost reads stays guarded: changed,
    the kernels compile again and the solve is the eager one of the new value."""
    import sys

    from torch._dynamo.eval_frame import _debug_get_cache_entry_list

    base = pendulum().replace(horizon=10, terminal_eq=None)  # a short horizon: its goal as a cost alone
    problem = base.replace(stage_cost=lambda x, u, p: base.stage_cost(x, u, p) + SCALE * (u ** 2).sum())
    x0 = tt.problems.sample_x0("pendulum", 2, seed=2)
    options = tt.EILQROptions(compile=True)
    first = tt.solve(problem, x0, "eilqr", options=options)
    guards = "".join(str(entry.guard_manager) for fn in compiled._KERNELS
                     for entry in _debug_get_cache_entry_list(fn.__code__))
    assert "G['__import_torchtraj_dot_" not in guards and "G['__import_torch_dot_" not in guards
    assert f"G['__import_{__name__.replace('.', '_dot_')}']" in guards  # SCALE's module
    monkeypatch.setattr(sys.modules[__name__], "SCALE", 3.0)
    second = tt.solve(problem, x0, "eilqr", options=options)
    assert_close_solutions(second, tt.solve(problem, x0, "eilqr"), tol=1e-9, costate_rtol=1e-9)
    assert bool((second.status == tt.Status.CONVERGED).all())
    assert (second.U - first.U).abs().max() > 1e-2  # the new weight moved the answer


def test_a_guard_source_is_a_library_global_by_its_module():
    assert compiled.library_global("G['__import_torchtraj_dot_core_dot_batching'].rollout.__code__")
    assert compiled.library_global("G['__import_torch_dot_nn_dot_functional'].relu")
    assert compiled.library_global("list(dict.keys(G['__builtins_dict___6']))")
    assert compiled.library_global("G['Iterate']")  # a global of the kernel's own module
    assert not compiled.library_global("G['__import___main__'].GAIN")
    assert not compiled.library_global("G['__import_math'].pi")
    assert not compiled.library_global("L['cons'].problem.dynamics.__code__")
