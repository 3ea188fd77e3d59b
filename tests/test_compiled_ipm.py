"""The interior point's compiled kernels (``IPOptions(compile=True)``, torchtraj.core.compiled).

Default run: Dynamo's capture alone (its ``"eager"`` backend, no inductor): each kernel of a solve is one graph (a graph
break splits a kernel into pieces, each with its own call overhead) traced once (the second-order corrections reuse
the kernels of the iteration's step and line search instead of specialisations of their own), and the solve is the
eager one; the instances that need more work run alone with no kernel traced again; a control step's last iterate.
``-m slow``: a later batch size captures no kernel again, in the iterations and in restoration phases; finished
instances left behind; the same solve compiled by inductor, against eager.
"""

import dataclasses

import pytest
import torch
from same_solutions import (
    assert_close_solutions,
    assert_compiled_matches_eager,
    assert_compiled_steps_apply_eager_controls,
    assert_one_graph_per_kernel,
    needs_compiler,
)

import torchtraj as tt
from torchtraj.core import compiled
from torchtraj.core.batching import rollout, rows_of
from torchtraj.kkt import certificate
from torchtraj.riccati import range_space
from torchtraj.solvers.ipm import (
    barrier,
    conclusion,
    expansion,
    line_search,
    newton,
    opening,
    scaling,
    soc,
    whole_iteration,
)
from torchtraj.solvers.ipm import solver as ipm_solver
from torchtraj.solvers.ipm.iterate import Iterate

pytest.importorskip("torch._inductor")


def pendulum():
    return tt.problems.get("pendulum").replace(horizon=30)


def spied(monkeypatch, module, name: str) -> list:
    """``module.name`` replaced by a function that calls it and keeps the arguments of each call in the list
    returned."""
    calls, original = [], getattr(module, name)

    def spy(*args):
        calls.append(args)
        return original(*args)

    monkeypatch.setattr(module, name, spy)
    return calls


def test_each_compiled_kernel_of_the_interior_point_is_one_graph_traced_once(monkeypatch, dynamo_capture):
    eager_factorizations = spied(monkeypatch, soc, "factorize_step")
    corrections = spied(monkeypatch, soc, "second_order_correction")  # of the rows that need one
    x0 = tt.problems.sample_x0("pendulum", 2, seed=0)
    solution = tt.solve(pendulum(), x0, "ipm", options=tt.IPOptions(compile=True))
    frames, kernels = dynamo_capture["frames"]["total"], len(compiled._KERNELS)
    breaks = dict(dynamo_capture["graph_break"])
    assert sum(int(args[12].sum()) for args in corrections) > 0, "the solve should take corrections"
    assert not breaks, breaks
    assert not eager_factorizations, "the corrections' steps should be made in the compiled kernels"
    assert kernels >= 5 and frames == kernels, (frames, kernels)
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "ipm"), tol=1e-9)


def test_compiled_solves_take_the_instances_that_need_more_work_alone(monkeypatch, dynamo_capture):
    """Compiled as eager, the inertia correction's later attempts and the second-order corrections run on the rows
    of the instances that need them (a single one taken twice), laid out as the batch's: no kernel is traced again
    for them, and the answers are eager's."""
    attempts = spied(monkeypatch, ipm_solver, "direction_of_rows")
    corrections = spied(monkeypatch, soc, "second_order_correction")
    x0 = tt.problems.sample_x0("pendulum", 4, seed=0)
    solution = tt.solve(pendulum(), x0, "ipm", options=tt.IPOptions(compile=True))
    sizes = {"attempt": [args[6].numel() for args in attempts],  # the instances attempted again
             "correction": [args[12].shape[0] for args in corrections]}  # the rows of the call
    assert sizes["attempt"] and max(sizes["attempt"]) < 4, sizes
    assert sizes["correction"] and min(sizes["correction"]) < 4, sizes
    frames, kernels = dynamo_capture["frames"]["total"], len(compiled._KERNELS)
    assert frames == kernels, (frames, kernels)
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "ipm"), tol=1e-7)


def test_a_compiled_first_round_of_the_full_step_alone(monkeypatch, dynamo_capture):
    """The first round of the full step alone (``IPOptions.line_search_first``, the default of large compiled
    batches), compiled: one graph each, traced once (the later rounds' trial points, four a round, have the trial
    kernel; the corrections' trial point is in their round's kernel); the answers are eager's."""
    corrections = spied(monkeypatch, soc, "second_order_correction")
    x0 = tt.problems.sample_x0("pendulum", 4, seed=0)
    solution = tt.solve(pendulum(), x0, "ipm", options=tt.IPOptions(compile=True, line_search_first=1))
    assert corrections, "the solve should take corrections"
    assert not dict(dynamo_capture["graph_break"]), dict(dynamo_capture["graph_break"])
    frames, kernels = dynamo_capture["frames"]["total"], len(compiled._KERNELS)
    assert frames == kernels, (frames, kernels)
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "ipm"), tol=1e-9)


def _same(a, b, rtol: float = 0.0) -> bool:
    """Whether two results (dataclasses, tuples, dicts, tensors) hold the same tensors: to the bit (NaN where both
    are), or floating ones within ``rtol`` of each other (relative to the larger of 1 and their entries)."""
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(_same(getattr(a, f.name), getattr(b, f.name), rtol)
                                          for f in dataclasses.fields(a))
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y, rtol) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k], rtol) for k in a)
    if not isinstance(a, torch.Tensor):
        return a == b
    if not a.is_floating_point():
        return torch.equal(a, b)
    if a.shape != b.shape:
        return False
    # NaN where both are (the steps of instances that have stopped are not read)
    near = (a == b) | (a.isnan() & b.isnan())  # (equal: the filters' infinite entries too)
    if rtol > 0.0:
        near = near | ((a - b).abs() <= rtol * torch.maximum(a.abs(), b.abs()).clamp_min(1))
    return bool(near.all())


@pytest.mark.parametrize("corrections", [None, 0])
def test_a_line_search_settled_by_its_first_round_ends_in_its_kernel(monkeypatch, corrections):
    """With compiled kernels the first round's kernel also makes the step and the iteration's end where that round
    settles the search (conclusion.first_round_concluded, line_search.settled_step): every pending instance accepts
    a candidate or takes a tiny step, and none needs a correction. With the kernels as plain functions
    (``torch.compile`` the identity), each such search made again by the backtracking from the same first round,
    and the iteration ended by ``conclude``, as where the round does not settle the search: the same step of the
    pending instances and the same end to the bit (also in the rounds of whole iterations); and the solve takes
    eager's iterations to the same answers. With corrections, some searches are settled so and others not; without
    them, rejected full steps are settled by shorter ones of the first round."""
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    settled, compared, kernel = [], [], ipm_solver.first_round_concluded

    def refuse(*args):
        raise AssertionError("a settled search needs no correction")

    def both(*args):
        first, done, step, concluded = kernel(*args)
        settled.append(bool(done))
        if done:
            problem, cons, params, it, d, model, mu, filt, theta_max, theta_min, factored, corrects, opts, wd, delta, \
                last, tol, restoring, tiny_steps, floor, running, lost, status, iterations = args
            again = line_search.line_search(problem, cons, params, it, d, model, mu, filt, theta_max, theta_min,
                                            factored, opts, refuse if corrects else None, first)
            pending = factored.nonzero().squeeze(-1)  # (the others' step is not taken: conclude reads `take`)
            assert _same(rows_of(step, pending), rows_of(again, pending))
            assert _same(concluded, conclusion.conclude(
                wd, again, d, it, filt, delta, last, factored, torch.zeros_like(factored), model.primal_error, tol,
                opts, True, restoring, tiny_steps, floor, running, lost, status, iterations))
            compared.append((bool(step.shortened.any()), bool(step.filter.slot.sum() > filt.slot.sum())))
        return first, done, step, concluded

    monkeypatch.setattr(ipm_solver, "first_round_concluded", both)
    monkeypatch.setattr(whole_iteration, "first_round_concluded", both)  # (the round of an iteration in one call)
    x0 = tt.problems.sample_x0("pendulum", 4, seed=0)
    options = tt.IPOptions() if corrections is None else tt.IPOptions(second_order_corrections=corrections)
    kernels = tt.solve(pendulum(), x0, "ipm", options=dataclasses.replace(options, compile=True))
    assert any(entered for _, entered in compared), compared
    if corrections is None:  # the iterations that take a correction are not settled by the first round
        assert any(settled) and not all(settled), settled
    else:
        assert any(short for short, _ in compared), compared
    eager = tt.solve(pendulum(), x0, "ipm", options=options)
    assert torch.equal(kernels.iterations, eager.iterations)
    assert_close_solutions(kernels, eager, tol=1e-10)


def test_an_iteration_whose_host_reads_change_nothing_is_one_kernel_call(monkeypatch):
    """With compiled kernels an iteration is one kernel call (whole_iteration.whole_iteration: the start, the Newton
    step of the first attempt, the line search's first round and the end) where no watchdog runs or may start. With
    the kernels as plain functions (``torch.compile`` the identity): most iterations are such calls, some of them go
    on from a part (an unsettled first round: the search goes on from it), and the solve is to the bit the solve
    whose iterations make the three calls in turn; its iterations are eager's."""
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    x0 = tt.problems.sample_x0("pendulum", 4, seed=0)
    options = tt.IPOptions(compile=True)
    calls, settled, whole = [], [], ipm_solver.whole_iteration

    def spy(*args):
        calls.append(args)
        out = whole(*args)
        settled.append(bool(out[1][1][1]))
        return out

    monkeypatch.setattr(ipm_solver, "whole_iteration", spy)
    kernels = tt.solve(pendulum(), x0, "ipm", options=options)
    made = ipm_solver.kernel_on_call
    monkeypatch.setattr(ipm_solver, "kernel_on_call", lambda fn, *args: None if fn is spy else made(fn, *args))
    calls_before = len(calls)
    in_turn = tt.solve(pendulum(), x0, "ipm", options=options)
    assert len(calls) == calls_before, "the iterations should make their calls in turn"
    assert 2 * calls_before > int(kernels.iterations.max()), (calls_before, kernels.iterations)
    assert any(settled) and not all(settled), settled
    assert _same(kernels, in_turn)
    eager = tt.solve(pendulum(), x0, "ipm")
    assert torch.equal(kernels.iterations, eager.iterations)
    assert_close_solutions(kernels, eager, tol=1e-10)


def test_a_round_made_again_after_a_further_attempt_goes_on_where_it_does_not_settle(monkeypatch):
    """Where an iteration in one call (whole_iteration) finds an instance whose first attempt fails, the loop makes
    the inertia correction's further attempts and the line search's first round again, in that round's own call;
    where that round does not settle the search, the search goes on from it. With the kernels as plain functions
    (``torch.compile`` the identity) on the pendulum at its own horizon: such rounds occur, and the solve takes
    eager's iterations to eager's answers. (The thirty-sixth session's loop read that call's results in the whole
    iteration's order, took every such round as settled and ended the iteration with its first round's step: the
    second instance here left eager's path at its 34th iteration, and a compiled batch of 1024 ended 16 % of its
    instances unconverged.)"""
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    unsettled, kernel = [], ipm_solver.first_round_concluded

    def spy(*args):  # the loop's own call (whole_iteration calls its module's name)
        out = kernel(*args)
        unsettled.append(not bool(out[1]))
        return out

    monkeypatch.setattr(ipm_solver, "first_round_concluded", spy)
    problem = tt.problems.get("pendulum")
    x0 = tt.problems.sample_x0("pendulum", 1024, seed=0)[:2]
    kernels = tt.solve(problem, x0, "ipm", options=tt.IPOptions(compile=True))
    assert any(unsettled), "some round made again should leave its search unsettled"
    eager = tt.solve(problem, x0, "ipm")
    assert_close_solutions(kernels, eager, tol=1e-10)


def test_an_iteration_after_a_failed_first_attempt_makes_its_calls_in_turn(monkeypatch):
    """For a batch, the iteration in one call (whole_iteration) comes only after an iteration whose first attempt of
    the inertia correction held for every running instance: where one failed, the next iteration makes its calls in
    turn (in a large batch some instance's first attempt fails in most iterations, and the one call's line-search
    round would be made again). With the kernels as plain functions (``torch.compile`` the identity), on two
    instances whose first attempts fail in some iterations: both kinds of iteration occur, and the solve is eager's.
    A single instance (the pendulum's own start, whose first attempt also fails in some iterations) takes the one
    call after such iterations too."""
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    events, whole, regularized = [], ipm_solver.whole_iteration, ipm_solver.regularized_direction

    def whole_spy(*args):
        events.append("whole")
        return whole(*args)

    def regularized_spy(attempt, floor, *args, **kwargs):
        d, delta = regularized(attempt, floor, *args, **kwargs)
        events.append("held" if delta is floor else "failed")
        return d, delta

    monkeypatch.setattr(ipm_solver, "whole_iteration", whole_spy)
    monkeypatch.setattr(ipm_solver, "regularized_direction", regularized_spy)
    problem = tt.problems.get("pendulum")
    x0 = tt.problems.sample_x0("pendulum", 1024, seed=0)[:2]
    kernels = tt.solve(problem, x0, "ipm", options=tt.IPOptions(compile=True))
    after = [events[i - 1] for i, event in enumerate(events) if event == "whole"]
    assert after and set(after) == {"held"}, after  # (the first iterations have no filter bounds: no call)
    next_to_failed = [b for a, b in zip(events, events[1:]) if a == "failed"]
    assert next_to_failed and "whole" not in next_to_failed, events  # such iterations occur, and go on in turn
    eager = tt.solve(problem, x0, "ipm")
    assert torch.equal(kernels.iterations, eager.iterations)
    assert_close_solutions(kernels, eager, tol=1e-10)
    events.clear()
    tt.solve(problem, None, "ipm", options=tt.IPOptions(compile=True))
    assert "whole" in [b for a, b in zip(events, events[1:]) if a == "failed"], events


def test_the_kernels_that_hold_the_expansion_take_its_batched_options():
    """The expansion's batched graphs are compiled without Inductor's masked tail vectors (``expand``'s
    ``batched_options``); a kernel's options are read off its own function, so the kernels whose graphs hold the
    expansion (the iteration's start, and the iteration in one call) carry them too (from b5b189a to aa588c3 they
    did not, and a batch's iteration start ran at less than half its speed: docs/benchmarks.md)."""
    wanted = expansion.expand.batched_options
    assert wanted.get("cpp.enable_loop_tail_vec") is False, wanted
    for kernel in (opening.opened, whole_iteration.whole_iteration):
        assert getattr(kernel, "batched_options", None) == wanted, kernel


def test_a_compiled_solves_objective_scale_is_one_kernel_with_the_eager_value(dynamo_capture):
    """The objective's scale (W&B §3.8, the cost gradient's largest entry at the start) of a compiled solve is one
    kernel call, one graph with no break, with every bit of the eager value, at starts whose scale is below 1: a
    single instance's graph, and one graph for the batches of 2 and 3 (the scalar costs' gradients are pullbacks of
    ones, which read no concrete batch size)."""
    problem = tt.problems.get("cartpole")  # its cost gradient at the start is above 100: scaled
    options = tt.IPOptions()
    graphs = {}
    for B in (1, 2, 3):
        x0 = problem.x0.expand(1, -1) if B == 1 else tt.problems.sample_x0("cartpole", B, seed=B)
        U = problem.u_init.expand(B, problem.N, -1)
        params = problem.batched_params(B)
        X = rollout(problem.dynamics, x0, U, params)
        eager = scaling.objective_scale(problem, X, U, params, options)
        kernel = scaling.objective_scale(problem, X, U, params, dataclasses.replace(options, compile=True))
        assert bool((eager < 1.0).all()), eager
        assert torch.equal(kernel, eager), (B, kernel, eager)
        graphs[B] = dynamo_capture["stats"]["unique_graphs"]
    assert set(compiled._KERNELS) == {scaling._largest_gradient}
    assert not dict(dynamo_capture["graph_break"]) and graphs == {1: 1, 2: 2, 3: 2}, graphs


def test_the_iterations_start_traced_is_its_eager_expansion_tests_and_barrier_update(monkeypatch):
    """The start of an iteration with compiled kernels, one kernel (opening.opened: the expansion, the tests that end
    an instance, the barrier update), traced by Dynamo on the arguments of a solve's third iteration: the values of
    the functions it calls in turn, eager, to rounding (a traced ``status == Status.RUNNING`` was a Python ``False``,
    which made every instance stop)."""
    trace = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    calls, start = [], ipm_solver.opened

    def spy(*args):
        calls.append(args)
        return start(*args)

    monkeypatch.setattr(ipm_solver, "opened", spy)
    monkeypatch.setattr(whole_iteration, "opened", spy)  # (the start of an iteration in one call)
    tt.solve(pendulum(), tt.problems.sample_x0("pendulum", 2, seed=0), "ipm", options=tt.IPOptions(compile=True))
    problem, cons, params, it, opts, base, status, iterations, budget, budgeted, tol, mu, tiny_steps, filt = calls[3]
    model = expansion.expand(problem, cons, params, it, opts, base)
    running = status == tt.Status.RUNNING
    error, status = opening.tested(model, it, status, running, tol)
    status = opening.checked(it, status, running, iterations, budget, budgeted, opts)
    eager = model, error, status, barrier.barrier_step(cons, model, it, mu, status, status == tt.Status.RUNNING,
                                                       tiny_steps, filt, tol, opts, False)
    assert bool((status == tt.Status.RUNNING).all())
    traced = trace(opening.opened, backend="eager", dynamic=False)(*calls[3])
    assert _same(traced, eager, rtol=1e-12)  # traced, the short products are sums of products (compiled.matmul)


def test_compiled_correction_rounds_take_the_instances_still_correcting_alone(monkeypatch):
    """With compiled kernels each round of the second-order corrections is the step's kernel, which forms the system
    again, and one kernel of the rest (soc.correction_round), on the rows of the instances still correcting alone
    (the first round all of them). On the corrections of three or more instances that an eager solve of 32 made,
    with the kernels as plain functions (``torch.compile`` the identity): the rounds shrink, and the instances, step
    sizes and iterates are those of the eager corrections, which solve with the step's kept factorisation."""
    correct = soc.second_order_correction
    calls = spied(monkeypatch, soc, "second_order_correction")
    tt.solve(pendulum(), tt.problems.sample_x0("pendulum", 32, seed=1), "ipm")
    monkeypatch.setattr(torch, "compile", lambda fn, **kwargs: fn)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    rounds = spied(monkeypatch, soc, "correction_round")
    shrunk = 0
    for args in (list(args) for args in calls if int(args[12].sum()) >= 3):
        assert bool(args[12].all())  # eager, the rows of the instances that need one
        eager = correct(*args)
        args[15], args[-1] = None, dataclasses.replace(args[-1], compile=True)  # no system: the kernels make it
        rounds.clear()
        alone = correct(*args)
        rows = [round_args[3].X.shape[0] for round_args in rounds]  # the instances of each round
        shrunk += rows[-1] < rows[0]
        assert torch.equal(alone.found, eager.found) and torch.equal(alone.unfiltered, eager.unfiltered)
        torch.testing.assert_close(alone.alpha, eager.alpha, atol=1e-12, rtol=0)
        for name in ("X", "U", "s", "z", "lam"):
            torch.testing.assert_close(getattr(alone.it, name)[alone.found], getattr(eager.it, name)[eager.found],
                                       atol=1e-10, rtol=0)
    assert shrunk, "a correction should end for some of its instances before the others"


@pytest.mark.slow  # compiling the kernels takes minutes on two cores
@needs_compiler
@pytest.mark.parametrize("first_round", [None, 1])  # 1: the full step alone, as in a large batch
def test_compiled_interior_point_matches_eager(first_round):
    x0 = tt.problems.sample_x0("pendulum", 2, seed=0)
    assert_compiled_matches_eager(pendulum(), x0, "ipm", tt.IPOptions(line_search_first=first_round), tol=1e-7)


@pytest.mark.slow  # most of a minute; the default run keeps the test above (its rows of fewer instances traced once)
def test_one_capture_of_each_kernel_serves_every_batch_size(dynamo_capture):
    """The batch dimension is dynamic in every kernel of the interior point: a batch of 3 after one of 2 captures no
    graph (the constraint rows and the expansion's derivatives are written so that ``vmap`` reads no concrete batch
    size, :func:`torchtraj.core.batching.concat` and :mod:`torchtraj.core.one_pass`), with the eager answers; but
    for the first graph of a kernel that the batch of 2 did not call (the barrier update alone, where the batch of 3
    leaves finished instances behind)."""
    graphs, first = {}, {}
    for B in (2, 3):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        before, known = dynamo_capture["stats"]["unique_graphs"], set(compiled._KERNELS)
        solution = tt.solve(pendulum(), x0, "ipm", options=tt.IPOptions(compile=True))
        graphs[B], first[B] = dynamo_capture["stats"]["unique_graphs"] - before, set(compiled._KERNELS) - known
        # traced, the expansion's derivatives are pullbacks of the mapped functions, not jacrev inside vmap: the
        # same derivatives, rounded otherwise (the states agree to 2e-9 where the tolerance is 1e-8)
        assert_close_solutions(solution, tt.solve(pendulum(), x0, "ipm"), tol=1e-7)
    assert graphs[2] >= 5 and graphs[3] == len(first[3]), (graphs, first)


@pytest.mark.slow  # two batches of restoration phases captured, a minute and a half
def test_a_restoration_phase_captures_its_kernels_once_for_every_batch_size(dynamo_capture):
    """The restoration problem's functions read no concrete batch size when traced (its dynamics join the clock to
    the states by :func:`torchtraj.core.batching.concat`): with the pendulum's goal out of reach in 10 stages every
    instance goes through a restoration phase, and a batch of 5 after one of 4 captures no graph, with the eager
    answers. With ``torch.cat`` each new batch size captured three kernels again, and a batch of 1024, whose
    restoration phases see many batch sizes, reached Dynamo's limit of specialisations. (Not 2 and 3: at B = 2 the
    line search's trial kernel keeps a guard on a coincidence of two sizes, ``d.dX.stride(1) == 2 * len(alphas)``.)"""
    problem = tt.problems.get("pendulum").replace(horizon=10)
    graphs = {}
    for B in (4, 5):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        before = dynamo_capture["stats"]["unique_graphs"]
        solution = tt.solve(problem, x0, "ipm", options=tt.IPOptions(compile=True))
        graphs[B] = dynamo_capture["stats"]["unique_graphs"] - before
        assert bool((solution.status == tt.Status.LOCALLY_INFEASIBLE).all()), solution.status  # restoration's verdict
        # the same iterations; the points, minimisers of the violation and flat there, agree to 4e-8
        assert_close_solutions(solution, tt.solve(problem, x0, "ipm"), tol=1e-6)
    assert graphs[4] >= 5 and graphs[5] == 0, graphs


@pytest.mark.slow  # Dynamo traces for half a minute; the default run keeps the first two tests
def test_compiled_solves_leave_finished_instances_behind(monkeypatch, dynamo_capture):
    """With a dynamic batch dimension the compiled kernels iterate the running instances alone
    (``IPOptions.compact_below``), down to two of them, with the eager answers; the rows they keep are laid out as
    the batch's, so that no kernel is traced again for them."""
    sizes = []
    mark = compiled.mark_batch

    def seen(*args):
        sizes.append(next((int(arg.X.shape[0]) for arg in args[0] if isinstance(arg, Iterate)), None))
        return mark(*args)

    monkeypatch.setattr(compiled, "mark_batch", seen)
    x0 = tt.problems.sample_x0("pendulum", 8, seed=1)
    solution = tt.solve(pendulum(), x0, "ipm", options=tt.IPOptions(compile=True))
    batches = {s for s in sizes if s is not None}
    assert max(batches) == 8 and 2 <= min(batches) < 8, batches  # never one: B = 1 has graphs of its own
    frames, kernels = dynamo_capture["frames"]["total"], len(compiled._KERNELS)
    assert frames == kernels, (frames, kernels)
    assert_close_solutions(solution, tt.solve(pendulum(), x0, "ipm"), tol=1e-7)


def test_a_control_steps_untested_last_iterate_is_a_kernel_of_its_own(dynamo_capture):
    """The control steps' options (``IPM.step_defaults``: the last iterate untested) compiled: its values are one
    more kernel, one graph with no break, and each step applies the eager controller's control."""
    short = pendulum().replace(horizon=10)  # the capture unrolls the stages: a short horizon
    assert_compiled_steps_apply_eager_controls(short, tt.problems.sample_x0("pendulum", 2, seed=0), "ipm")
    assert_one_graph_per_kernel(dynamo_capture, {
        opening.opened, expansion.last_values, conclusion.first_round_concluded, newton.newton_direction,
        range_space.formed, rollout, whole_iteration.whole_iteration, certificate._residuals,
        scaling._largest_gradient})
