"""The compiled kernels' graph pass (torchtraj.core.short_products): short products become broadcast products and
sums with the library's results, long or symbolic contractions stay library calls."""

import torch
from torch.fx.experimental.proxy_tensor import make_fx

from torchtraj.core.short_products import ShortProducts

aten = torch.ops.aten
PRODUCTS = {aten.mm.default, aten.bmm.default, aten.addmm.default, aten.baddbmm.default}


def products(graph: torch.fx.GraphModule) -> list:
    return [n.target for n in graph.graph.nodes if n.op == "call_function" and n.target in PRODUCTS]


def rewritten(fn, *args, tracing_mode="fake", longest=8):
    graph = make_fx(fn, tracing_mode=tracing_mode)(*args)
    before = products(graph)
    ShortProducts(longest)(graph.graph)
    graph.graph.lint()
    graph.recompile()
    return graph, before


def user_functions(x, Q, W, b, A):
    quadratic = torch.func.vmap(lambda e: e @ Q @ e)(x)  # a cost's e @ Q @ e over the knots: mm and bmm
    layer = torch.nn.functional.linear(x, W, b)  # addmm
    scaled = torch.baddbmm(A, A, A, beta=0.5, alpha=2.0)
    return quadratic, layer, scaled


def test_short_products_become_sums_with_the_library_results():
    g = torch.Generator().manual_seed(0)
    args = (torch.randn(7, 3, generator=g, dtype=torch.float64), torch.randn(3, 3, generator=g, dtype=torch.float64),
            torch.randn(4, 3, generator=g, dtype=torch.float64), torch.randn(4, generator=g, dtype=torch.float64),
            torch.randn(5, 2, 2, generator=g, dtype=torch.float64))
    graph, before = rewritten(user_functions, *args)
    assert {aten.mm.default, aten.addmm.default, aten.baddbmm.default} <= set(before)
    assert products(graph) == []
    for got, expected in zip(graph(*args), user_functions(*args)):
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-14)


def test_long_and_symbolic_contractions_stay_library_products():
    a, b = torch.randn(6, 9, dtype=torch.float64), torch.randn(9, 2, dtype=torch.float64)
    graph, before = rewritten(torch.mm, a, b)
    assert products(graph) == before == [aten.mm.default]
    graph, before = rewritten(torch.mm, a, b, longest=9)
    assert products(graph) == []
    torch.testing.assert_close(graph(a, b), a @ b, rtol=0, atol=1e-14)
    small = torch.randn(4, 3, dtype=torch.float64), torch.randn(3, 5, dtype=torch.float64)
    graph, before = rewritten(torch.mm, *small, tracing_mode="symbolic")  # the contraction's length a symbol
    assert products(graph) == before == [aten.mm.default]


def test_a_term_added_with_beta_zero_is_not_read():
    a, b = torch.randn(3, 2, dtype=torch.float64), torch.randn(2, 4, dtype=torch.float64)
    term = torch.full((3, 4), float("nan"), dtype=torch.float64)

    def product(term, a, b):
        return torch.addmm(term, a, b, beta=0.0, alpha=3.0)

    graph, _ = rewritten(product, term, a, b)
    assert products(graph) == []
    torch.testing.assert_close(graph(term, a, b), 3.0 * (a @ b), rtol=0, atol=1e-14)
