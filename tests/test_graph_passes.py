"""The simplification of recorded graphs (torchtraj.core.graph_passes): what reads no input of a graph is computed
once, at the trace, and every call still returns tensors of its own and reads what it holds by reference."""

import dataclasses

import torch

from torchtraj.bench.ops import OperatorCounter
from torchtraj.core import graph_passes
from torchtraj.core.recorded import TRACE_AT, Recorded

F64 = torch.float64


def _recorded(fn, *args):
    f = Recorded(fn)
    for _ in range(TRACE_AT):
        f(*args)
    assert f.traces == 1
    return f


def _basis_product(x):
    """An identity, its scaled columns and a literal, then one product with the input and one sum: what ``vmap``
    and ``jacrev`` make of a basis."""
    basis = torch.eye(3, dtype=x.dtype).mul(2.0)[:, :2] + torch.tensor([1.0, -1.0], dtype=x.dtype)
    return x @ basis + torch.zeros_like(x[:, :2]).add(0.5)


def test_what_reads_no_input_is_computed_once_to_the_last_bit():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(4, 3, dtype=F64, generator=g)
    f = _recorded(_basis_product, x)
    for _ in range(3):
        x = torch.randn(4, 3, dtype=F64, generator=g)
        with OperatorCounter() as calls:
            got = f(x)
        assert torch.equal(got, _basis_product(x))
        assert calls.total == 2, calls.by_name  # the product and the sum: the rest was computed at the trace


def test_without_folding_the_same_graph_calls_its_factories(monkeypatch):
    """The pass, not the tracer, removed the factories' calls: with a limit of no elements nothing is folded."""
    monkeypatch.setattr(graph_passes, "FOLD_LIMIT", 0)
    x = torch.randn(4, 3, dtype=F64)
    f = _recorded(_basis_product, x)
    with OperatorCounter() as calls:
        assert torch.equal(f(x), _basis_product(x))
    assert calls.total > 5


def test_a_returned_constant_is_a_new_tensor_at_every_call():
    """An output made of constants alone, or a view of one, is not folded: a caller may write into it."""
    f = _recorded(lambda x: (x * 2.0, torch.ones(2, 3, dtype=x.dtype).mul(3.0), torch.zeros(3, dtype=x.dtype)
                             .add(1.0).expand(2, 3)), torch.ones(3, dtype=F64))
    _, a, b = f(torch.ones(3, dtype=F64))
    a.add_(1.0)
    b._base.add_(1.0)  # the expanded tensor's own storage
    _, a2, b2 = f(torch.ones(3, dtype=F64))
    assert torch.equal(a2, torch.full((2, 3), 3.0, dtype=F64)) and torch.equal(b2, torch.ones(2, 3, dtype=F64))


def test_a_tensor_held_by_reference_is_not_folded():
    """A frozen argument's tensor is read at every call (a change in place is seen), so nothing computed from it is
    folded, although it is no input of the graph."""
    @dataclasses.dataclass(frozen=True)
    class Weights:
        w: torch.Tensor

    weights = Weights(torch.ones(3, dtype=F64))
    f = _recorded(lambda x, ref: x * (ref.w * 2.0), torch.ones(3, dtype=F64), weights)
    weights.w.mul_(5.0)
    assert torch.equal(f(torch.ones(3, dtype=F64), weights), torch.full((3,), 10.0, dtype=F64))


def test_views_of_the_same_elements_are_taken_once():
    """``x[:, 1]`` and ``x.t()[1]`` are the same elements of ``x``: a ``select`` and a view chain (one strided view
    once collapsed), which common subexpression elimination sees as different operators; the replay takes one."""
    fn = lambda x: x[:, 1] * 2.0 + x.t()[1]  # noqa: E731
    buffer = torch.randn(3, 4, 3, dtype=F64)
    f = _recorded(fn, buffer[0])
    for row in buffer.unbind(0):  # rows of one buffer: the view read at each input's own offset
        with OperatorCounter() as calls:
            got = f(row)
        assert torch.equal(got, fn(row))
        assert calls.total == 3, calls.by_name  # one view, the product and the sum


def _components(x):
    """A dynamics function's reads of its state's components, ``x[:, 0]`` and ``x[:, 1]`` (one read twice)."""
    return torch.stack([x[:, 1], torch.sin(x[:, 0]) - 0.1 * x[:, 1]], 1)


def test_selects_of_one_tensor_are_one_unbind():
    """The components a function reads of one tensor are views of one ``unbind``, one call instead of one a
    component; replayed on rows of one buffer (other offsets), to the last bit."""
    buffer = torch.randn(3, 5, 2, dtype=F64)
    f = _recorded(_components, buffer[0])
    for row in buffer.unbind(0):
        with OperatorCounter() as calls:
            got = f(row)
        assert torch.equal(got, _components(row))
        assert calls.by_name["aten.unbind.int"] == 1 and "aten.select.int" not in calls.by_name, calls.by_name
        assert calls.total == 5, calls.by_name  # the unbind, the sine, the product, the difference, the stack


def _bits(t):
    return t.view(torch.int64)  # signed zeros and NaNs told apart


def _halves(a, b):
    """The gradient of a two-component vector read as ``x[:, 0]`` and ``x[:, 1]``: two scattered halves, summed."""
    S = [a.shape[0], 2]
    return torch.ops.aten.select_backward(a, S, 1, 1) + torch.ops.aten.select_backward(b, S, 1, 0)


def test_exact_rewrites_keep_every_bit_with_fewer_calls():
    """``x + (−y)`` replays as one difference, two scattered halves as a stack and ``+ 0``, a split into one piece as
    the tensor split: the eager bits, negative zeros (which the sum with a scattered zero makes positive) and
    infinities included."""
    a = torch.tensor([-0.0, 1.5, float("inf"), 0.0], dtype=F64)
    b = torch.tensor([2.0, -0.0, -3.0, -0.0], dtype=F64)
    cases = ((lambda x, y: x + (-y), 1), (lambda x, y: (-y) + x * 2.0, 2), (_halves, 2),
             (lambda x, y: torch.split(x, [4])[0] * y, 1))
    for fn, calls in cases:
        f = _recorded(fn, a, b)
        with OperatorCounter() as counted:
            got = f(a, b)
        assert torch.equal(_bits(got), _bits(fn(a, b))), (got, fn(a, b))
        assert counted.total == calls, counted.by_name
