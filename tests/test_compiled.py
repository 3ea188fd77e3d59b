"""``compile=True`` (torchtraj.core.compiled): the same solver logic on torch.compile'd kernels gives the eager answers.

Default run: Dynamo's capture of ALTRO's kernels at two batch sizes, the options each kind of graph gets, the batch
marks and a long rollout's pieces. ``-m slow``: inductor's kernels against eager (ALTRO to convergence with its
projection, the MPC policy's warm-started ALTRO steps, a float32 ALTRO solve with a failing instance, iLQR at two
batch sizes). Each first call compiles its kernels (about a minute on two cores), so the problems are short. The
batch dimension is compiled dynamic: a second batch size compiles nothing new for iLQR
(``test_one_compilation_serves_every_batch_size``, inductor) nor for ALTRO (Dynamo's capture alone, the
``dynamo_capture`` fixture: seconds; ALTRO's projection with ``-m slow``), compiled iterations run on the running
instances' rows, and ``mark_batch`` marks the batch's tensors alone.
"""

import contextlib
import dataclasses
import shutil

import pytest
import torch

import torchtraj as tt
from torchtraj import envs
from torchtraj.core.compiled import batch_of, mark_batch
from torchtraj.core.constraints import Constraints
from torchtraj.solvers.altro.augmented_lagrangian import AugmentedLagrangian, Duals

pytest.importorskip("torch._inductor")
pytestmark = pytest.mark.skipif(not any(shutil.which(c) for c in ("g++", "c++", "clang++")),
                                reason="torch.compile's CPU backend needs a C++ compiler")


def small_pendulum(horizon=8):
    return tt.problems.get("pendulum").replace(horizon=horizon, u_init=torch.zeros(1, dtype=torch.float64),
                                               terminal_eq=None)


def assert_same_solution(a: tt.Solution, b: tt.Solution, tol=1e-9):
    assert torch.equal(a.status, b.status)
    assert torch.equal(a.iterations, b.iterations)
    torch.testing.assert_close(a.U, b.U, atol=tol, rtol=0)
    torch.testing.assert_close(a.X, b.X, atol=tol, rtol=0)
    torch.testing.assert_close(a.cost, b.cost, atol=tol, rtol=0)
    torch.testing.assert_close(a.K, b.K, atol=1e-7, rtol=0)


@pytest.mark.slow
def test_compiled_altro_matches_eager_on_a_constrained_problem():
    problem = small_pendulum()
    x0 = tt.problems.sample_x0("pendulum", 3, seed=1)
    opts = tt.ALTROOptions(iterations_inner=40, iterations_outer=6)
    eager = tt.solve(problem, x0, "altro", options=opts)
    compiled = tt.solve(problem, x0, "altro",
                        options=dataclasses.replace(opts, ilqr=tt.ILQROptions(compile=True)))
    assert bool((eager.U.abs() > 3.0 - 1e-6).any()), "the torque bound should be active somewhere"
    assert_same_solution(eager, compiled)


@pytest.mark.slow  # compiling the kernels takes minutes on two cores
def test_compiled_mpc_steps_match_eager():
    env = envs.PendulumEnv()
    problem = env.problem(horizon=5)
    eager, compiled = tt.MPC(problem, "altro", iterations=2), tt.MPC(problem, "altro", iterations=2, compile=True)
    assert compiled.options.ilqr.compile and not eager.options.ilqr.compile
    x = torch.tensor([[0.3, 2.0], [3.0, 0.2]], dtype=torch.float64)
    for _ in range(3):
        u_eager, u_compiled = eager(x), compiled(x)
        torch.testing.assert_close(u_compiled, u_eager, atol=1e-9, rtol=0)
        x = torch.func.vmap(lambda s, a: problem.dynamics(s, a, problem.params))(x, u_eager)


@pytest.mark.slow  # compiling the kernels takes minutes on two cores
def test_compiled_float32_altro_matches_eager_and_isolates_a_failing_instance():
    # float32 batches shorter than a vector register once met an inductor miscompile of argmax (core.masks.first_true)
    problem = tt.problems.get("pendulum", dtype=torch.float32).replace(
        horizon=8, u_init=torch.zeros(1, dtype=torch.float32), terminal_eq=None)
    x0 = tt.problems.sample_x0("pendulum", 3, seed=1).float()
    x0[1] = float("nan")
    opts = tt.ALTROOptions(iterations_inner=40, iterations_outer=6)
    eager = tt.solve(problem, x0, "altro", options=opts)
    compiled = tt.solve(problem, x0, "altro", options=dataclasses.replace(opts, ilqr=tt.ILQROptions(compile=True)))
    assert compiled.U.dtype == torch.float32
    # not the iteration counts: in float32 the last steps of this short solve meet the tolerances by a few units of
    # round-off, and inductor's fused arithmetic rounds otherwise than the eager library calls
    assert int(compiled.status[1]) == int(eager.status[1]) == int(tt.Status.NON_FINITE)
    assert int(compiled.iterations[1]) == int(eager.iterations[1]) == 0
    keep = torch.tensor([0, 2])
    # the controls to what float32 determines on the pendulum's flattest directions (as in the contract test's float32
    # case: up to about 5e-3), the cost to float32's resolution of it
    torch.testing.assert_close(compiled.U[keep], eager.U[keep], atol=5e-3, rtol=0)
    torch.testing.assert_close(compiled.cost[keep], eager.cost[keep], atol=1e-5, rtol=1e-5)


def _marked(t: torch.Tensor) -> bool:
    return 0 in getattr(t, "_dynamo_weak_dynamic_indices", ())  # what torch._dynamo.maybe_mark_dynamic sets


def test_mark_batch_marks_the_batch_dimension_alone():
    problem = small_pendulum()  # N = 8: a knot mask (8, m) beside a batch of 3
    constraints = Constraints.of(problem)
    x0 = torch.zeros(3, 2, dtype=torch.float64)
    al = AugmentedLagrangian(constraints, Duals.initial(constraints, 3, 1.0, x0))
    params = {"mass": torch.ones(3, dtype=torch.float64)}
    steps = torch.ones(5, dtype=torch.float64)
    mark_batch((problem, al, params, x0, torch.zeros(3, 9, 2, dtype=torch.float64), steps, 1e-6, None), {})
    assert _marked(x0) and _marked(params["mass"]) and _marked(al.duals.stage) and _marked(al.duals.terminal)
    assert not _marked(steps) and not _marked(al.knot_mask)
    assert not any(_marked(t) for t in (problem.u_lower, problem.u_upper, constraints.ineq_knot_mask))


def test_a_solve_of_one_instance_marks_nothing_and_a_batch_its_batch():
    """Inside ``batch_of(1)`` (``tt.solve`` of one instance) no argument is marked, whatever its sizes; inside
    ``batch_of(3)`` and outside any, the batch's tensors are."""
    batch = torch.zeros(3, 2, dtype=torch.float64)
    with batch_of(1):
        mark_batch((batch, torch.zeros(3, 9, dtype=torch.float64)), {})
    assert not _marked(batch)
    for context in (batch_of(3), contextlib.nullcontext()):
        fresh = torch.zeros(3, 2, dtype=torch.float64)
        with context:
            mark_batch((fresh, torch.zeros(3, 9, dtype=torch.float64)), {})
        assert _marked(fresh)


def _masked_rows(rows: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    return rows * knots.sum()


def test_a_batch_mark_lasts_for_its_call(dynamo_capture):
    """A tensor that outlives a kernel's call, as a problem's knot mask ``(N, m)``, is marked where the batch's rows
    happen to number N (the rows of a compacted batch); the mark comes off after the call (``compiled.unmark``), so
    that a later call finds the graph compiled without it. It stayed before, and the next solve of the same batch
    compiled four IPM kernels again."""
    from torchtraj.core import compiled

    knots = torch.ones(4, 2, dtype=torch.float64)  # N = 4
    kernel = compiled.kernel(_masked_rows, True)
    with batch_of(6):
        kernel(torch.ones(6, 2, dtype=torch.float64), knots)
        kernel(torch.ones(4, 2, dtype=torch.float64), knots)  # four rows: the mask marked for this call
        assert not _marked(knots) and not hasattr(knots, "_has_dynamo_dim_marking")
        before = dynamo_capture["stats"]["unique_graphs"]
        kernel(torch.ones(5, 2, dtype=torch.float64), knots)
    assert dynamo_capture["stats"]["unique_graphs"] == before


def test_a_single_instance_calls_kernels_compiled_with_pooled_buffers(monkeypatch):
    """A kernel is compiled twice: with :data:`~torchtraj.core.compiled.SINGLE_OPTIONS` (inductor's pooled buffers)
    for the calls inside ``batch_of(1)``, and with the batched options for the others, told a batch or not; both with
    the guard filter."""
    from torchtraj.core import compiled
    from torchtraj.core.batching import rollout

    calls = []

    def recorded(fn, dynamic, options):
        def run(*args, **kwargs):
            calls.append(options)
            return fn(*args, **kwargs)
        return run

    monkeypatch.setattr(torch, "compile", recorded)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    problem = small_pendulum()
    step = compiled.kernel(rollout, True)
    for size, context in ((1, batch_of(1)), (3, batch_of(3)), (1, contextlib.nullcontext())):
        with context:
            params = {name: torch.as_tensor(v).expand(size, *torch.as_tensor(v).shape)
                      for name, v in problem.params.items()}
            X = step(problem.dynamics, torch.zeros(size, 2, dtype=torch.float64),
                     torch.zeros(size, 8, 1, dtype=torch.float64), params)
        assert X.shape == (size, 9, 2)
    filtered = {"guard_filter_fn": compiled.kept_guards}  # no guards on library globals, each kernel
    assert calls == [{**compiled.SINGLE_OPTIONS, **filtered}, {**compiled.OPTIONS, **filtered},
                     {**compiled.OPTIONS, **filtered}]
    assert compiled.SINGLE_OPTIONS["memory_planning"] and not compiled.OPTIONS.get("memory_planning", False)


def test_a_kernels_own_options_add_to_its_single_or_batched_graphs(monkeypatch):
    """``single_options`` and ``batched_options`` add a kernel's own Inductor settings to one kind of graph each:
    ALTRO's projection and its Newton steps on the KKT conditions compile a single instance without memory planning
    (which recursed past Python's limit on their buffers), their batched graphs with the batched options."""
    from torchtraj.core import compiled
    from torchtraj.solvers.altro import polish, projection

    seen = {}

    def recorded(fn, dynamic, options):
        seen.setdefault(fn, []).append({k: v for k, v in options.items() if k != "guard_filter_fn"})
        return fn

    monkeypatch.setattr(torch, "compile", recorded)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    for fn in (projection._linearised_step, projection._least_squares_multipliers, polish.newton_kkt_step):
        compiled.kernel(fn, True)
        assert seen[fn] == [compiled.OPTIONS, {**compiled.SINGLE_OPTIONS, "memory_planning": False}], fn.__name__
    plain = compiled.kernel(polish.kkt_error, True)
    assert plain is not polish.kkt_error
    assert seen[polish.kkt_error] == [compiled.OPTIONS, compiled.SINGLE_OPTIONS]


def test_one_capture_of_each_altro_kernel_serves_every_batch_size(dynamo_capture):
    """ALTRO's kernels (the AL objective and violation, the iLQR iteration, the multiplier update) take the batch as
    a symbol: a batch of 3 after one of 2 captures no graph, and none breaks (Dynamo's capture alone), with the eager
    answers."""
    problem = tt.problems.get("pendulum").replace(horizon=12)
    opts = tt.ALTROOptions(iterations_outer=3)
    compiled_opts = dataclasses.replace(opts, ilqr=tt.ILQROptions(compile=True))
    graphs = {}
    for B in (2, 3):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        before = dynamo_capture["stats"]["unique_graphs"]
        solution = tt.solve(problem, x0, "altro", options=compiled_opts)
        graphs[B] = dynamo_capture["stats"]["unique_graphs"] - before
        assert_same_solution(solution, tt.solve(problem, x0, "altro", options=opts))
    assert not dynamo_capture["graph_break"], dict(dynamo_capture["graph_break"])
    assert graphs[2] >= 5 and graphs[3] == 0, graphs


@pytest.mark.slow  # Dynamo traces the projection's kernels for most of a minute
def test_one_capture_of_each_altro_projection_kernel_serves_every_batch_size(dynamo_capture, monkeypatch):
    """The kernels of ALTRO's projection (its feasibility steps, multiplier solves, Newton steps on the KKT
    conditions and their KKT errors) take the batch as a symbol too: a batch of 3 after one of 2 captures no graph,
    and none breaks (Dynamo's capture alone; the AL stage eager, so that only the projection is captured), with the
    eager answers."""
    from torchtraj.solvers.altro import projection, stages

    called, kernel, project = set(), projection.kernel, projection.project

    def counted(fn, enabled):
        if enabled:
            called.add(fn.__name__)
        return kernel(fn, enabled)

    monkeypatch.setattr(projection, "kernel", counted)
    problem = small_pendulum(8)
    opts = tt.ALTROOptions(iterations_outer=3)
    graphs = {}
    for B in (2, 3):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        eager = tt.solve(problem, x0, "altro", options=opts)
        before = dynamo_capture["stats"]["unique_graphs"]
        with monkeypatch.context() as patch:
            patch.setattr(stages, "project", lambda *args, **kwargs: project(*args, **{**kwargs, "compile": True}))
            solution = tt.solve(problem, x0, "altro", options=opts)
        graphs[B] = dynamo_capture["stats"]["unique_graphs"] - before
        assert bool((eager.status == tt.Status.CONVERGED).all()), "the projection should end every solve"
        assert_same_solution(solution, eager)
    assert {"_linearised_step", "_least_squares_multipliers", "newton_kkt_step", "kkt_error"} <= called, called
    assert not dynamo_capture["graph_break"], dict(dynamo_capture["graph_break"])
    assert graphs[2] >= 4 and graphs[3] == 0, graphs


@pytest.mark.slow  # Dynamo traces for half a minute; the default run keeps the test above
def test_compiled_altro_iterates_the_running_instances_alone(monkeypatch, dynamo_capture):
    """Compiled iLQR iterations leave the finished instances behind (``ILQROptions.compact_below``) down to two
    instances, with no graph for the smaller batches and the eager answers (Dynamo's capture alone)."""
    from torchtraj.iterations import ilqr

    on_rows, sizes = ilqr._on_rows, []

    def counted(iteration, rows, *args):
        sizes.append(rows.numel())
        return on_rows(iteration, rows, *args)

    monkeypatch.setattr(ilqr, "_on_rows", counted)
    problem = tt.problems.get("pendulum").replace(horizon=12)
    opts = tt.ALTROOptions(iterations_outer=4)
    compiled_opts = dataclasses.replace(opts, ilqr=tt.ILQROptions(compile=True))
    x0 = tt.problems.sample_x0("pendulum", 8, seed=1)
    solution = tt.solve(problem, x0, "altro", options=compiled_opts)
    graphs_at_8 = dynamo_capture["stats"]["unique_graphs"]
    tt.solve(problem, x0[:6], "altro", options=compiled_opts)
    assert dynamo_capture["stats"]["unique_graphs"] == graphs_at_8
    assert sizes and min(sizes) >= 2 and max(sizes) < 8, sizes
    assert_same_solution(solution, tt.solve(problem, x0, "altro", options=opts))


def test_concat_joins_per_instance_rows_as_cat_does_and_keeps_the_batch_dynamic():
    """``batching.concat`` traced (zero pads and a sum) gives ``torch.cat``'s rows, vectors and matrices alike,
    skips empty parts, and a vmapped function using it is captured once for batches of 2 and 3; with ``torch.cat``
    the capture is specialised to each batch size."""
    from torch._dynamo.utils import counters
    from torch.func import vmap

    from torchtraj.core.batching import concat

    def rows(join):
        def per_instance(x):
            matrix = torch.outer(x[:2], x)
            return join([x[:2].sin(), x.new_zeros(0), x * 2.0]), join([matrix, -matrix[:1]])
        return lambda X: vmap(per_instance)(X)

    graphs = {}
    for join in (concat, torch.cat):
        torch._dynamo.reset()
        counters.clear()
        fn = torch.compile(rows(join), backend="eager", dynamic=False)
        for B in (2, 3):
            X = torch.randn(B, 3, dtype=torch.float64)
            torch._dynamo.maybe_mark_dynamic(X, 0)
            for got, expected in zip(fn(X), rows(torch.cat)(X)):
                torch.testing.assert_close(got, expected, atol=0, rtol=0)
        graphs[join] = counters["stats"]["unique_graphs"]
    torch._dynamo.reset()
    assert graphs[concat] == 1 and graphs[torch.cat] == 2, graphs


def test_applied_inequality_rows_are_the_knot_masks_ones():
    """The count the KKT residuals read without a host read: the ones of the knot mask, and none where the
    constraints are ignored (the unconstrained problem's KKT conditions)."""
    for name in tt.problems.names():
        constraints = Constraints(tt.problems.get(name))
        assert constraints.applied_ineq_rows == int(constraints.ineq_knot_mask.sum()), name
        assert Constraints(tt.problems.get(name), ignored=True).applied_ineq_rows == 0, name


@pytest.mark.slow  # compiling the iLQR kernels takes about a minute on two cores
def test_one_compilation_serves_every_batch_size():
    torch._dynamo.reset()  # no graph from an earlier test: the B = 2 solve compiles the kernels
    counters = torch._dynamo.utils.counters
    problem = small_pendulum()
    opts = tt.ILQROptions(iterations=10)
    graphs = {}
    for B in (2, 3):
        x0 = tt.problems.sample_x0("pendulum", B, seed=B)
        eager = tt.solve(problem, x0, "ilqr", options=opts)
        before = counters["stats"]["unique_graphs"]
        compiled = tt.solve(problem, x0, "ilqr", options=dataclasses.replace(opts, compile=True))
        graphs[B] = counters["stats"]["unique_graphs"] - before
        assert_same_solution(eager, compiled)
    assert graphs[2] > 0 and graphs[3] == 0, graphs


def test_a_long_horizon_is_rolled_out_by_one_kernel_in_pieces(dynamo_capture, monkeypatch):
    """Past ``ROLLOUT_STAGES`` stages the compiled rollout takes the controls in consecutive pieces (here 4, 4 and 2
    of 10): two specialisations of one kernel, the full piece and the last, and the eager rollout's states to the
    bit (Dynamo's capture runs the same operations); within the bound it is one call of the kernel."""
    from torchtraj.core import batching, compiled

    monkeypatch.setattr(compiled, "ROLLOUT_STAGES", 4)
    problem = small_pendulum(horizon=10)
    for B in (3, 1):  # a single instance's views of its states pass .contiguous() unchanged: they are copied
        torch._dynamo.reset()
        dynamo_capture.clear()
        x0 = tt.problems.sample_x0("pendulum", B, seed=1)
        U = torch.linspace(-1, 1, 10 * B, dtype=torch.float64).reshape(B, 10, 1)
        params = {name: torch.as_tensor(v).expand(B, *torch.as_tensor(v).shape) for name, v in problem.params.items()}
        eager = batching.rollout(problem.dynamics, x0, U, params)
        X = compiled.rollout_kernel(True)(problem.dynamics, x0, U, params)
        assert torch.equal(X, eager)
        assert dynamo_capture["stats"]["unique_graphs"] == 2 and not dynamo_capture["graph_break"], B
    short = compiled.rollout_kernel(True)(problem.dynamics, x0, U[:, :4].clone(memory_format=torch.contiguous_format),
                                          params)
    assert torch.equal(short, eager[:, :5]) and dynamo_capture["stats"]["unique_graphs"] == 2
    assert compiled.rollout_kernel(False) is batching.rollout
