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
  its inputs'), its offset relative to the tensor's own (:func:`strided`), so that inputs at other offsets in
  their storages (the stages of a rollout, views of one buffer) share a record.

Replayed, the graph calls the remaining operators directly, through the library's public functions where one
takes the operator's arguments (``torch.mul`` for ``aten.mul.Tensor``: the same operator, with a faster argument
parser than an ``OpOverload`` call). They are the eager call's operators, on the same data and in the same order,
less the duplicates: the results are the eager call's to the last bit (``tests/test_recorded.py``).

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

A trace costs about a hundred eager calls of the function (a third of a second for the pendulum's expansion),
so recording pays where the same shapes come back: a controller's steps, a training loop, a long solve. A
signature is traced at its :data:`TRACE_AT`-th call, and each function keeps :data:`LIMIT` records, the most
recently used (and, apart, the call counts of four times as many signatures not yet traced).
"""

from __future__ import annotations

import collections
from typing import Any, Callable

import torch
import torch.utils._pytree as pytree
from torch import Tensor
from torch.func import functionalize

#: Records kept per function (input signatures: batch sizes, horizons, problems, dtypes, devices).
LIMIT = 32
#: A signature is traced at its eighth call: one seen a few times only (a large batch's size for the iterations
#: after some instances finished, a line search's rare number of trial steps) runs eager and costs no trace.
TRACE_AT = 8

_EAGER = object()  # a signature whose trace failed: run the function itself
# the torch.func transforms the call is inside (None: none); a function of torch's private API, so looked up softly
_TRANSFORMS = getattr(torch._C._functorch, "peek_interpreter_stack", None)

_VIEWS = {
    torch.ops.aten.view.default, torch.ops.aten._unsafe_view.default, torch.ops.aten.expand.default,
    torch.ops.aten.select.int, torch.ops.aten.slice.Tensor, torch.ops.aten.unsqueeze.default,
    torch.ops.aten.squeeze.dim, torch.ops.aten.squeeze.dims, torch.ops.aten.squeeze.default,
    torch.ops.aten.transpose.int, torch.ops.aten.permute.default, torch.ops.aten.t.default,
    torch.ops.aten.alias.default, torch.ops.aten.diagonal.default, torch.ops.aten.as_strided.default,
    torch.ops.aten.unfold.default,
}


class Recorded:
    """``fn`` recorded per input signature and replayed (module docstring). Call it as ``fn``; ``fn`` takes and
    returns pytrees (tuples, lists, dicts, ``None``) of tensors and other values; its outputs must be tensors or
    ``None``."""

    def __init__(self, fn: Callable):
        self.fn = fn
        self.records: collections.OrderedDict = collections.OrderedDict()  # signature -> record
        self.calls: collections.OrderedDict = collections.OrderedDict()  # signature -> calls, until traced
        self.traces = 0  # signatures traced (failed ones included)

    def __call__(self, *args):
        if torch.compiler.is_compiling():  # traced by torch.compile: the function itself, nothing of the record's
            return self.fn(*args)
        flat = _flatten(args)
        if flat is None:  # containers that only pytree knows (named tuples, ordered dictionaries)
            leaves, spec = pytree.tree_flatten(args)
            key = (spec,) + tuple(_signature(leaf) for leaf in leaves)
        else:
            leaves, key = flat
        if _must_run_eager(leaves):
            return self.fn(*args)
        record = self.records.get(key)
        if record is None:
            # counted apart from the records, so that signatures seen a few times (a controller whose problem is
            # rebuilt with new parameters at every step) never push a record out
            calls = self.calls.pop(key, 0) + 1
            if calls < TRACE_AT:
                self.calls[key] = calls
                if len(self.calls) > 4 * LIMIT:
                    self.calls.popitem(last=False)
                return self.fn(*args)
            record = self.records[key] = self._trace(*pytree.tree_flatten(args))
            if len(self.records) > LIMIT:
                self.records.popitem(last=False)
        self.records.move_to_end(key)
        graph, unflatten, _ = record
        if graph is _EAGER:
            return self.fn(*args)
        return unflatten(graph.forward(*(leaf for leaf in leaves if isinstance(leaf, torch.Tensor))))

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
            if not all(isinstance(v, torch.Tensor) or v is None for v in _output_values(graph)) \
                    or _foreign_constants(graph, kept):
                return _EAGER, None, kept
            return simplify(graph), _unflattener(out_spec[-1]), kept
        except Exception:  # control flow on tensor values, an operator fake tensors lack: eager from now on
            return _EAGER, None, kept


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
    if _TRANSFORMS is not None and _TRANSFORMS() is not None:
        return True
    if any(isinstance(leaf, torch.Tensor) and leaf.is_cuda for leaf in leaves) \
            and torch.cuda.is_current_stream_capturing():
        return True
    return torch.is_grad_enabled() and any(isinstance(leaf, torch.Tensor) and leaf.requires_grad for leaf in leaves)


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
            key.append((value.shape, value.stride(), value.dtype, value.device))
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


def _signature(leaf: Any) -> Any:
    if isinstance(leaf, torch.Tensor):  # not the storage offset: the replay's strided views are relative
        return (tuple(leaf.shape), leaf.stride(), leaf.dtype, leaf.device)
    if leaf is None or isinstance(leaf, (bool, int, float, str, torch.dtype, torch.device)):
        return (type(leaf), leaf)
    return (type(leaf), id(leaf))


def _output_values(graph: torch.fx.GraphModule) -> list:
    """The trace's value (a fake tensor, or what the function returned) of each output."""
    return [node.meta.get("val") if isinstance(node, torch.fx.Node) else node for node in _output_nodes(graph.graph)]


def simplify(graph: torch.fx.GraphModule) -> torch.fx.GraphModule:
    """``graph`` (functional: no operator mutates a tensor) with dead code, repeated operators and view chains
    removed (module docstring)."""
    from torch.fx.passes.dialect.common.cse_pass import CSEPass

    graph.graph.eliminate_dead_code()
    graph.recompile()
    groups = _storage_groups(graph)
    mutating = {n.target.overloadpacket for n in graph.graph.nodes
                if n.op == "call_function" and hasattr(n.target, "_schema") and n.target._schema.is_mutable}
    graph = CSEPass(banned_ops=mutating)(graph).graph_module
    _collapse_views(graph.graph)
    _drop_identity_views(graph.graph)
    _separate_outputs(graph.graph, groups)
    graph.graph.eliminate_dead_code()
    _relative_strides(graph.graph)
    _public_functions(graph.graph)
    graph.graph.lint()
    graph.recompile()
    return graph


def strided(base: Tensor, size: tuple, stride: tuple, shift: int) -> Tensor:
    """``base``'s elements at ``size``, ``stride``, starting ``shift`` elements after ``base``'s own first one:
    a strided view whose offset follows ``base``'s, wherever ``base`` lies in its storage."""
    return torch.as_strided(base, size, stride, base.storage_offset() + shift)


def _relative_strides(graph: torch.fx.Graph) -> None:
    """Each ``as_strided`` of an input's storage as a :func:`strided` view of its argument, its offset relative to
    the argument's (from the trace), so that a replay of inputs at other offsets in their storages reads their own
    elements: a rollout's stages are views of one buffer at offsets one stage apart. (A tensor the graph makes
    lies where the trace's did.)"""
    inputs = [n.meta.get("val") for n in graph.nodes if n.op == "placeholder"]
    storages = [v.untyped_storage() for v in inputs if isinstance(v, torch.Tensor)]
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target != torch.ops.aten.as_strided.default:
            continue
        base, size, stride, *offset = node.args
        val, base_val = node.meta.get("val"), base.meta.get("val") if isinstance(base, torch.fx.Node) else None
        if not (isinstance(val, torch.Tensor) and isinstance(base_val, torch.Tensor) and _static(val)
                and _static(base_val)):
            raise _NotRecordable("a strided view whose offsets the trace did not fix")
        if not any(base_val.untyped_storage() is storage for storage in storages):
            continue
        node.target = strided
        node.args = (base, size, stride, val.storage_offset() - base_val.storage_offset())


class _NotRecordable(Exception):
    pass


def _public_functions(graph: torch.fx.Graph) -> None:
    """Operators replayed through the library's public functions (``torch.mul``, ``Tensor.view``), which call the
    same operator: an ``OpOverload`` call matches its Python arguments against the schema on every call, a public
    function's parser is compiled, and a graph of small tensors spends most of its time in these calls."""
    for node in graph.nodes:
        if node.op == "call_function" and set(node.kwargs) <= _PUBLIC_KEYWORDS:
            node.target = _PUBLIC.get(node.target, node.target)


def _public_table() -> dict:
    """``{operator overload: public function}`` for the overloads whose public function takes the schema's
    arguments under the same names and positions (the rest are replayed as overloads)."""
    aten = torch.ops.aten
    table = {aten.view.default: torch.Tensor.view, aten.expand.default: torch.Tensor.expand,
             aten.as_strided.default: torch.as_strided}
    for name, overloads in {
        "mul": ("Tensor", "Scalar"), "add": ("Tensor",), "sub": ("Tensor",), "div": ("Tensor",), "neg": ("default",),
        "sin": ("default",), "cos": ("default",), "tan": ("default",), "exp": ("default",), "log": ("default",),
        "sqrt": ("default",), "rsqrt": ("default",), "tanh": ("default",), "sigmoid": ("default",),
        "abs": ("default",), "reciprocal": ("default",), "pow": ("Tensor_Scalar", "Tensor_Tensor"),
        "select": ("int",), "permute": ("default",), "transpose": ("int",), "unsqueeze": ("default",),
        "squeeze": ("dim",), "diagonal": ("default",), "stack": ("default",), "cat": ("default",),
        "sum": ("dim_IntList",), "amax": ("default",), "where": ("self",), "clone": ("default",),
        "mm": ("default",), "bmm": ("default",), "baddbmm": ("default",), "addmm": ("default",),
        "split_with_sizes": ("default",), "remainder": ("Scalar", "Tensor"), "maximum": ("default",),
        "minimum": ("default",), "lt": ("Scalar", "Tensor"), "gt": ("Scalar", "Tensor"), "le": ("Scalar", "Tensor"),
        "ge": ("Scalar", "Tensor"), "eq": ("Scalar", "Tensor"),
    }.items():
        for overload in overloads:
            table[getattr(getattr(aten, name), overload)] = getattr(torch, name)
    return table


_PUBLIC = _public_table()
_PUBLIC_KEYWORDS = {"alpha", "beta", "dtype", "memory_format"}


def _output(graph: torch.fx.Graph) -> torch.fx.Node:
    return next(n for n in graph.nodes if n.op == "output")


def _output_nodes(graph: torch.fx.Graph) -> list:
    return pytree.tree_leaves(_output(graph).args)


def _storage_groups(graph: torch.fx.GraphModule) -> list:
    """Per output, the index of the first output that shares its storage (views of one tensor), from the trace."""
    storages = [val.untyped_storage() if isinstance(val, torch.Tensor) else None for val in _output_values(graph)]
    return [next(j for j in range(i + 1) if storages[j] is not None and storages[j] is s) if s is not None else i
            for i, s in enumerate(storages)]


def _base(node):
    while isinstance(node, torch.fx.Node) and node.op == "call_function" and node.target in _VIEWS:
        node = node.args[0]
    return node


def _separate_outputs(graph: torch.fx.Graph, groups: list) -> None:
    """Outputs that the eager function returned as separate tensors but that common subexpressions made views of
    one get copies (a caller may write into one of them)."""
    out = _output(graph)
    leaves, spec = pytree.tree_flatten(out.args)
    owner: dict = {}
    for i, node in enumerate(leaves):
        if not isinstance(node, torch.fx.Node):
            continue
        base = _base(node)
        first = owner.setdefault(base, groups[i])
        if first != groups[i]:
            with graph.inserting_before(out):
                copy = graph.call_function(torch.ops.aten.clone.default, (node,))
            copy.meta = dict(node.meta)
            leaves[i] = copy
    out.args = pytree.tree_unflatten(leaves, spec)


def _collapse_views(graph: torch.fx.Graph) -> None:
    """Each view of a view (of a view ...) of a tensor as one ``as_strided`` of that tensor, from the sizes, strides
    and offset the fake tensors recorded."""
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in _VIEWS:
            continue
        parent = node.args[0]
        if not (isinstance(parent, torch.fx.Node) and parent.op == "call_function" and parent.target in _VIEWS):
            continue
        root = _base(parent)
        val = node.meta.get("val")
        if not isinstance(val, torch.Tensor) or not _static(val):
            continue
        with graph.inserting_before(node):
            strided = graph.call_function(torch.ops.aten.as_strided.default,
                                          (root, tuple(val.shape), tuple(val.stride()), val.storage_offset()))
        strided.meta = dict(node.meta)
        node.replace_all_uses_with(strided)
        graph.erase_node(node)


def _drop_identity_views(graph: torch.fx.Graph) -> None:
    """Views that return their tensor as it is (``vmap``'s ``permute`` of a batched vector to its own order) are
    that tensor: their uses read it."""
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in _VIEWS or not isinstance(node.args[0], torch.fx.Node):
            continue
        val, base_val = node.meta.get("val"), node.args[0].meta.get("val")
        if isinstance(val, torch.Tensor) and isinstance(base_val, torch.Tensor) and _static(val) \
                and _static(base_val) and (val.shape, val.stride(), val.storage_offset()) \
                == (base_val.shape, base_val.stride(), base_val.storage_offset()):
            node.replace_all_uses_with(node.args[0])
            graph.erase_node(node)


def _static(val: torch.Tensor) -> bool:
    return all(isinstance(s, int) for s in (*val.shape, *val.stride(), val.storage_offset()))
