"""Recorded kernels (torchtraj.core.recorded): a function's operator graph traced once per signature, simplified and
replayed, with the eager call's results to the last bit and fewer operator calls."""

import dataclasses

import pytest
import torch
from same_solutions import assert_same_solutions

import torchtraj as tt
from torchtraj import problems
from torchtraj.bench.ops import OperatorCounter
from torchtraj.core import batching, one_pass, recorded
from torchtraj.core.batching import closed_loop_rollout
from torchtraj.core.constraints import Constraints
from torchtraj.core.one_pass import problem_kkt_expansion, problem_values
from torchtraj.core.recorded import SIZE_SCALE, TRACE_AT, TRACE_AT_AUTO, Recorded, trace_at
from torchtraj.core.scripted import Scripted

F64 = torch.float64
REPLAYS = (torch.fx.GraphModule, Scripted)  # a record's replay: its graph's Python code, or TorchScript's


def _point(name: str, B: int, seed: int = 0):
    """A random point of problem ``name`` with random multipliers (nonzero everywhere: every term counts)."""
    p = problems.get(name)
    cons = Constraints.of(p)
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.randn(*shape, dtype=F64, generator=g)

    X, U = rand(B, p.N + 1, p.nx), rand(B, p.N, p.nu)
    multipliers = (rand(B, p.N + 1, p.nx), rand(B, p.N, cons.me), rand(B, p.N, cons.mi).abs(), rand(B, cons.meN),
                   rand(B, cons.miN).abs())
    params = {k: v.unsqueeze(0) for k, v in p.params.items()}
    return p, cons, X, U, params, multipliers


def _same(a, b):
    assert a.shape == b.shape and a.stride() == b.stride() and a.dtype == b.dtype
    assert torch.equal(a, b)


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "car_3obs", "quadrotor2d"])
def test_the_recorded_expansion_is_the_eager_one_to_the_last_bit_with_fewer_calls(name):
    p, cons, X, U, params, w = _point(name, 3)
    with torch.no_grad():
        with OperatorCounter() as eager_calls:
            eager = problem_kkt_expansion(p, cons, X, U, params, *w)
        for _ in range(TRACE_AT):  # traced at the last of these
            problem_kkt_expansion(p, cons, X, U, params, *w, record=True)
        with OperatorCounter() as recorded_calls:
            recorded = problem_kkt_expansion(p, cons, X, U, params, *w, record=True)
        for field in ("cost", "Lz", "Lzz", "LNx", "LNxx", "f", "fz", "h", "Hz", "g", "Gz", "hN", "HN", "gN", "GN"):
            _same(getattr(recorded, field), getattr(eager, field))
        # values at other points and multipliers: the record is of the operators, not of the numbers
        _, _, X2, U2, _, w2 = _point(name, 3, seed=1)
        again = problem_kkt_expansion(p, cons, X2, U2, params, *w2, record=True)
        _same(again.Lzz, problem_kkt_expansion(p, cons, X2, U2, params, *w2).Lzz)
        values = problem_values(p, cons, X2, U2, params, record=True)
        _same(values.f, problem_values(p, cons, X2, U2, params).f)
    assert recorded_calls.total < 0.8 * eager_calls.total


def test_control_flow_on_tensor_values_runs_eager():
    """A trace on fake tensors cannot take a branch on a value: that signature runs the function itself, so each
    call takes its own branch."""
    def branching(x):
        return x * 2.0 if bool(x.sum() > 0) else x - 1.0

    f = Recorded(branching)
    x = torch.ones(3, dtype=F64)
    for _ in range(TRACE_AT):
        assert torch.equal(f(x), x * 2.0) and torch.equal(f(-x), -x - 1.0)
    assert f.traces == 1


def test_repeated_subexpressions_do_not_alias_the_outputs():
    """Common subexpressions are computed once, but outputs that the function returned as separate tensors stay
    separate: writing into one leaves the other."""
    f = Recorded(lambda x: (x * 2.0, x * 2.0, (x * 2.0)[1:]))
    x = torch.arange(4, dtype=F64)
    for _ in range(TRACE_AT - 1):
        f(x)
    a, b, c = f(x)
    assert f.traces == 1
    a.add_(1.0)
    assert torch.equal(b, x * 2.0) and torch.equal(c, (x * 2.0)[1:])


def test_a_signature_is_traced_once_at_its_trace_at_th_call_and_autograd_runs_eager():
    f = Recorded(lambda x, scale: (x.sin() * scale).sum(-1))
    x = torch.rand(2, 5, dtype=F64)
    for _ in range(TRACE_AT - 1):
        f(x, 2.0)
    assert f.traces == 0  # seen fewer times: eager
    for _ in range(3):
        assert torch.equal(f(x, 2.0), (x.sin() * 2.0).sum(-1))
    assert f.traces == 1
    for other in ((x, 3.0), (x.t().contiguous().t(), 2.0), (torch.rand(4, 5, dtype=F64), 2.0)):  # a number,
        for _ in range(TRACE_AT):  # strides, a size: each another record
            f(*other)
    assert f.traces == 4
    y = x.clone().requires_grad_()
    f(y, 2.0).sum().backward()  # eager: autograd sees the operators
    assert torch.allclose(y.grad, 2.0 * x.cos())
    assert f.traces == 4


def test_views_of_one_buffer_at_other_offsets_share_a_record_and_read_their_own_elements():
    """The signature leaves out the storage offset: a collapsed view chain (``as_strided``) is replayed relative to
    its tensor's own offset, so that the stages of a rollout, views one stage apart in a buffer, share a record."""
    f = Recorded(lambda x: x.t()[1:].t() * 2.0)  # a view of a view: one strided view of x in the record
    buffer = torch.rand(6, 3, 4, dtype=F64)
    stages = buffer.unbind(0)  # (3, 4) views at offsets 0, 12, 24, ...
    for _ in range(TRACE_AT):
        f(stages[0])
    assert f.traces == 1
    with OperatorCounter() as calls:
        replayed = [f(stage) for stage in stages]
    for stage, out in zip(stages, replayed):
        assert torch.equal(out, stage[:, 1:] * 2.0)
    assert f.traces == 1 and calls.total == 2 * len(stages)  # the strided view and the product, replayed


@pytest.mark.parametrize("name,expanded", [("pendulum", False), ("cartpole", False), ("pendulum", True)])
def test_a_recorded_rollout_is_the_eager_one_to_the_last_bit_in_fewer_calls(name, expanded):
    """``closed_loop_rollout(..., record=True)`` (the line search of iLQR and ALTRO with ``ILQROptions.record``):
    each stage replayed from one record, the eager rollout's states and controls to the last bit; ``expanded``: the
    E trajectories of an instance start from one state, expanded (a line search's candidates), whose layout is not
    that of the later stages' states."""
    p = problems.get(name)
    g = torch.Generator().manual_seed(0)
    B, E, N = (1, 4, p.N) if expanded else (2, 3, p.N)
    x0 = p.x0.expand(B, E, p.nx) + 0.1 * torch.randn(B, E, p.nx, dtype=F64, generator=g)
    if expanded:
        x0 = x0[:, :1].expand(B, E, p.nx)
    U = 0.5 * torch.randn(B, E, N, p.nu, dtype=F64, generator=g)
    X_ref = torch.randn(B, N + 1, p.nx, dtype=F64, generator=g)
    K = 0.1 * torch.randn(B, N, p.nu, p.nx, dtype=F64, generator=g)
    params = {k: v.unsqueeze(0).expand(B, *v.shape) for k, v in p.params.items()}
    with OperatorCounter() as eager_calls:
        X, Us = closed_loop_rollout(p.dynamics, x0, U, params, X_ref, K)
    traces = batching._RECORDED_STAGE_STEP.traces
    closed_loop_rollout(p.dynamics, x0, U, params, X_ref, K, record=True)  # its N stages count N calls: traced
    with OperatorCounter() as recorded_calls:
        Xr, Ur = closed_loop_rollout(p.dynamics, x0, U, params, X_ref, K, record=True)
    assert batching._RECORDED_STAGE_STEP.traces - traces <= 1  # one record serves every stage
    assert torch.equal(Xr, X) and torch.equal(Ur, Us)
    assert recorded_calls.total < 0.8 * eager_calls.total


@pytest.mark.parametrize("name,B", [("pendulum", 3), ("car_3obs", 2)])
def test_an_interior_point_solve_with_recorded_kernels_is_the_eager_solve(name, B):
    """``IPOptions.record``: the same iterates to the last bit, in the solve that records (from its
    ``TRACE_AT``-th expansion on) and in a second one that replays its records (and may record signatures that
    reach their ``TRACE_AT``-th call only then)."""
    p = problems.get(name)
    x0 = problems.sample_x0(name, B, 0)
    eager = tt.solve(p, x0, "ipm", options=tt.IPOptions(iterations=30, record=False))
    traces = one_pass._RECORDED_EXPANSION.traces
    recorded = tt.solve(p, x0, "ipm", options=tt.IPOptions(iterations=30, record=True))
    traced = one_pass._RECORDED_EXPANSION.traces
    assert traced > traces  # the batch's size, and the running instances' once one has finished
    again = tt.solve(p, x0, "ipm", options=tt.IPOptions(iterations=30, record=True))  # replays those
    for sol in (recorded, again):
        assert_same_solutions(sol, eager)


def test_an_altro_solve_with_recorded_kernels_is_the_eager_solve():
    """``ILQROptions.record`` (ALTRO's inner iLQR, as a control step takes it): the same answer to the last bit."""
    p = problems.get("pendulum")
    x0 = problems.sample_x0("pendulum", 3, 0)
    eager = tt.solve(p, x0, "altro", options=tt.ALTROOptions(
        iterations_outer=3, iterations_inner=20, ilqr=tt.ILQROptions(record=False)))
    recorded = tt.solve(p, x0, "altro", options=tt.ALTROOptions(
        iterations_outer=3, iterations_inner=20, ilqr=tt.ILQROptions(record=True)))
    assert_same_solutions(recorded, eager)


@pytest.mark.parametrize("initial", [False, True])
def test_a_solutions_measures_replay_to_the_last_bit(initial):
    """The cost and largest violation of a method's answer (ALTRO's and eILQR's), taken once a solve (a
    controller's every step), replay from their record (the methods' ``record`` option) with the eager bits, defects,
    violated rows and the initial defect (``x0``, eILQR's fixed start) included."""
    from torchtraj.kkt import merit
    p = problems.get("car_3obs")
    g = torch.Generator().manual_seed(0)
    X = torch.randn(2, p.N + 1, p.nx, dtype=F64, generator=g)
    U = torch.randn(2, p.N, p.nu, dtype=F64, generator=g)
    x0 = X[:, 0] + 10.0 if initial else None  # a defect larger than any other violation
    args = (p, Constraints.of(p), X, U, p.batched_params(2), x0)
    eager = merit.cost_and_violation(*args)
    measure = merit.solution_measures(False, True)
    for _ in range(TRACE_AT):
        recorded = measure(*args)
    record = next(reversed(merit._RECORDED_COST_AND_VIOLATION.records.values()))  # the last one used
    assert isinstance(record[0], REPLAYS) and all(torch.equal(a, b) for a, b in zip(recorded, eager))
    assert bool((eager[1] > 0).all())
    assert not initial or bool((eager[1] >= 10.0).all())


@pytest.mark.parametrize("method,options", [("eilqr", tt.EILQROptions), ("hm-ilqr", tt.HMILQROptions)])
def test_the_other_methods_with_recorded_kernels_are_their_eager_solves(method, options):
    """``EILQROptions.record`` and ``HMILQROptions.record`` (their control steps' default): the same answer to the
    last bit."""
    p = problems.get("pendulum")
    x0 = problems.sample_x0("pendulum", 2, 0)
    eager = tt.solve(p, x0, method, options=options(iterations=30, record=False))
    recorded = tt.solve(p, x0, method, options=options(iterations=30, record=True))
    assert_same_solutions(recorded, eager)


def test_a_tensor_read_from_a_closure_keeps_the_function_eager():
    """A replay holds the tensors it read by reference, so one read from a closure or from an argument whose
    attributes can be reassigned (a reference trajectory that the caller replaces between calls) would go stale:
    such a signature runs eager. Tensors of a frozen dataclass argument and literals the function makes are
    recorded (an in-place change of the former is seen)."""
    class Reference:
        def __init__(self):
            self.goal = torch.ones(3, dtype=F64)

    @dataclasses.dataclass(frozen=True)
    class Frozen:
        goal: torch.Tensor

    outside, frozen = Reference(), Frozen(torch.ones(3, dtype=F64))
    closure = Recorded(lambda x: x - outside.goal)
    argument = Recorded(lambda x, ref: x - ref.goal)
    owned = Recorded(lambda x, ref: x - ref.goal + torch.tensor(2.0, dtype=F64))
    x = torch.zeros(3, dtype=F64)
    for _ in range(TRACE_AT):
        closure(x)
        argument(x, outside)
        owned(x, frozen)
    outside.goal = torch.full((3,), 5.0, dtype=F64)
    assert torch.equal(closure(x), x - 5.0) and torch.equal(argument(x, outside), x - 5.0)
    assert closure.traces == argument.traces == owned.traces == 1
    for eager in (closure, argument):
        assert not isinstance(next(iter(eager.records.values()))[0], REPLAYS)
    assert isinstance(next(iter(owned.records.values()))[0], REPLAYS)
    frozen.goal.mul_(2.0)
    assert torch.equal(owned(x, frozen), x)  # 0 - 2 + 2: the frozen argument's tensor, changed in place


def test_signatures_seen_a_few_times_never_push_a_record_out():
    """A controller whose problem is rebuilt at every step makes a new signature a step: their call counts are
    kept apart from the records, so the steady signature's record stays."""
    f = Recorded(lambda x: x * 2.0)
    steady = torch.ones(3, dtype=F64)
    for _ in range(TRACE_AT):
        f(steady)
    for n in range(4 * recorded.LIMIT + 5):  # each another size, seen once
        f(torch.ones(n + 4, dtype=F64))
    assert f.traces == 1 and len(f.calls) == 4 * recorded.LIMIT
    (record,) = f.records.values()  # the steady signature's, still there
    assert isinstance(record[0], REPLAYS)
    assert torch.equal(f(steady), steady * 2.0) and f.traces == 1


def test_a_call_inside_a_transform_runs_eager():
    f = Recorded(lambda x: x.sin() * 2.0)
    xs = torch.rand(4, 3, dtype=F64)
    for _ in range(TRACE_AT):
        out = torch.func.vmap(f)(xs)
    assert f.traces == 0 and torch.equal(out, xs.sin() * 2.0)
    grad = torch.func.grad(lambda x: f(x).sum())(xs[0])
    assert f.traces == 0 and torch.allclose(grad, 2.0 * xs[0].cos())


def test_the_record_option_says_when_a_signature_is_traced():
    """``record``: ``True`` early, ``None`` (the solvers' default) when its eager calls have cost about a trace,
    ``False`` never; a call of a :class:`Recorded` traces its signature at the ``trace_at``-th call."""
    assert (trace_at(True), trace_at(None), trace_at(False)) == (TRACE_AT, TRACE_AT_AUTO, None)
    assert TRACE_AT < TRACE_AT_AUTO
    f = Recorded(lambda x: x * 3.0)
    x = torch.rand(4, dtype=F64)
    for _ in range(TRACE_AT_AUTO - 1):
        assert torch.equal(f(x, trace_at=TRACE_AT_AUTO), x * 3.0)
    assert f.traces == 0
    f(x, trace_at=TRACE_AT_AUTO)  # traced here
    assert f.traces == 1
    with OperatorCounter() as calls:
        out = f(x, trace_at=TRACE_AT_AUTO)
    assert torch.equal(out, x * 3.0) and f.traces == 1 and calls.total == 1  # replayed


def test_a_call_on_larger_arguments_counts_for_more():
    """An eager call's cost grows with its arguments, a trace's does not: a call whose largest argument holds ``n``
    elements counts ``1 + n // SIZE_SCALE`` calls towards ``trace_at``."""
    f = Recorded(lambda x: x * 3.0)
    x = torch.rand(4 * SIZE_SCALE, dtype=F64)  # counts 5
    for _ in range(TRACE_AT_AUTO // 5 - 1):
        f(x, trace_at=TRACE_AT_AUTO)
    assert f.traces == 0
    f(x, trace_at=TRACE_AT_AUTO)  # the twentieth call: traced
    assert f.traces == 1 and torch.equal(f(x, trace_at=TRACE_AT_AUTO), x * 3.0)


def test_rollouts_of_nearby_batch_sizes_share_a_padded_record(monkeypatch):
    """A recorded rollout runs its trajectories padded to ``padded_rows`` (copies of the last one): the line
    searches' many batch sizes share a few records, and each trajectory's states are the eager rollout's."""
    assert [batching.padded_rows(n) for n in (1, 4, 5, 6, 7, 9, 13, 17, 25, 33, 104, 129, 1024, 1025)] == \
        [1, 4, 6, 6, 8, 12, 16, 24, 32, 48, 128, 192, 1024, 1536]
    stage = Recorded(batching._RECORDED_STAGE_STEP.fn)
    monkeypatch.setattr(batching, "_RECORDED_STAGE_STEP", stage)
    p = problems.get("pendulum")
    g = torch.Generator().manual_seed(0)
    for n in (5, 6, 5):
        x0 = torch.randn(n, p.nx, dtype=F64, generator=g)
        U = torch.randn(n, p.N, p.nu, dtype=F64, generator=g)
        X_ref = torch.randn(n, p.N + 1, p.nx, dtype=F64, generator=g)
        K = 0.1 * torch.randn(n, p.N, p.nu, p.nx, dtype=F64, generator=g)
        params = p.batched_params(n)
        X, Us = closed_loop_rollout(p.dynamics, x0, U, params, X_ref, K)
        Xr, Ur = closed_loop_rollout(p.dynamics, x0, U, params, X_ref, K, record=True)  # N ≥ TRACE_AT calls
        assert Xr.shape == X.shape and torch.equal(Xr, X) and torch.equal(Ur, Us)
    assert stage.traces == 1  # 5 and 6 trajectories: one record of 6


def test_a_rollout_counts_its_stages_before_it_replays_them():
    """``Recorded.loop``: a rollout asks once for its N stages, counted as N calls of the stage's signature;
    they replay from the call that reaches ``trace_at`` on, and never where the trace failed."""
    f = Recorded(lambda x: x * 3.0)
    x = torch.rand(2, dtype=F64)
    assert [f.loop(x, calls=30, trace_at=100, varying=1) is not None for _ in range(4)] == [False, False, False, True]
    assert f.traces == 1 and f.loop(x, calls=30, trace_at=100, varying=1) is not None and f.traces == 1
    branching = Recorded(lambda x: x if bool(x.sum() > 0) else -x)
    assert branching.loop(x, calls=30, trace_at=10, varying=1) is None and branching.traces == 1
    assert branching.loop(x, calls=30, trace_at=10, varying=1) is None and branching.traces == 1


@pytest.mark.parametrize("method", ["altro", "ipm", "hm-ilqr"])
def test_a_default_solve_records_its_hot_shapes_and_keeps_the_eager_answer(method, monkeypatch):
    """With the default ``record=None`` a solve traces a shape once it has been evaluated ``TRACE_AT_AUTO`` times
    (a hundred; twenty here, with new records, so that a short solve crosses it): the rollouts' stages and the
    expansions, then replays them, with the answer of the eager solve to the last bit."""
    fresh = {}
    for module, name in ((batching, "_RECORDED_STAGE_STEP"), (batching, "_RECORDED_MAP_STAGE"),
                         (one_pass, "_RECORDED_EXPANSION"), (one_pass, "_RECORDED_VALUES")):
        fresh[name] = Recorded(getattr(module, name).fn)
        monkeypatch.setattr(module, name, fresh[name])
    monkeypatch.setattr(recorded, "TRACE_AT_AUTO", 20)
    p = problems.get("pendulum")
    x0 = problems.sample_x0("pendulum", 1 if method == "altro" else 2, 0)  # B = 1: candidates from one state
    if method == "altro":
        options = dict(iterations_outer=3, iterations_inner=20)
        eager = tt.solve(p, x0, method, options=tt.ALTROOptions(**options, ilqr=tt.ILQROptions(record=False)))
        default = tt.solve(p, x0, method, options=tt.ALTROOptions(**options))
        assert fresh["_RECORDED_STAGE_STEP"].traces >= 1
    elif method == "hm-ilqr":  # its segments' steps: Recorded.loop through stage_mapper
        eager = tt.solve(p, x0, method, options=tt.HMILQROptions(iterations=30, record=False))
        default = tt.solve(p, x0, method, options=tt.HMILQROptions(iterations=30))
        assert fresh["_RECORDED_MAP_STAGE"].traces >= 1
    else:
        eager = tt.solve(p, x0, method, options=tt.IPOptions(iterations=30, record=False))
        default = tt.solve(p, x0, method, options=tt.IPOptions(iterations=30))
    assert fresh["_RECORDED_EXPANSION"].traces >= 1
    assert_same_solutions(default, eager)


def test_a_loop_computes_what_reads_only_its_fixed_tensors_once():
    """``Recorded.loop``: for calls that change only the first tensors, the operators that read only the others (a
    rollout stage's products of parameters) run once, before the loop; each step replays the rest, the function's
    results to the last bit, and returns tensors of its own."""
    f = Recorded(lambda x, a, b: (x * (a * b) + a.sin(), x - b))
    a, b = torch.rand(3, dtype=F64), torch.rand(3, dtype=F64)
    xs = torch.rand(5, 3, dtype=F64).unbind(0)
    assert f.loop(xs[0], a, b, calls=5, trace_at=10, varying=1) is None  # counted, not yet worth a trace
    assert f.loop(xs[0], a, b, calls=5, trace_at=10, varying=1) is not None and f.traces == 1  # traced
    with OperatorCounter() as before:
        step = f.loop(xs[0], a, b, calls=5, trace_at=10, varying=1)
    assert before.total == 2 and f.traces == 1  # the hoisted a * b and a.sin()
    with OperatorCounter() as calls:
        outs = [step(x) for x in xs]
    assert calls.total == 3 * len(xs)  # the product, the sum and the difference
    for x, (y, z) in zip(xs, outs):
        assert torch.equal(y, x * (a * b) + a.sin()) and torch.equal(z, x - b)
    outs[0][0].add_(1.0)
    assert torch.equal(outs[1][0], xs[1] * (a * b) + a.sin())


def test_a_recorded_map_of_the_stages_is_the_eager_one_in_fewer_calls():
    """``batching.recorded_map_stage`` (HM-iLQR's defects at its segments' nodes): the pendulum's step at some
    knots of two instances, replayed from the eighth call with ``record=True``, eager with ``False``."""
    p = problems.get("pendulum")
    params, g = {k: v.unsqueeze(0) for k, v in p.params.items()}, torch.Generator().manual_seed(0)
    X, U = torch.randn(2, 5, p.nx, dtype=F64, generator=g), torch.randn(2, 5, p.nu, dtype=F64, generator=g)
    eager = batching.map_stage(p.dynamics, X, U, params)
    with OperatorCounter() as eager_calls:
        assert torch.equal(batching.recorded_map_stage(p.dynamics, X, U, params, False), eager)
    for _ in range(TRACE_AT):
        batching.recorded_map_stage(p.dynamics, X, U, params, True)
    with OperatorCounter() as calls:
        assert torch.equal(batching.recorded_map_stage(p.dynamics, X, U, params, True), eager)
    assert 3 * calls.total < 2 * eager_calls.total, (calls.total, eager_calls.total)  # 52 against 95
