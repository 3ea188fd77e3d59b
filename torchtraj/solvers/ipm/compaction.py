r"""Finished instances leave the batch (``IPOptions.compact_below``), and the solution is written back whole.

Once the running instances are at most that share of the batch being iterated, their rows are gathered
(iterate, model, filter, parameters) and the next iterations run on them alone; the others' results are written
back into the full batch's :class:`Final`. The arithmetic of an instance is unchanged, bit for bit, and the batch's
spread of iteration counts no longer costs the slowest one's iterations for all: the time of an iteration grows
about linearly with the batch past a few dozen instances. The history records which rows were iterated, so that
the full batch's history repeats a finished instance's last values (step size 0) after it left.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ...core.batching import rows_of
from ...core.compiled import DYNAMIC_FROM
from ...core.masks import RowPicker
from ...core.solution import History
from ...riccati.range_space import TerminalGains, select_gains
from .iterate import Iterate, Model


def pick(mask: Tensor, a, b):
    """The batch-first dataclass ``a`` where ``mask (B,)``, else ``b`` (field by field; a field that is no tensor,
    as a :class:`~torchtraj.solvers.ipm.newton.Direction`'s factor, is kept where ``a`` and ``b`` share it, else
    ``None``)."""
    rows = RowPicker(mask)

    def one(x, y):
        if isinstance(x, Tensor) and isinstance(y, Tensor):
            return rows(x, y)
        return select_gains(mask, x, y) if isinstance(x, (Tensor, TerminalGains)) else (x if x is y else None)

    return type(a)(**{f.name: one(getattr(a, f.name), getattr(b, f.name)) for f in fields(a)})


def gather_rows(value, index: Tensor):
    """The rows ``index`` of a batch-first tensor or dataclass (:func:`~torchtraj.core.batching.rows_of`;
    :class:`Model`'s ``knots`` is per stage; a :class:`~torchtraj.solvers.ipm.newton.Direction`'s factorisation
    becomes ``None``)."""
    return rows_of(value, index, shared=("knots",), dropped=("factor",))


def gather_laid_out(value, index: Tensor):
    """:func:`gather_rows` for compiled kernels: each tensor's rows laid out as the tensor itself
    (:func:`laid_out_as`). A compiled kernel is specialised to its inputs' strides, and with a dynamic batch to the
    equalities between their offsets: the rows of a view (the model's fields are views of the expansion's rows)
    gathered plainly would compile each kernel again for their own layout. A tensor that ``value`` holds more than
    once (a corrected model shares most fields with the model it corrects) is gathered once, and so is a buffer that
    holds several tensors' rows (:func:`_buffer_rows`: a kernel's outputs side by side in one buffer)."""
    taken, buffers = {}, {}

    def take(v: Tensor, i: Tensor) -> Tensor:
        if id(v) not in taken:  # `value` holds every tensor while this call runs: no identity is reused
            rows = _buffer_rows(v, i, buffers)
            taken[id(v)] = laid_out_as(v[i], v) if rows is None else rows
        return taken[id(v)]

    return rows_of(value, index, shared=("knots",), dropped=("factor",), take=take)


def _buffer_rows(v: Tensor, index: Tensor, buffers: dict) -> "Tensor | None":
    """The rows ``index`` of ``v`` laid out as ``v``, taken from the rows of its whole buffer: the buffer seen as
    ``(B, stride(0))``, gathered once for every tensor of ``buffers`` (keyed by buffer and row length) that lies in
    it, and ``v``'s view of it again. ``None`` where ``v``'s rows do not each lie within a row of its buffer (an
    instance's elements interleaved with another's, as in a time-major buffer, or every instance one repeated row)
    or ``v`` is its buffer's rows."""
    B, row = (v.shape[0], v.stride(0)) if v.dim() else (0, 0)
    if B < 1 or row < 1 or v.numel() == 0 or any(st < 0 for st in v.stride()) or v.is_contiguous():
        return None  # (a contiguous tensor is its buffer's rows: gathered plainly, laid out as itself)
    extent = v.storage_offset() + sum((n - 1) * st for n, st in zip(v.shape[1:], v.stride()[1:]))
    if extent >= row or v.untyped_storage().nbytes() < B * row * v.element_size():
        return None
    key = (v.untyped_storage().data_ptr(), row, v.dtype)
    if key not in buffers:
        buffers[key] = v.as_strided((B, row), (row, 1), 0)[index]
    return buffers[key].as_strided((index.shape[0], *v.shape[1:]), v.stride(), v.storage_offset())


def kernel_rows(rows: Tensor) -> Tensor:
    """The rows ``rows (R,)`` that a compiled kernel takes for them: at least :data:`DYNAMIC_FROM`, the instances
    repeated where fewer (a batch of one has kernels of its own, and a batch's kernels serve every larger count); the
    first ``R`` are ``rows`` themselves."""
    return rows if rows.numel() >= DYNAMIC_FROM else rows.repeat(-(-DYNAMIC_FROM // rows.numel()))


def laid_out_as(value: Tensor, like: Tensor) -> Tensor:
    """``value``, of ``like``'s shape but for its batch size, with the strides and storage offset of ``like`` (a
    copy where they differ; ``value`` itself where ``like`` repeats an element, which no copy can be laid out as)."""
    if value.stride() == like.stride() and value.storage_offset() == like.storage_offset():
        return value
    if any(st == 0 and n > 1 for n, st in zip(like.shape, like.stride())):
        return value
    extent = like.storage_offset() + 1 + sum((n - 1) * st for n, st in zip(value.shape, like.stride()) if n > 0)
    return like.new_empty(extent).as_strided(value.shape, like.stride(), like.storage_offset()).copy_(value)


def write_rows(value, index: Tensor, rows):
    """The batch-first dataclass ``value`` with its rows ``index`` replaced by ``rows`` (a new object; a field that
    is no tensor, as a :class:`~torchtraj.solvers.ipm.newton.Direction`'s factor, becomes ``None``)."""
    def one(x, y):
        if isinstance(x, Tensor):  # in place into a copy, which keeps the layout (index_copy's own result is
            return x.clone().index_copy_(0, index, y)  # contiguous, and a compiled kernel would specialise to it)
        return x.index_copy(0, index, y) if isinstance(x, TerminalGains) else None

    return type(value)(**{f.name: one(getattr(value, f.name), getattr(rows, f.name)) for f in fields(value)})


@dataclass
class Final:
    """What the solution reports of every instance of the full batch, written back as instances leave the
    iterated set (``IPOptions.compact_below``) and at the end."""

    X: Tensor
    U: Tensor
    s: Tensor
    sN: Tensor
    lam: Tensor
    z: Tensor
    zN: Tensor
    nu: Tensor
    nuN: Tensor
    J: Tensor
    violation: Tensor
    status: Tensor
    iterations: Tensor
    K: Tensor

    @classmethod
    def of(cls, it: Iterate, measures: tuple, status: Tensor, iterations: Tensor, K: Tensor) -> "Final":
        """The final values of ``it``, with its ``measures``: the objective and the largest violation ``(B,)``."""
        J, violation = measures
        return cls(X=it.X, U=it.U, s=it.s, sN=it.sN, lam=it.lam, z=it.z, zN=it.zN, nu=it.nu, nuN=it.nuN, J=J,
                   violation=violation, status=status, iterations=iterations, K=K)

    def write(self, index: Tensor, rows: "Final") -> "Final":
        """Overwrite the rows ``index`` with ``rows`` (in place: the buffers are this object's own copies)."""
        for f in fields(self):
            getattr(self, f.name)[index] = getattr(rows, f.name)
        return self


def history_row(model: Model, step_size: Tensor, regularization: Tensor, mu: Tensor, error: Tensor) -> dict:
    """One iteration's entry of the history, ``(B,)`` each."""
    return {"cost": model.J, "max_violation": model.violation, "step_size": step_size,
            "regularization": regularization, "barrier": mu, "kkt_error": error,
            "stationarity": model.dual_error}


def full_history(records: list) -> History:
    """The history of the full batch from records ``(index, values, iteration)`` of the iterated rows ``index``
    (``None``: all): an iteration's row, or (``iteration`` false) the values that the instances about to leave
    the iterated set repeat from then on, with step size 0."""
    full, previous = [], None
    for index, row, iteration in records:
        if index is not None:
            row = {k: (torch.zeros_like(v) if k == "step_size" else v.clone()).index_copy_(0, index, row[k])
                   for k, v in previous.items()}
        if iteration:
            full.append(row)
        previous = row
    return History.from_rows(full)
