r"""The simplification of a recorded operator graph (:mod:`torchtraj.core.recorded`): dead code, repeated
operators, view chains and identity views removed, exact algebraic rewrites (:mod:`~torchtraj.core.graph_rewrites`),
views of the same elements taken once, what reads no input computed once (constants), views of the inputs made
relative to their offsets, and the operators called through the library's public functions. Every pass keeps the
graph's results to the last bit.
"""

from __future__ import annotations

import operator
from typing import Optional

import torch
import torch.utils._pytree as pytree
from torch import Tensor

from .graph_rewrites import rewrite

_VIEWS = {
    torch.ops.aten.view.default, torch.ops.aten._unsafe_view.default, torch.ops.aten.expand.default,
    torch.ops.aten.select.int, torch.ops.aten.slice.Tensor, torch.ops.aten.unsqueeze.default,
    torch.ops.aten.squeeze.dim, torch.ops.aten.squeeze.dims, torch.ops.aten.squeeze.default,
    torch.ops.aten.transpose.int, torch.ops.aten.permute.default, torch.ops.aten.t.default,
    torch.ops.aten.alias.default, torch.ops.aten.diagonal.default, torch.ops.aten.as_strided.default,
    torch.ops.aten.unfold.default,
}


def output_values(graph: torch.fx.GraphModule) -> list:
    """The trace's value (a fake tensor, or what the function returned) of each output."""
    return [node.meta.get("val") if isinstance(node, torch.fx.Node) else node for node in _output_nodes(graph.graph)]


def simplify(graph: torch.fx.GraphModule) -> torch.fx.GraphModule:
    """``graph`` (functional: no operator mutates a tensor) with dead code, repeated operators and view chains
    removed (:mod:`~torchtraj.core.recorded`'s docstring)."""
    from torch.fx.passes.dialect.common.cse_pass import CSEPass

    graph.graph.eliminate_dead_code()
    graph.recompile()
    groups = _storage_groups(graph)
    _fold_constants(graph)
    mutating = {n.target.overloadpacket for n in graph.graph.nodes
                if n.op == "call_function" and hasattr(n.target, "_schema") and n.target._schema.is_mutable}
    graph = CSEPass(banned_ops=mutating)(graph).graph_module
    rewrite(graph.graph)
    _collapse_views(graph.graph)
    _drop_identity_views(graph.graph)
    _merge_equal_views(graph.graph)
    _separate_outputs(graph.graph, groups)
    graph.graph.eliminate_dead_code()
    _unbind_selects(graph.graph)
    _relative_strides(graph.graph)
    _public_functions(graph.graph)
    graph.graph.lint()
    graph.recompile()
    return graph


#: Operators whose result depends on their tensor arguments' sizes, dtypes and devices alone (a signature fixes
#: them), not on their values.
_FACTORIES = {
    torch.ops.aten.new_zeros.default, torch.ops.aten.new_ones.default, torch.ops.aten.new_full.default,
    torch.ops.aten.zeros_like.default, torch.ops.aten.ones_like.default, torch.ops.aten.full_like.default,
    torch.ops.aten.zeros.default, torch.ops.aten.ones.default, torch.ops.aten.full.default,
    torch.ops.aten.eye.default, torch.ops.aten.eye.m, torch.ops.aten.scalar_tensor.default,
    torch.ops.aten.arange.default, torch.ops.aten.arange.start, torch.ops.aten.arange.start_step,
}
#: Largest constant (bytes of its storage: an expanded tensor counts its one instance) that
#: :func:`_fold_constants` keeps with a graph; larger ones stay operators, whose arithmetic is their cost anyway.
FOLD_LIMIT = 1 << 17


def _fold_constants(graph: torch.fx.GraphModule) -> None:
    """Operators that read neither an input of the graph nor a tensor it holds by reference (factories such as
    ``vmap``'s basis vectors and identities, copies of the literals the function made, and the views and products
    of what they make) computed once, here, with the operators themselves, and kept with the graph as constants of
    at most :data:`FOLD_LIMIT` bytes. Not folded: random operators; an output, or a tensor an output is a view of
    (each call returns tensors of its own, which the caller may write into)."""
    values: dict = {}
    returned = set()
    for node in _output_nodes(graph.graph):
        while isinstance(node, torch.fx.Node) and node not in returned:
            returned.add(node)
            node = node.args[0] if node.op == "call_function" and node.target in _VIEWS else None
    for node in graph.graph.nodes:
        if node.op != "call_function" or torch.Tag.nondeterministic_seeded in getattr(node.target, "tags", ()) \
                or getattr(getattr(node.target, "_schema", None), "is_mutable", True):
            continue
        inputs = node.all_input_nodes
        if node.target in _FACTORIES:  # the tensor arguments lend their size, dtype and device alone
            env = {n: values[n] if n in values else _stand_in(n.meta.get("val")) for n in inputs}
            if any(v is None for v in env.values()):
                continue
        elif node.target is torch.ops.aten.lift_fresh_copy.default and inputs[0].op == "get_attr":
            env = {inputs[0]: getattr(graph, inputs[0].target)}  # a literal the function made, nobody else holds
        elif inputs and all(n in values for n in inputs):
            env = values
        else:
            continue
        try:
            value = node.target(*torch.fx.node.map_arg(node.args, env.__getitem__),
                                **torch.fx.node.map_arg(node.kwargs, env.__getitem__))
        except Exception:  # an operator that does not take the stand-ins: it stays in the graph
            continue
        if isinstance(value, Tensor) and value.untyped_storage().nbytes() <= FOLD_LIMIT:
            values[node] = value
    for i, node in enumerate(list(values)):
        if node in returned or all(user in values for user in node.users):
            continue  # returned, or read by constants alone (removed with them)
        name = f"_folded_{i}"
        graph.register_buffer(name, values[node], persistent=False)
        with graph.graph.inserting_before(node):
            constant = graph.graph.get_attr(name)
        constant.meta = {**node.meta, "val": values[node]}  # the constant's own layout, for the later passes
        node.replace_all_uses_with(constant)
    graph.graph.eliminate_dead_code()


def _stand_in(val) -> Optional[Tensor]:
    """A tensor of ``val``'s size, strides, dtype and device (zeros), for a factory that reads no values."""
    if not isinstance(val, Tensor) or not _static(val):
        return None
    return torch.empty_strided(val.shape, val.stride(), dtype=val.dtype, device=val.device).zero_()


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
        base, size, stride = node.args[:3]
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
        "split_with_sizes": ("default",), "unbind": ("int",), "remainder": ("Scalar", "Tensor"),
        "maximum": ("default",), "minimum": ("default",), "lt": ("Scalar", "Tensor"), "gt": ("Scalar", "Tensor"),
        "le": ("Scalar", "Tensor"), "ge": ("Scalar", "Tensor"), "eq": ("Scalar", "Tensor"),
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
    storages = [val.untyped_storage() if isinstance(val, torch.Tensor) else None for val in output_values(graph)]
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


def _merge_equal_views(graph: torch.fx.Graph) -> None:
    """Views of one tensor with the same size, strides and offset (a ``select`` and a collapsed chain that lands on
    the same elements, which common subexpression elimination cannot see as one) are the first of them."""
    first: dict = {}
    for node in list(graph.nodes):
        if node.op != "call_function" or node.target not in _VIEWS:
            continue
        val = node.meta.get("val")
        if not isinstance(val, torch.Tensor) or not _static(val):
            continue
        key = (node.args[0], tuple(val.shape), tuple(val.stride()), val.storage_offset(), val.dtype)
        if key in first:
            node.replace_all_uses_with(first[key])
            graph.erase_node(node)
        else:
            first[key] = node


def _unbind_selects(graph: torch.fx.Graph) -> None:
    """Two or more ``select``s of one tensor along one dimension (a vector's components, ``x[0]`` and ``x[1]`` of
    a dynamics function under ``vmap``) as one ``unbind`` of it, whose views they read: the same views, one call."""
    groups: dict = {}
    for node in graph.nodes:
        if node.op == "call_function" and node.target == torch.ops.aten.select.int \
                and isinstance(node.args[0], torch.fx.Node) and isinstance(node.meta.get("val"), torch.Tensor):
            base = node.args[0].meta.get("val")
            if not isinstance(base, torch.Tensor) or not _static(base):
                continue
            dim, index = node.args[1] % base.dim(), node.args[2] % base.shape[node.args[1]]
            groups.setdefault((node.args[0], dim), []).append((node, index))
    for (base, dim), selects in groups.items():
        if len(selects) < 2:
            continue
        with graph.inserting_before(selects[0][0]):
            parts = graph.call_function(torch.ops.aten.unbind.int, (base, dim))
        parts.meta = {}
        for node, index in selects:
            with graph.inserting_before(node):
                part = graph.call_function(operator.getitem, (parts, index))
            part.meta = dict(node.meta)
            node.replace_all_uses_with(part)
            graph.erase_node(node)


def _static(val: torch.Tensor) -> bool:
    return all(isinstance(s, int) for s in (*val.shape, *val.stride(), val.storage_offset()))


def hoisted(graph: torch.fx.GraphModule, varying: int) -> Optional[tuple]:
    """``(prologue, body)``: ``graph`` split for a loop of calls that change only its first ``varying`` inputs
    (loop-invariant code motion). The operators that read only the other inputs and constants (a rollout stage's
    products of parameters) are computed once, by ``prologue(*inputs)``, which returns those of their values that
    the rest reads; ``body(*inputs, *values)`` is the rest. ``None`` where nothing is left to hoist, where an
    operator mutates a tensor, or where an output would be hoisted (each call returns tensors of its own)."""
    nodes = list(graph.graph.nodes)
    fixed = set([n for n in nodes if n.op == "placeholder"][varying:])
    for node in nodes:
        if node.op == "get_attr":
            fixed.add(node)
        elif node.op == "call_function":
            schema = getattr(node.target, "_schema", None)
            if schema is not None and schema.is_mutable:
                return None
            if all(arg in fixed for arg in node.all_input_nodes):
                fixed.add(node)
    if any(node in fixed for node in _output_nodes(graph.graph)):
        return None
    hoist = [n for n in nodes if n.op == "call_function" and n in fixed and any(u not in fixed for u in n.users)]
    if not hoist:
        return None
    prologue, mapping, _ = _copy(graph.graph)
    prologue.output(tuple(mapping[n] for n in hoist))
    body, mapping, out = _copy(graph.graph)
    body.output(out)
    anchor = [n for n in body.nodes if n.op == "placeholder"][-1]
    for i, node in enumerate(hoist):
        with body.inserting_after(anchor):
            anchor = body.placeholder(f"hoisted_{i}")
        anchor.meta = dict(node.meta)
        mapping[node].replace_all_uses_with(anchor)
    for part in (prologue, body):
        part.eliminate_dead_code()
        part.lint()
    return torch.fx.GraphModule(graph, prologue), torch.fx.GraphModule(graph, body)


def _copy(graph: torch.fx.Graph) -> tuple:
    """A copy of ``graph`` without its output node: ``(copy, node -> copied node, the output's copied value)``."""
    copy, mapping = torch.fx.Graph(), {}
    out = copy.graph_copy(graph, mapping)
    return copy, mapping, out
