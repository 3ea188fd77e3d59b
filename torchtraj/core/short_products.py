r"""Inductor's graph pass that writes the compiled kernels' short matrix products as broadcast products and sums.

A product :math:`C = A B` with a short contraction (``k ≤`` :data:`~torchtraj.core.compiled.FUSED_CONTRACTION`)

.. math:: C_{ij} = \sum_{l < k} A_{il} B_{lj}

is, in a traced graph, ``mm`` or ``bmm`` (``addmm`` and ``baddbmm`` with a term added). Inductor leaves those to the
library, a call of its own with its checks and its output buffer, where the products of the stage matrices of small
systems are a few multiply-adds each. :func:`torchtraj.core.compiled.matmul` writes the library's own products as a
broadcast product and a sum (``(A[..., :, :, None] * B[..., None, :, :]).sum(-2)``), which Inductor fuses into its
loops; this pass does the same for the products it cannot reach, those of the user's functions (``e @ Q @ e`` in a
cost, ``A @ x`` in the dynamics) in a kernel's expansion, trial points and rollouts, after ``vmap`` and the
derivatives made them batched products of the whole batch's knots.

The pass runs on the graph after Inductor's decompositions (``post_grad_custom_pre_pass``, an option of every
kernel: :data:`~torchtraj.core.compiled.OPTIONS`). It rewrites a product whose contraction length is a static size
up to the threshold and keeps every other (a neural network's layers, a symbolic length); the result is the same sum
of the same products, in the order Inductor's reduction takes, so compiled answers move by rounding alone.
"""

from __future__ import annotations

import torch
from torch._inductor.custom_graph_pass import CustomGraphPass, get_hash_for_files

aten = torch.ops.aten

#: The products rewritten, and the argument positions of their two factors.
_PRODUCTS = {
    aten.mm.default: (0, 1),
    aten.bmm.default: (0, 1),
    aten.addmm.default: (1, 2),
    aten.baddbmm.default: (1, 2),
}


class ShortProducts(CustomGraphPass):
    """The pass: ``mm``, ``bmm``, ``addmm`` and ``baddbmm`` with a static contraction up to ``longest`` written as a
    broadcast product and a sum (``addmm`` and ``baddbmm`` as that sum scaled by ``alpha`` plus the added term
    scaled by ``beta``)."""

    def __init__(self, longest: int):
        self.longest = longest

    def __call__(self, graph: torch.fx.Graph) -> None:
        for node in list(graph.nodes):
            if node.op != "call_function" or node.target not in _PRODUCTS:
                continue
            first, second = _PRODUCTS[node.target]
            a, b = node.args[first], node.args[second]
            k = a.meta["val"].shape[-1]
            if not isinstance(k, int) or k > self.longest:
                continue
            with graph.inserting_before(node):
                value = _short_product(graph, node, a, b)
            node.replace_all_uses_with(value)
            graph.erase_node(node)

    def uuid(self):
        return (get_hash_for_files((__file__,)), self.longest)


def _short_product(graph: torch.fx.Graph, node: torch.fx.Node, a: torch.fx.Node, b: torch.fx.Node) -> torch.fx.Node:
    """The nodes of ``a @ b`` as a broadcast product and a sum (plus ``node``'s added term, for ``addmm`` and
    ``baddbmm``), each with its fake value in ``meta["val"]`` as Inductor's lowering reads it."""
    fake_mode = a.meta["val"].fake_mode

    def call(target, *args):
        made = graph.call_function(target, args)
        with fake_mode:
            made.meta["val"] = target(*(arg.meta["val"] if isinstance(arg, torch.fx.Node) else arg for arg in args))
        return made

    product = call(aten.mul.Tensor, call(aten.unsqueeze.default, a, -1), call(aten.unsqueeze.default, b, -3))
    value = call(aten.sum.dim_IntList, product, [-2])
    if node.target in (aten.addmm.default, aten.baddbmm.default):
        beta, alpha = node.kwargs.get("beta", 1), node.kwargs.get("alpha", 1)
        term = node.args[0]
        if alpha != 1:
            value = call(aten.mul.Tensor, value, alpha)
        if beta != 0:  # the library's rule: with beta = 0 the term is not read (not even its NaNs)
            value = call(aten.add.Tensor, term if beta == 1 else call(aten.mul.Tensor, term, beta), value)
    return value
