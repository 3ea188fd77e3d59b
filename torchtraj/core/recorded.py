r"""Recorded kernels: a function's operator graph traced once per input signature, simplified, and replayed.

An eager call of a ``torch.func`` transform of the user's functions (``vmap``, ``jacrev``, ``vjp``: the one-pass
expansion, :mod:`torchtraj.core.one_pass`) runs the transforms' Python machinery on every call (levels, wrappers,
batching rules) and issues every operator the derivative is made of, some of them more than once and some whose
results nobody reads. :class:`Recorded` traces the function once per input signature with ``make_fx`` on fake
tensors, functionalised (no in-place operators left), and simplifies the graph:

* dead code elimination: operators whose results reach no output;
* common subexpression elimination: an operator applied again to the same inputs (the transforms' repeated
  views, broadcasts and products) is computed once;
* view chains: a view of a view of ... a tensor is one ``as_strided`` of that tensor, with the size and strides
  the trace recorded (an input's strides are part of the signature, and an operator's output layout follows from
  its inputs'); a view of an input takes its offset relative to the input's own
  (:func:`~torchtraj.core.graph_passes.strided`), so that inputs at other offsets in their storages (the stages of
  a rollout, views of one buffer) share a record; views of one tensor that land on the same elements are one;
* constants: what reads no input of the graph and no tensor it holds by reference (``vmap``'s basis vectors, the
  identities and zeros of the derivatives, and what is computed from them alone) is computed once, at the trace.
* exact algebraic rewrites (:mod:`~torchtraj.core.graph_rewrites`): ``x + (−y)`` as ``x − y``, a gradient's two
  scattered halves as one stack, a split into one piece as the tensor split; and the components read of one tensor
  (``x[0]``, ``x[1]``) as views of one ``unbind``.

The passes are those of :mod:`torchtraj.core.graph_passes`.

Replayed, the graph calls the remaining operators directly, through the library's public functions where one
takes the operator's arguments (``torch.mul`` for ``aten.mul.Tensor``: the same operator, with a faster argument
parser than an ``OpOverload`` call). They are the eager call's operators, on the same data and in the same order,
less the duplicates: the results are the eager call's to the last bit (``tests/test_recorded.py``). On the CPU the
graph's code is traced once more by TorchScript and replayed by its interpreter (:mod:`~torchtraj.core.scripted`):
the same operators again, without a Python line each.

The signature is every tensor argument's size, strides, dtype and device, and every other
argument by value (numbers, strings) or identity (a problem, its constraints: kept alive by the record, so that
an identity is never reused). A function whose Python control flow reads tensor values (``if x > 0``, ``.item()``,
``nonzero``) cannot be traced on fake tensors: the trace raises, and that signature runs eager from then on.
Calls that need autograd (an input that requires grad, under grad mode) and calls inside another transform or
``torch.compile`` run eager.

Tensors the function reads from elsewhere than its tensor arguments are recorded as constants, by reference: a
change in place is seen by the replay, a tensor *replaced* by another object is not. So a signature is recorded
only where every such constant is a literal the function makes (``torch.tensor(2.0)``) or belongs to an argument
whose tensors cannot be replaced: a frozen dataclass (a :class:`~torchtraj.core.problem.Problem`'s bounds) or an
object whose class says so (``RECORDED_OWNER = True``: the constraints layout). One that reads a tensor from a
closure, a global or any other object (a user's reference trajectory, reassigned between calls) runs eager.

A trace costs about a hundred eager calls of the function at a small batch (its operators dispatched on fake
tensors; ``docs/benchmarks.md`` has the figures), so recording pays where the same shapes come back: a
controller's steps, a training loop, a long solve. When to trace is the ``record`` option of the solvers
(:func:`trace_at`): ``True``, a signature is traced at its :data:`TRACE_AT`-th call (repeated use known in
advance: a controller); ``None``, the default, at its :data:`TRACE_AT_AUTO`-th, about when its eager calls have
cost what its trace costs, so that recording never costs much more than twice the cheaper of eager and recorded
calls, whatever the number of calls to come (the ski rental rule): a short solve runs eager, a long one, or a solve
repeated often enough, replays; ``False``, never. A trace's cost does not depend on the sizes of the arguments (fake
tensors hold no data), an eager call's grows with them: a call counts ``1 + n // SIZE_SCALE`` times, ``n`` the
elements of its largest tensor argument (:data:`SIZE_SCALE`): the pendulum's expansion at B = 1024 is traced at its
twentieth call, about when replays would have saved what its trace costs, not at its hundredth. Each function
keeps :data:`LIMIT` records, the most recently used (and, apart, the call counts of four times as many signatures
not yet traced), shared by every solve in the process.
"""

from __future__ import annotations

import collections
import weakref
from typing import Any, Callable, Optional

import torch
import torch.utils._pytree as pytree
from torch.func import functionalize

from .graph_passes import hoisted, output_values, simplify
from .graphs import capturing
from .scripted import Scripted, scripted

#: Records kept per function (input signatures: batch sizes, horizons, problems, dtypes, devices).
LIMIT = 32
#: A signature is traced at its eighth call: one seen a few times only (a large batch's size for the iterations
#: after some instances finished, a line search's rare number of trial steps) runs eager and costs no trace.
TRACE_AT = 8
#: With ``record=None`` (the solvers' default), a signature is traced at its hundredth call: about what a trace
#: costs in eager calls at a small batch (module docstring).
TRACE_AT_AUTO = 100
#: A call whose largest tensor argument holds ``n`` elements counts ``1 + n // SIZE_SCALE`` calls towards its
#: signature's trace (module docstring): the pendulum's expansion (``X (B, 51, 2)``) counts 1 up to B = 245 and 5 at
#: B = 1024, where a replay saves ten times what it saves at B = 1 and the trace costs as much.
SIZE_SCALE = 25_000

_EAGER = object()  # a signature whose trace failed: run the function itself
_INSTANCES: "weakref.WeakSet[Recorded]" = weakref.WeakSet()  # for forget()
# the torch.func transforms the call is inside (None: none); a function of torch's private API, so looked up softly
_TRANSFORMS = getattr(torch._C._functorch, "peek_interpreter_stack", None)


def forget() -> None:
    """Drop every function's records and call counts: the next calls run as in a new process (a benchmark that
    counts a cold solve)."""
    for recorded in list(_INSTANCES):
        recorded.records.clear()
        recorded.calls.clear()
        recorded.loops.clear()


def traces() -> int:
    """The signatures traced so far in this process, by every recorded function (failed traces included): a
    benchmark repeats a warm-up until it traces nothing new."""
    return sum(recorded.traces for recorded in list(_INSTANCES))


def under_transform() -> bool:
    """Whether the caller runs inside a ``torch.func`` transform (``vmap``, ``grad``, and a trace's
    ``functionalize``)."""
    return _TRANSFORMS is not None and _TRANSFORMS() is not None


def trace_at(record: Optional[bool]) -> Optional[int]:
    """The call of a signature at which the option ``record`` traces it: :data:`TRACE_AT` (``True``),
    :data:`TRACE_AT_AUTO` (``None``, the default), or ``None``: never (``False``)."""
    if record is False:
        return None
    return TRACE_AT if record else TRACE_AT_AUTO


class Recorded:
    """``fn`` recorded per input signature and replayed (module docstring). Call it as ``fn``; ``fn`` takes and
    returns pytrees (tuples, lists, dicts, ``None``) of tensors and other values; its outputs must be tensors or
    ``None``."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self.records: collections.OrderedDict = collections.OrderedDict()  # signature -> record
        self.calls: collections.OrderedDict = collections.OrderedDict()  # signature -> calls, until traced
        self.traces = 0  # signatures traced (failed ones included)
        self.loops: collections.OrderedDict = collections.OrderedDict()  # (signature, varying) -> hoisted split
        _INSTANCES.add(self)

    def __call__(self, *args, trace_at: int = TRACE_AT):
        """``fn(*args)``, replayed from the record of the arguments' signature, which is traced at its
        ``trace_at``-th call (eager before)."""
        if torch.compiler.is_compiling():  # traced by torch.compile: the function itself, nothing of the record's
            return self.fn(*args)
        leaves, _, record = self._lookup(args, 1, trace_at)
        if record is None:
            return self.fn(*args)
        graph, unflatten, _ = record
        return unflatten(graph.forward(*(leaf for leaf in leaves if isinstance(leaf, torch.Tensor))))

    def option(self, record: Optional[bool]) -> Callable:
        """``fn`` as the solvers' option ``record`` asks (:func:`trace_at`): ``fn`` itself where it says never
        (``False``), else this record's calls, each signature traced at the call the option names."""
        at = trace_at(record)
        return self.fn if at is None else lambda *args: self(*args, trace_at=at)

    def loop(self, *args, calls: int, trace_at: int, varying: int) -> Optional[Callable]:
        """A loop's calls of ``fn``, ``calls`` of them, that change only the first ``varying`` tensors of ``args``
        (in the order of their leaves: a rollout's state and stage operands; the rest, its parameters, stay): ``None``
        while they are not worth a trace (the ``calls`` are counted, and the caller makes them eager: a rollout's
        ``N`` stages under one ``vmap``) or where it failed, else ``step(*tensors)``, ``fn`` with those tensors in
        their places, replayed with the operators that read only the other tensors computed once, here
        (:func:`~torchtraj.core.graph_passes.hoisted`), and without a lookup a call. The trace, at the call that
        brings the count to ``trace_at``, is made from ``args``."""
        if torch.compiler.is_compiling():
            return None
        leaves, key, record = self._lookup(args, calls, trace_at)
        if record is None:
            return None
        graph, unflatten, _ = record
        tensors = [leaf for leaf in leaves if isinstance(leaf, torch.Tensor)]
        fixed = tensors[varying:]
        if (key, varying) not in self.loops:
            self.loops[key, varying] = _scripted_split(graph, varying, tensors)
            if len(self.loops) > LIMIT:
                self.loops.popitem(last=False)
        split = self.loops[key, varying]
        if split is None:
            return lambda *moving: unflatten(graph.forward(*moving, *fixed))
        prologue, body = split
        values = prologue.forward(*tensors)
        return lambda *moving: unflatten(body.forward(*moving, *fixed, *values))

    def _lookup(self, args: tuple, calls: int, trace_at: int) -> tuple:
        """``(leaves, signature, record)`` of ``args``: the record that replays them, traced here where these
        ``calls`` bring the signature's count to ``trace_at``; ``None`` while the signature is not worth a trace, where
        its trace failed, or where the call must run eager (:func:`_must_run_eager`)."""
        leaves, key = _key(args)
        if _must_run_eager(leaves):
            return leaves, key, None
        record = self.records.get(key)
        if record is None:
            size = max((leaf.numel() for leaf in leaves if isinstance(leaf, torch.Tensor)), default=0)
            if not self._count(key, calls * (1 + size // SIZE_SCALE), trace_at):
                return leaves, key, None
            record = self._store(key, args)
        self.records.move_to_end(key)
        return leaves, key, None if record[0] is _EAGER else record

    def _count(self, key, calls: int, trace_at: int) -> bool:
        """Add ``calls`` to the count of ``key`` (not yet recorded); whether it reached ``trace_at``."""
        # counted apart from the records, so that signatures seen a few times (a controller whose problem is
        # rebuilt with new parameters at every step) never push a record out
        count = self.calls.pop(key, 0) + calls
        if count < trace_at:
            self.calls[key] = count
            if len(self.calls) > 4 * LIMIT:
                self.calls.popitem(last=False)
            return False
        return True

    def _store(self, key, args: tuple) -> tuple:
        record = self.records[key] = self._trace(*pytree.tree_flatten(args))
        if len(self.records) > LIMIT:
            self.records.popitem(last=False)
        return record

    def _trace(self, leaves: list, spec) -> tuple:
        """``(graph, its outputs' unflatten, the non-tensor arguments kept alive)``, or ``(_EAGER, None, ...)``."""
        self.traces += 1
        tensor_at = [i for i, leaf in enumerate(leaves) if isinstance(leaf, torch.Tensor)]
        out_spec = []

        def flat(*tensors):
            full = list(leaves)
            for i, t in zip(tensor_at, tensors):
                full[i] = t
            out, tree = pytree.tree_flatten(self.fn(*pytree.tree_unflatten(full, spec)))
            out_spec.append(tree)
            return out

        kept = [leaf for leaf in leaves if not isinstance(leaf, torch.Tensor)]
        tensors = [leaves[i] for i in tensor_at]
        try:
            from torch.fx.experimental.proxy_tensor import make_fx

            graph = make_fx(functionalize(flat, remove="mutations"), tracing_mode="fake",
                            _allow_non_fake_inputs=True)(*tensors)
            if not all(isinstance(v, torch.Tensor) or v is None for v in output_values(graph)) \
                    or _foreign_constants(graph, kept):
                return _EAGER, None, kept
            return scripted(simplify(graph), tensors), _unflattener(out_spec[-1]), kept
        except Exception:  # control flow on tensor values, an operator fake tensors lack: eager from now on
            return _EAGER, None, kept


def _scripted_split(graph, varying: int, tensors: list) -> Optional[tuple]:
    """The hoisted ``(prologue, body)`` of ``graph`` (:func:`~torchtraj.core.graph_passes.hoisted`), each replayed
    by TorchScript where ``graph`` is (:mod:`~torchtraj.core.scripted`); ``tensors``: the inputs of a call."""
    split = hoisted(graph.module if isinstance(graph, Scripted) else graph, varying)
    if split is None or not isinstance(graph, Scripted):
        return split
    prologue, body = split
    values = prologue.forward(*tensors)
    return scripted(prologue, tensors), scripted(body, [*tensors, *values])


def _owner(value) -> bool:
    """Whether ``value``'s tensors cannot be replaced: a frozen dataclass, or a class with ``RECORDED_OWNER``."""
    params = getattr(type(value), "__dataclass_params__", None)
    return (params is not None and params.frozen) or getattr(type(value), "RECORDED_OWNER", False)


def _owned_tensors(objects: list, depth: int = 3) -> set:
    """The storages of the tensors held by those of ``objects`` that are owners (:func:`_owner`), in their
    attributes and the dictionaries, sequences and owners these hold, ``depth`` levels deep."""
    owned, seen = set(), set()

    def visit(value, level):
        if isinstance(value, torch.Tensor):
            owned.add(value.untyped_storage().data_ptr())
        elif level < depth and id(value) not in seen:
            seen.add(id(value))
            if isinstance(value, dict):
                children = value.values()
            elif isinstance(value, (list, tuple)):
                children = value
            elif _owner(value):
                children = vars(value).values()
            else:
                return
            for child in children:
                visit(child, level + 1)

    for obj in objects:
        visit(obj, 0)
    return owned


def _foreign_constants(graph: torch.fx.GraphModule, kept: list) -> bool:
    """Whether the trace read a tensor that is neither one of the arguments' objects' nor a literal it lifted."""
    owned = None
    for node in graph.graph.nodes:
        if node.op != "get_attr":
            continue
        value = getattr(graph, node.target)
        if not isinstance(value, torch.Tensor) or all(user.target == torch.ops.aten.lift_fresh_copy.default
                                                      for user in node.users):
            continue
        owned = _owned_tensors(kept) if owned is None else owned
        if value.untyped_storage().data_ptr() not in owned:
            return True
    return False


def _must_run_eager(leaves: list) -> bool:
    if under_transform():
        return True
    if capturing():
        return True
    return torch.is_grad_enabled() and any(isinstance(leaf, torch.Tensor) and leaf.requires_grad for leaf in leaves)


def _key(args: tuple) -> tuple:
    """``(leaves, signature)`` of ``args``."""
    flat = _flatten(args)
    if flat is None:  # containers that only pytree knows (named tuples, ordered dictionaries)
        leaves, spec = pytree.tree_flatten(args)
        return leaves, (spec,) + tuple(_signature(leaf) for leaf in leaves)
    return flat


def _flatten(args: tuple):
    """``(leaves, key)``: ``pytree.tree_flatten(args)``'s leaves and a signature of them and of the containers
    (tuples, lists, dictionaries and their keys), made without a ``TreeSpec`` (whose hash, taken at every lookup,
    walks the tree); ``None`` where ``args`` hold another container pytree knows."""
    leaves, key = [], []
    pending = [args]  # depth first, left to right: pytree's order of the leaves
    while pending:
        value = pending.pop()
        kind = type(value)
        if kind is torch.Tensor:
            leaves.append(value)
            key.append(_tensor_signature(value))
        elif kind is tuple or kind is list:
            key.append((kind, len(value)))
            pending.extend(reversed(value))
        elif kind is dict:
            key.append((dict, tuple(value)))
            pending.extend(reversed(value.values()))
        elif isinstance(value, (tuple, list, dict, collections.deque)) or kind in pytree.SUPPORTED_NODES:
            return None
        else:
            leaves.append(value)
            key.append(_signature(value))
    return leaves, tuple(key)


def _unflattener(spec) -> Callable:
    """``spec``'s ``tree_unflatten`` of a replay's outputs, without pytree where the outputs are one tensor or a
    flat tuple or list of them."""
    if spec.is_leaf():
        return lambda out: out[0]
    if spec.type in (tuple, list) and all(child.is_leaf() for child in spec.children()):
        return spec.type
    return lambda out: pytree.tree_unflatten(out, spec)


def _tensor_signature(t: torch.Tensor) -> tuple:
    # not the storage offset: the replay's views of an input are relative to its offset (graph_passes.strided)
    return (t.shape, t.stride(), t.dtype, t.device)


def _signature(leaf: Any) -> Any:
    if isinstance(leaf, torch.Tensor):
        return _tensor_signature(leaf)
    if leaf is None or isinstance(leaf, (bool, int, float, str, torch.dtype, torch.device)):
        return (type(leaf), leaf)
    return (type(leaf), id(leaf))
