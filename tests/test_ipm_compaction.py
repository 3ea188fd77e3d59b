"""The interior point's row helpers (torchtraj.solvers.ipm.compaction): gathered rows laid out as the batch's, and
rows written back without changing the layout. A compiled kernel is specialised to its inputs' strides, so the
rows that a compiled solve gathers (an inertia correction's later attempt, a correction, a later line-search
round) must reach its kernels laid out as the whole batch's, or each kernel would be compiled again."""

from dataclasses import dataclass
from typing import Optional

import torch

from torchtraj.bench.ops import OperatorCounter
from torchtraj.solvers.ipm.compaction import gather_laid_out, laid_out_as, write_rows


@dataclass
class _Rows:
    a: torch.Tensor
    b: torch.Tensor
    knots: torch.Tensor
    factor: Optional[object] = None


@dataclass
class _Pair:
    a: torch.Tensor
    b: torch.Tensor


def _view_of_a_buffer(B: int) -> torch.Tensor:
    """``(B, 4, 2)`` rows of a larger time-major buffer, starting past its first element: strides and an offset that
    a plain gather does not keep."""
    return torch.randn(5, B, 3, dtype=torch.float64)[1:, :, 1:].transpose(0, 1)


def test_gathered_rows_keep_the_strides_and_offset_of_the_batch_and_its_values():
    batch = _view_of_a_buffer(6)
    index = torch.tensor([4, 1, 1])
    rows = gather_laid_out(batch, index)
    assert rows.stride() == batch.stride() and rows.storage_offset() == batch.storage_offset()
    assert batch[index].stride() != batch.stride()  # else the test shows nothing
    assert torch.equal(rows, batch[index])


def test_a_dataclass_is_gathered_field_by_field_with_its_shared_and_dropped_fields():
    value = _Rows(a=_view_of_a_buffer(5), b=torch.arange(5.0), knots=torch.ones(4, 2), factor=object())
    index = torch.tensor([3, 0])
    rows = gather_laid_out(value, index)
    assert torch.equal(rows.a, value.a[index]) and rows.a.stride() == value.a.stride()
    assert torch.equal(rows.b, value.b[index])
    assert rows.knots is value.knots and rows.factor is None


def test_a_tensor_held_twice_is_gathered_once():
    shared, own = _view_of_a_buffer(5), torch.arange(5.0)
    model, corrected = _Pair(a=shared, b=own), _Pair(a=shared, b=own + 1.0)  # a corrected model's shared fields
    index = torch.tensor([3, 0, 3])
    rows_model, rows_corrected, alone = gather_laid_out((model, corrected, shared), index)
    assert rows_model.a is rows_corrected.a is alone
    assert torch.equal(alone, shared[index]) and alone.stride() == shared.stride()
    assert torch.equal(rows_model.b, own[index]) and torch.equal(rows_corrected.b, own[index] + 1.0)


def test_a_tensor_that_repeats_an_element_is_gathered_plainly():
    shared = torch.randn(1, 3).expand(4, 3)
    rows = laid_out_as(shared[torch.tensor([0, 2])], shared)
    assert rows.stride() == (3, 1) and torch.equal(rows, shared[:2])


def test_rows_written_back_keep_the_batch_layout():
    batch = _Pair(a=torch.randn(4, 6, 2, dtype=torch.float64).transpose(0, 1), b=torch.arange(6.0))
    index = torch.tensor([5, 2])
    new = _Pair(a=torch.randn(2, 4, 2, dtype=torch.float64), b=torch.tensor([10.0, 20.0]))
    written = write_rows(batch, index, new)
    assert written.a.stride() == batch.a.stride()
    want = batch.a.clone()
    want[index] = new.a
    assert torch.equal(written.a, want) and torch.equal(written.b, torch.tensor([0, 1, 20, 3, 4, 10.0]))


def test_tensors_side_by_side_in_one_buffer_are_gathered_from_its_rows_once():
    """A kernel's outputs that share a buffer (each instance's row holding several of them, past an offset, as the
    expansion's values and Jacobians are laid out): the buffer's rows are gathered once for all of them, and each
    comes back with its values, strides and offset."""
    buffer = torch.randn(6, 11, dtype=torch.float64)
    first = buffer[:, 1:7].unflatten(1, (3, 2))  # (6, 3, 2), offset 1
    second = buffer[:, 7:10]  # (6, 3), offset 7
    alone = torch.arange(6.0)
    index = torch.tensor([5, 0, 5, 2])
    with OperatorCounter() as counter:
        rows = gather_laid_out(_Pair(a=first, b=second), index)
    assert counter.by_name["aten.index.Tensor"] == 1  # the buffer's rows, once
    assert "aten.copy_.default" not in counter.by_name  # no copy into the layout
    for got, batch in ((rows.a, first), (rows.b, second)):
        assert torch.equal(got, batch[index])
        assert got.stride() == batch.stride() and got.storage_offset() == batch.storage_offset()
    assert rows.a.untyped_storage().data_ptr() == rows.b.untyped_storage().data_ptr()
    assert torch.equal(gather_laid_out(alone, index), alone[index])
