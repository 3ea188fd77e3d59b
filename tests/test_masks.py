"""Per-instance choices by masks (torchtraj.core.masks): a mask picks rows, shaped once for many tensors."""

import torch

from torchtraj.bench.ops import OperatorCounter
from torchtraj.core.masks import RowPicker, where_rows

F64 = torch.float64


def test_a_row_picker_is_where_rows_with_the_mask_shaped_once_per_dimensionality():
    """The fields of an iterate (3-D, 2-D and per-instance tensors) picked by one mask: ``where_rows``' tensors,
    with one reshape for each number of dimensions beyond the first (none for ``(B,)`` tensors)."""
    g = torch.Generator().manual_seed(0)
    mask = torch.tensor([True, False, True])
    pairs = [(torch.randn(3, *shape, dtype=F64, generator=g), torch.randn(3, *shape, dtype=F64, generator=g))
             for shape in ((4, 2), (5, 2), (2,), (), (3,))]
    expected = [where_rows(mask, a, b) for a, b in pairs]
    with OperatorCounter() as calls:
        pick = RowPicker(mask)
        got = [pick(a, b) for a, b in pairs]
    assert all(torch.equal(x, y) for x, y in zip(got, expected))
    assert calls.by_name["aten.where.self"] == 5 and calls.total == 5 + 2, calls.by_name  # 3-D and 2-D shapes
