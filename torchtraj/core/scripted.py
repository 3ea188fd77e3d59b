r"""A recorded graph replayed by TorchScript's interpreter instead of its Python code.

A simplified graph of :mod:`~torchtraj.core.recorded` is replayed by the Python code ``torch.fx`` generates for it:
one line an operator, each a call of a public function whose argument parser and result wrapping cost about as much
as the small operator itself. :func:`scripted` traces that code once more with ``torch.jit.trace`` (on the trace's
own inputs) and replays the TorchScript graph by the interpreter, without optimisation passes
(``torch.jit.optimized_execution(False)``): the same operators on the same data in the same order, with each call's
overhead in C++. The results are the graph's to the last bit (``tests/test_scripted.py``).

A view relative to an input's offset (:func:`~torchtraj.core.graph_passes.strided`, the stages of a rollout as views
of one buffer) reads the offset at run time through a scripted function; a constant a graph reads (a problem's
bounds) is read by reference, as the Python replay reads it.

Where the trace fails, or on a device other than the CPU, the Python replay stays. ``torch.jit.trace`` is deprecated
in PyTorch 2.13 in favour of ``torch.compile`` and ``torch.export``; neither replays a small graph with less
overhead than its Python code without a compilation of seconds, so it is used here, its warning silenced, behind a
fallback: where ``torch.jit`` goes, the Python replay is what remains.
"""

from __future__ import annotations

import warnings
from typing import Callable, List, Sequence

import torch
from torch import Tensor

from .graph_passes import output_values, strided


def _strided_at_run_time(base: Tensor, size: List[int], stride: List[int], shift: int) -> Tensor:
    """:func:`~torchtraj.core.graph_passes.strided`, scripted so that a trace reads ``base``'s offset at run time
    rather than recording the trace's."""
    return torch.as_strided(base, size, stride, base.storage_offset() + shift)


_SCRIPTED_STRIDED: list = []  # the scripted function, made at the first graph that needs it


def relative_view(base: Tensor, size: List[int], stride: List[int], shift: int) -> Tensor:
    """The view of :func:`_strided_at_run_time`, by its scripted version (a trace records a call of it)."""
    if not _SCRIPTED_STRIDED:
        _SCRIPTED_STRIDED.append(torch.jit.script(_strided_at_run_time))
    return _SCRIPTED_STRIDED[0](base, size, stride, shift)


class Scripted:
    """A graph's replay by TorchScript (module docstring): call ``forward(*tensors)`` as the graph's; ``None``
    outputs are put back where the graph returned them."""

    def __init__(self, traced: Callable, outputs: Sequence, graph: torch.fx.GraphModule):
        self.traced = traced
        self.none_at = [i for i, out in enumerate(outputs) if out is None]
        self.count = len(outputs)
        self.module = graph  # the graph it replays (hoisting reads it)

    def forward(self, *tensors):
        with torch.jit.optimized_execution(False):
            out = self.traced(*tensors)
        if not self.none_at:
            return list(out)
        out = iter(out)
        return [None if i in self.none_at else next(out) for i in range(self.count)]


def scripted(graph: torch.fx.GraphModule, tensors: Sequence[Tensor]):
    """``graph``'s replay by TorchScript's interpreter, traced on ``tensors`` (its inputs; CPU tensors), or ``graph``
    itself where the inputs are elsewhere or the trace fails."""
    if not tensors or any(t.device.type != "cpu" for t in tensors):
        return graph
    try:
        code = torch.fx.GraphModule(graph, _for_the_tracer(graph.graph))
        outputs = output_values(graph)  # None where the graph returns None

        def tensors_out(*args):
            return tuple(out for out in code(*args) if out is not None)

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the deprecation of torch.jit.trace, and tracer warnings
            traced = torch.jit.trace(tensors_out, tuple(tensors), check_trace=False, strict=False)
        return Scripted(traced, outputs, graph)
    except Exception:  # an operator or output the tracer does not take: the Python replay
        return graph


def _for_the_tracer(graph: torch.fx.Graph) -> torch.fx.Graph:
    """A copy of ``graph`` whose relative views (:func:`~torchtraj.core.graph_passes.strided`) call the scripted
    :func:`_strided_at_run_time`, and whose functional ``fill`` (which the tracer of PyTorch 2.13 records as a
    ``full_like`` without its options, an invalid graph) is the ``full_like`` it means: a tensor like its argument
    filled with the value."""
    copy = torch.fx.Graph()
    out = copy.graph_copy(graph, {})
    copy.output(out)
    for node in copy.nodes:
        if node.op == "call_function" and node.target is strided:
            node.target = relative_view
            node.args = (node.args[0], list(node.args[1]), list(node.args[2]), node.args[3])
        elif node.op == "call_function" and node.target == torch.ops.aten.fill.Scalar and not node.kwargs:
            node.target = torch.full_like
    return copy
