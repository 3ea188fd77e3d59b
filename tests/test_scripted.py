"""Recorded graphs replayed by TorchScript's interpreter (torchtraj.core.scripted): the eager results to the last bit,
views relative to the inputs' offsets, and the Python replay where the tracer fails."""

import pytest
import torch

from torchtraj.bench.ops import OperatorCounter
from torchtraj.core import scripted
from torchtraj.core.recorded import TRACE_AT, Recorded
from torchtraj.core.scripted import Scripted


def _mixed(x, n):
    """Python scalars, an integer tensor times a float, a functional ``fill``, ``where`` with a scalar, a view of
    an input and a ``None`` output: what a replay must type and place as the eager call does."""
    filled = torch.empty_like(x)
    filled.fill_(2.5)
    scaled = n * 0.5 + x.sin() * 3.0
    return scaled, None, torch.where(x > 0.1, x, 0.0) + filled, x[1:] - x[:-1], (n + 1).cumsum(0)


def _record(fn, *args):
    f = Recorded(fn)
    for _ in range(TRACE_AT):
        f(*args)
    (record,) = f.records.values()
    return f, record[0]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_cpu_record_replays_by_torchscript_to_the_last_bit(dtype):
    g = torch.Generator().manual_seed(0)
    x, n = torch.randn(5, dtype=dtype, generator=g), torch.arange(5)
    f, replay = _record(_mixed, x, n)
    assert isinstance(replay, Scripted)
    for _ in range(3):
        x, n = torch.randn(5, dtype=dtype, generator=g), torch.randint(-3, 3, (5,), generator=g)
        got, want = f(x, n), _mixed(x, n)
        assert got[1] is None
        for a, b in zip(got, want):
            if b is not None:
                assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)


def test_a_replay_reads_each_inputs_own_offset():
    """Rows of one buffer share a signature (their offsets are not part of it); a view the graph takes of its input
    is relative to that input's offset at each replay, not the trace's."""
    buf = torch.arange(40, dtype=torch.float64).reshape(8, 5)
    fn = lambda row: row.unsqueeze(0)[:, 1:] * 2.0 + row[:-1]  # noqa: E731  (a view of a view: one strided view)
    f, replay = _record(fn, buf[0])
    assert isinstance(replay, Scripted)
    for k in range(8):
        assert torch.equal(f(buf[k]), fn(buf[k]))


def test_a_replay_counts_its_operators():
    """The operators a TorchScript replay calls go through the dispatcher: the operator counter sees them."""
    x = torch.ones(3, dtype=torch.float64)
    f, _ = _record(lambda x: (x.sin() * 2.0).cos(), x)
    with OperatorCounter() as ops:
        f(x)
    assert ops.total == 3 and set(ops.by_name) == {"aten.sin.default", "aten.mul.Tensor", "aten.cos.default"}


def test_where_the_tracer_fails_the_graph_replays_in_python(monkeypatch):
    def refuse(*args, **kwargs):
        raise RuntimeError("no TorchScript here")

    monkeypatch.setattr(scripted.torch.jit, "trace", refuse)
    x, n = torch.randn(5, dtype=torch.float64), torch.arange(5)
    f, replay = _record(_mixed, x, n)
    assert isinstance(replay, torch.fx.GraphModule)
    for a, b in zip(f(x * 2.0, n), _mixed(x * 2.0, n)):
        assert (a is None and b is None) or torch.equal(a, b)
