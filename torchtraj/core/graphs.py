"""Opt-in CUDA graphs of the solvers' per-iteration kernels (``IPOptions.cuda_graphs``).

On a GPU a solver iteration at a moderate batch is bound by launches, not arithmetic: a few thousand small
kernels, each with its share of Python, dispatcher and launch cost (``python -m torchtraj.bench --grad
--device cuda``: 2,500 launches an interior-point iteration on ``linear_box``). A CUDA graph records a kernel's
launches once and replays them as one. :func:`graphed` wraps a function of tensors:

* its arguments are flattened: tensors, ``None``, dataclasses holding tensors (iterates, LQR matrices, a problem
  with its parameters), tuples, lists and dicts of them, and objects that name the attributes they are made from
  (``graph_rebuilt_from``: a problem's :class:`~torchtraj.core.constraints.Constraints`). Options, dataclasses
  without tensors, are part of the graph's key by value; any other value (a problem's functions) is a constant
  of the graph, held by identity. So a solve of a new problem object with the same functions and new parameter
  tensors, as a training step makes, replays the graphs of the last one;
* on the first call for a set of shapes, dtypes and constants it runs the function twice on a side stream
  (warm-up: lazy initialisation, workspace allocation) and captures a third run into a graph reading static
  copies of the tensor arguments;
* on every call it copies the arguments into those copies, replays the graph and returns clones of its outputs
  (a later replay overwrites the static outputs).

The wrapped function must not synchronise with the host (no ``.item()``, ``bool(tensor)``, no host-to-device copy)
and must launch the same kernels whatever the values: the solvers' kernels decide per instance by masks, and the
loops with host decisions (line-search rounds, regularisation attempts, iterations) stay in Python around them.
Answers are those of the eager kernels to rounding (the same kernels run). Each wrapper keeps
:data:`GRAPHS_KEPT` graphs, the most recently used, each with its own memory pool. Code that must take another
path while it is captured (a LAPACK-like call that reads its status on the host) asks :func:`capturing`.

**Checked on a CPU.** :func:`emulated` makes a solve on the CPU take the graphed path: each wrapped call runs
as if captured (:func:`capturing` true), under a dispatch mode that refuses the operators that read device memory
on the host or a solver's status (:data:`HOST_READS`), and falls back to eager with the same warning as a failed
capture. So the contract above is tested without a GPU (``tests/test_graphs_on_cpu.py``); what a CPU cannot show
(a copy from host memory into a graph) still needs one.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings
from collections import OrderedDict
from typing import Callable

import torch
from torch import Tensor
from torch.utils._python_dispatch import TorchDispatchMode

#: Graphs kept per wrapped function (least recently used dropped first).
GRAPHS_KEPT = 8

#: operators that read a tensor on the host (a value, a count, a solver's status): a CUDA graph cannot hold them
HOST_READS = frozenset({
    "aten._local_scalar_dense", "aten.is_nonzero", "aten.item", "aten.equal", "aten.nonzero", "aten.masked_select",
    "aten._unique2", "aten.unique_consecutive", "aten.unique_dim", "aten._linalg_check_errors", "aten._linalg_eigh",
    "aten._linalg_svd", "aten.linalg_eig",
})

_EMULATED = False  # graphed calls on the CPU run as if captured (:func:`emulated`)
_CAPTURING = False  # an emulated capture is running


def capturing() -> bool:
    """Whether a CUDA graph is being captured now (or, on the CPU, emulated: :func:`emulated`)."""
    return _CAPTURING or (torch.cuda.is_available() and torch.cuda.is_current_stream_capturing())


@contextlib.contextmanager
def emulated():
    """Solves inside take the graphed path on the CPU, each graphed call checked as a capture (module docstring)."""
    global _EMULATED
    before, _EMULATED = _EMULATED, True
    try:
        yield
    finally:
        _EMULATED = before


class _HostReadsRefused(TorchDispatchMode):
    """Raises ``RuntimeError`` at an operator of :data:`HOST_READS`, at indexing by a boolean mask (its count is
    read) and at an operator asked to check its errors."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.name().split(".")[0].replace("::", ".")
        if name in HOST_READS or _by_mask(name, args) or kwargs.get("check_errors", False):
            raise RuntimeError(f"{func.name()} reads device memory on the host, which a CUDA graph cannot capture")
        return func(*args, **kwargs)


def _by_mask(name: str, args: tuple) -> bool:
    """Whether an operator indexes by a boolean mask (whose count of true entries it reads)."""
    if name not in ("aten.index", "aten.index_put", "aten.index_put_") or len(args) < 2 or args[1] is None:
        return False
    return any(isinstance(index, Tensor) and index.dtype == torch.bool for index in args[1])


def _emulated_capture(fn: Callable, args: tuple):
    """``fn(*args)`` as if captured: :func:`capturing` true, host reads refused."""
    global _CAPTURING
    before, _CAPTURING = _CAPTURING, True
    try:
        with _HostReadsRefused():
            return fn(*args)
    finally:
        _CAPTURING = before


def _flatten(value, tensors: list, key: list):
    """Append the tensors of ``value`` to ``tensors`` and a description of everything else to ``key``; return a
    template from which :func:`_rebuild` makes ``value`` again with other tensors."""
    if isinstance(value, Tensor):
        tensors.append(value)
        key.append(("T", tuple(value.shape), value.dtype, value.device, value.stride()))
        return _Slot(len(tensors) - 1)
    rebuilt_from = getattr(type(value), "graph_rebuilt_from", None)
    if rebuilt_from is not None:  # made again from these attributes, its constructor's arguments
        key.append(("R", type(value)))
        return (type(value), {name: _flatten(getattr(value, name), tensors, key) for name in rebuilt_from})
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        if _holds_tensors(value):
            key.append(("D", type(value)))
            return (type(value), {f.name: _flatten(getattr(value, f.name), tensors, key)
                                  for f in dataclasses.fields(value)})
        settings = (type(value), tuple(getattr(value, f.name) for f in dataclasses.fields(value)))
        try:  # options: by value, as a new copy of the same settings is the same graph
            hash(settings)
            key.append(("V", settings))
        except TypeError:
            key.append(("C", id(value)))
        return _Constant(value)
    if isinstance(value, (tuple, list)):
        key.append(("S", type(value), len(value)))
        return (type(value), [_flatten(v, tensors, key) for v in value])
    if isinstance(value, dict):
        key.append(("M", tuple(value)))
        return (dict, {k: _flatten(v, tensors, key) for k, v in value.items()})
    if value is None or isinstance(value, (bool, int, float, str, torch.dtype, torch.device)):
        key.append(("V", value))  # by value: a float argument is a new object at every call
    else:
        key.append(("C", id(value)))
    return _Constant(value)


def _holds_tensors(value) -> bool:
    """Whether a dataclass is data (iterates, models, LQR matrices, a problem with its parameters) rather than a
    constant (options)."""
    def tensors_in(v) -> bool:
        if isinstance(v, Tensor):
            return True
        if isinstance(v, dict):
            return any(tensors_in(x) for x in v.values())
        return isinstance(v, (tuple, list)) and any(tensors_in(x) for x in v)

    return any(tensors_in(getattr(value, f.name)) for f in dataclasses.fields(value))


@dataclasses.dataclass(frozen=True)
class _Slot:
    index: int


@dataclasses.dataclass(frozen=True)
class _Constant:
    value: object


def _rebuild(template, tensors: list):
    if isinstance(template, _Slot):
        return tensors[template.index]
    if isinstance(template, _Constant):
        return template.value
    kind, parts = template
    if isinstance(parts, dict):
        values = {k: _rebuild(v, tensors) for k, v in parts.items()}
        return values if kind is dict else kind(**values)  # a dict or a dataclass
    values = [_rebuild(v, tensors) for v in parts]
    return kind(values) if kind in (tuple, list) else kind(*values)  # a named tuple takes its fields


@dataclasses.dataclass
class _Captured:
    graph: torch.cuda.CUDAGraph
    inputs: list  # static copies of the tensor arguments
    outputs: list  # the graph's output tensors
    template: object  # the output's structure
    arguments: tuple  # the arguments made from the static copies: the graph reads their tensors (and those their
    # constructors made, as a Constraints' knot mask), which must live as long as it


class Graphed:
    """``fn`` replayed from CUDA graphs (module docstring); eager where no tensor argument is on a CUDA device."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self.graphs: OrderedDict = OrderedDict()
        self.eager: set = set()  # keys whose capture failed
        self.captures = 0  # graphs captured so far

    def __call__(self, *args):
        tensors, key = [], []
        template = _flatten(args, tensors, key)
        on_gpu = any(t.is_cuda for t in tensors)
        if (not on_gpu and not _EMULATED) or capturing():
            return self.fn(*args)
        key = tuple(key)
        if key in self.eager:
            return self.fn(*args)
        if not on_gpu:  # emulated on the CPU: checked as a capture at every call, not replayed
            try:
                return _emulated_capture(self.fn, args)
            except RuntimeError as exc:
                return self._eager_from_now(key, exc, args)
        captured = self.graphs.get(key)
        if captured is None:
            try:
                captured = self._capture(template, tensors)
            except RuntimeError as exc:  # an operation that cannot be captured: this kernel stays eager
                return self._eager_from_now(key, exc, args)
            self.graphs[key] = captured
            while len(self.graphs) > GRAPHS_KEPT:
                self.graphs.popitem(last=False)
        else:
            self.graphs.move_to_end(key)
            for static, value in zip(captured.inputs, tensors):
                static.copy_(value)
        captured.graph.replay()
        return _rebuild(captured.template, [t.clone() for t in captured.outputs])

    def _eager_from_now(self, key: tuple, exc: RuntimeError, args: tuple):
        """``fn(*args)`` eager, and eager at every later call with ``key``: its capture failed with ``exc``."""
        warnings.warn(f"torchtraj: {getattr(self.fn, '__qualname__', self.fn)} runs without a CUDA graph ({exc})",
                      RuntimeWarning, stacklevel=3)
        self.eager.add(key)
        return self.fn(*args)

    def _capture(self, template, tensors: list) -> _Captured:
        inputs = [t.clone() for t in tensors]
        args = _rebuild(template, inputs)
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(2):
                self.fn(*args)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            out = self.fn(*args)
        self.captures += 1
        outputs = []
        out_template = _flatten(out, outputs, [])
        return _Captured(graph, inputs, outputs, out_template, args)


def graphs_used(options, device: torch.device) -> bool:
    """Whether a solve's kernels are replayed from CUDA graphs: ``options.cuda_graphs`` asked for, not
    ``options.compile``, on a CUDA ``device`` (elsewhere no argument is flattened)."""
    return getattr(options, "cuda_graphs", False) and not getattr(options, "compile", False) \
        and (device.type == "cuda" or _EMULATED)


_GRAPHED: dict = {}


def graphed(fn: Callable) -> Graphed:
    """The one :class:`Graphed` wrapper of ``fn`` (module-level functions: every solve shares its graphs)."""
    wrapper = _GRAPHED.get(fn)
    if wrapper is None:
        wrapper = _GRAPHED[fn] = Graphed(fn)
    return wrapper


def captures() -> int:
    """Graphs captured so far by every :func:`graphed` wrapper (a run that captured none replayed its graphs)."""
    return sum(wrapper.captures for wrapper in _GRAPHED.values())
