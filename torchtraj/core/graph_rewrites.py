r"""Exact algebraic rewrites of a recorded operator graph (:func:`~torchtraj.core.graph_passes.simplify`): patterns
that reverse-mode differentiation leaves in a graph, each replaced by fewer operators that give the same bits.

* **A sum with a negation** ``x + (−y)`` is ``x − y``: IEEE 754 defines the difference as the sum with the
  negated operand, signed zeros and all (and the library's difference is its sum with ``α = −1``).
* **Two scattered halves** ``select_backward(a, S, d, 0) + select_backward(b, S, d, 1)`` (the gradient of a
  vector of two components read as ``x[0]`` and ``x[1]``: each ``select_backward`` a zero tensor of size ``S``
  with its gradient written at one index of dimension ``d``, ``S_d = 2``) are ``stack([a, b], d) + 0``: each
  element of the sum is one gradient plus a positive zero, which is the gradient itself except that a negative
  zero becomes positive; the added ``+ 0`` does the same. Two calls instead of three, and at a large batch one
  tensor written instead of two zero-filled ones and their sum.
* **A split into one piece** (``split_with_sizes(t, [n], d)`` with ``n`` the size of ``t`` along ``d``, which
  ``torch.func`` makes of a single block) returns ``t``'s own elements: its piece is ``t``.

A rewrite applies only where the operator it removes has no other user, so that no value is computed twice.
"""

from __future__ import annotations

import operator

import torch

aten = torch.ops.aten


def rewrite(graph: torch.fx.Graph) -> None:
    """Apply the module's rewrites to ``graph`` (functional, its nodes' ``meta["val"]`` from the trace)."""
    for node in list(graph.nodes):
        if node.op != "call_function":
            continue
        if node.target == aten.split_with_sizes.default:
            _whole_split(graph, node)
        elif node.target == aten.add.Tensor and not node.kwargs and len(node.args) == 2 \
                and not _halves(graph, node):
            _difference(graph, node)


def _whole_split(graph: torch.fx.Graph, node: torch.fx.Node) -> bool:
    """The pieces of a split into one piece, read as the split tensor itself."""
    t, sizes = node.args[0], node.args[1]
    dim = node.args[2] if len(node.args) > 2 else node.kwargs.get("dim", 0)
    val = t.meta.get("val") if isinstance(t, torch.fx.Node) else None
    if not isinstance(val, torch.Tensor) or len(sizes) != 1 or sizes[0] != val.shape[dim] \
            or not all(user.target is operator.getitem and user.args[1] == 0 for user in node.users):
        return False
    for user in list(node.users):
        user.replace_all_uses_with(t)
        graph.erase_node(user)
    graph.erase_node(node)
    return True


def _sole(value, target) -> bool:
    """Whether ``value`` is a node of operator ``target`` with one user."""
    return isinstance(value, torch.fx.Node) and value.op == "call_function" and value.target == target \
        and len(value.users) == 1


def _replace(graph: torch.fx.Graph, node: torch.fx.Node, target, args: tuple) -> torch.fx.Node:
    """A call of ``target`` on ``args`` before ``node``, with its value, in place of ``node``."""
    with graph.inserting_before(node):
        new = graph.call_function(target, args)
    new.meta = dict(node.meta)
    node.replace_all_uses_with(new)
    graph.erase_node(node)
    return new


def _difference(graph: torch.fx.Graph, node: torch.fx.Node) -> bool:
    """``x + (−y)`` or ``(−y) + x`` as ``x − y``."""
    a, b = node.args
    if _sole(b, aten.neg.default):
        x, negated = a, b
    elif _sole(a, aten.neg.default):
        x, negated = b, a
    else:
        return False
    if not isinstance(x, torch.fx.Node):  # a number: the difference's first operand must be a tensor
        return False
    _replace(graph, node, aten.sub.Tensor, (x, negated.args[0]))
    graph.erase_node(negated)
    return True


def _halves(graph: torch.fx.Graph, node: torch.fx.Node) -> bool:
    """``select_backward(a, S, d, i) + select_backward(b, S, d, 1 − i)``, ``S_d = 2``, as
    ``stack([a, b] in index order, d) + 0``."""
    a, b = node.args
    if not (_sole(a, aten.select_backward.default) and _sole(b, aten.select_backward.default)):
        return False
    (ga, sizes, dim, ia), (gb, sizes_b, dim_b, ib) = a.args, b.args
    val = node.meta.get("val")
    if list(sizes) != list(sizes_b) or dim != dim_b or not isinstance(val, torch.Tensor):
        return False
    dim = dim % len(sizes)
    if sizes[dim] != 2 or {ia % 2, ib % 2} != {0, 1} or not val.is_contiguous():
        return False
    parts = [ga, gb] if ia % 2 == 0 else [gb, ga]
    with graph.inserting_before(node):
        stacked = graph.call_function(aten.stack.default, (parts, dim))
    stacked.meta = dict(node.meta)
    _replace(graph, node, aten.add.Tensor, (stacked, 0.0))
    graph.erase_node(a)
    graph.erase_node(b)
    return True
