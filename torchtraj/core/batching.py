"""Evaluating per-instance user functions on batches, with ``torch.func.vmap``.

User functions see one instance: ``f(x (nx,), u (nu,), p)``. Solvers hold tensors shaped
``(B, *E, n)``: a batch dimension B (to which the parameters ``p`` belong) followed by any
number of extra dimensions E (time steps, line-search candidates). :func:`map_stage` and
:func:`map_state` flatten E, vmap over it with ``p`` held fixed, vmap again over B with
``p`` batched, and restore the shape. No Python loop over the batch.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import weakref
from typing import Callable, Mapping, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor
from torch._C._functorch import is_functorch_wrapped_tensor
from torch.func import vmap

from .recorded import Recorded, trace_at

Params = Mapping[str, Tensor]


def shared_param(value: Tensor) -> bool:
    """Whether a batched parameter is one instance's value for all: expanded from it (stride 0), or B = 1."""
    return value.shape[0] == 1 or value.stride(0) == 0


def concat(parts: Sequence[Tensor]) -> Tensor:
    """``torch.cat(parts)`` of a per-instance function's vectors (along their first dimension). Traced by
    ``torch.compile``, it is written as zero pads and a sum: in PyTorch 2.13, ``cat``'s batching rule under ``vmap``
    reads the concrete batch size, which would specialise a kernel compiled with a dynamic batch dimension
    (:mod:`torchtraj.core.compiled`) to it; a pad's does not. The same values (a zero added is exact)."""
    if not torch.compiler.is_compiling() or not any(p.shape[0] for p in parts):
        return torch.cat(list(parts))
    parts = [p for p in parts if p.shape[0]]  # an empty one adds nothing (and may be an unbatched constant)
    if len(parts) == 1:
        return parts[0]
    total, start, out = sum(p.shape[0] for p in parts), 0, None
    for p in parts:
        padded = F.pad(p, [0, 0] * (p.dim() - 1) + [start, total - start - p.shape[0]])
        out = padded if out is None else out + padded
        start += p.shape[0]
    return out


def param_rows(params: Params, index: Tensor) -> dict:
    """The rows ``index`` of the batched parameters; a shared one stays an expanded view (and shared)."""
    return {k: v[:1].expand(index.shape[0], *v.shape[1:]) if shared_param(v) else v[index] for k, v in params.items()}


def rows_of(value, index: Tensor, shared: tuple = (), dropped: tuple = (), take: Optional[Callable] = None):
    """The instances ``index (R,)`` of a batch-first value: a tensor (or another object indexed as one, as the
    range-space gains), a tuple of such values, or a dataclass of them, field by field; ``None`` stays ``None``.
    The fields named in ``shared`` hold per-stage values that the batch shares and are kept whole; those named in
    ``dropped`` (a factorisation, which is not taken apart) become ``None``. ``take(tensor, index)``, given, takes
    each tensor's rows instead of indexing it."""
    if value is None:
        return None
    if isinstance(value, tuple):
        return tuple(rows_of(v, index, shared, dropped, take) for v in value)
    if take is not None and isinstance(value, Tensor):
        return take(value, index)
    if hasattr(value, "__getitem__"):
        return value[index]
    return type(value)(**{f.name: getattr(value, f.name) if f.name in shared
                          else None if f.name in dropped
                          else rows_of(getattr(value, f.name), index, shared, dropped, take)
                          for f in dataclasses.fields(value)})


def _split_params(params: Params) -> tuple[dict, dict, bool]:
    """``(p, p_dims, all_shared)``: a parameter expanded from one instance (:func:`shared_param`) is shared and
    passed as that instance's value with vmap dimension ``None``; the others keep their batch dimension 0.

    A solver maps its functions over the same parameters many times an iteration, so the split of plain tensors
    (no autograd, no ``torch.func`` transform, not traced) is kept for the :data:`_SPLITS_KEPT` most recent
    parameter sets, keyed by each tensor's identity and layout, and used again only while weak references show
    the same tensors alive (an identity of a dead tensor may be reused). What is kept is the views of the shared
    parameters' single values, so no batch-sized tensor outlives its solve; a change in place is seen through them,
    a tensor replaced is another key."""
    key = _split_key(params)
    if key is not None:
        kept = _SPLITS.get(key)
        if kept is not None and all(ref() is v for ref, v in zip(kept[0], params.values())):
            _SPLITS.move_to_end(key)
            values, p_dims, all_shared = kept[1]
            return {k: values.get(k, v) for k, v in params.items()}, p_dims, all_shared
    shared = {k for k, v in params.items() if shared_param(v)}
    p = {k: (v[0] if k in shared else v) for k, v in params.items()}
    p_dims = {k: (None if k in shared else 0) for k in params}
    if key is not None:
        values = {k: p[k] for k in shared}
        _SPLITS[key] = (tuple(weakref.ref(v) for v in params.values()), (values, p_dims, len(shared) == len(params)))
        if len(_SPLITS) > _SPLITS_KEPT:
            _SPLITS.popitem(last=False)
    return p, p_dims, len(shared) == len(params)


#: Parameter sets whose split :func:`_split_params` keeps.
_SPLITS_KEPT = 16
_SPLITS: collections.OrderedDict = collections.OrderedDict()
_TRACING = (torch._C._TorchDispatchModeKey.FAKE, torch._C._TorchDispatchModeKey.PROXY,
            torch._C._TorchDispatchModeKey.FUNCTIONAL)


def _split_key(params: Params) -> Optional[tuple]:
    """The key of ``params``' split, ``None`` where it must be made afresh: a tensor that requires grad, is wrapped
    by a ``torch.func`` transform or is of a subclass (a fake one), or a trace (``torch.compile``, a record's)."""
    if torch.compiler.is_compiling() or any(torch._C._get_dispatch_mode(mode) is not None for mode in _TRACING):
        return None
    key = []
    for name, v in params.items():
        if type(v) is not Tensor or v.requires_grad or is_functorch_wrapped_tensor(v):
            return None
        key.append((name, id(v), v.data_ptr(), v.shape, v.stride(), v.dtype, v.device))
    return tuple(key)


def _map(fn: Callable, tensors: tuple, params: Params, split: Optional[tuple] = None) -> Tensor:
    lead = tensors[0].shape[:-1]
    B, E = lead[0], math.prod(lead[1:])
    p, p_dims, all_shared = _split_params(params) if split is None else split
    n_in = len(tensors)
    if all_shared:
        # every parameter shared: close over them rather than pass the dict through vmap, whose
        # pytree handling of it costs about as much as the pendulum's RK4 step itself
        flat = tuple(t.reshape(B * E, t.shape[-1]) for t in tensors)
        out = vmap(lambda *args: fn(*args, p))(*flat)
        return _restore(out, lead, flat_batch=True)
    if E == 1:
        # one vmap level over the B instances
        flat = tuple(t.reshape(B, t.shape[-1]) for t in tensors)
        out = vmap(fn, in_dims=(*([0] * n_in), p_dims))(*flat, p)
        return _restore(out, lead, flat_batch=True)
    flat = tuple(t.reshape(B, E, t.shape[-1]) for t in tensors)
    inner = vmap(fn, in_dims=(*([0] * n_in), None))
    out = vmap(inner, in_dims=(*([0] * n_in), p_dims))(*flat, p)
    return _restore(out, lead, flat_batch=False)


def _restore(out, lead, flat_batch: bool):
    if isinstance(out, tuple):
        return tuple(_restore(o, lead, flat_batch) for o in out)
    return out.reshape(*lead, *out.shape[1 if flat_batch else 2:])


def map_stage(fn: Callable, X: Tensor, U: Tensor, params: Params) -> Tensor:
    """``fn(x, u, p)`` on ``X (B, *E, nx)``, ``U (B, *E, nu)`` with ``params`` batched over B."""
    return _map(fn, (X, U), params)


def recorded_map_stage(fn: Callable, X: Tensor, U: Tensor, params: Params, record: Optional[bool]) -> Tensor:
    """:func:`map_stage`, replayed from its operator graph as ``record`` says
    (:func:`~torchtraj.core.recorded.trace_at`: ``False`` never, ``True`` from a signature's eighth call, ``None`` once
    its calls are worth the trace): the same numbers to the last bit in fewer calls."""
    return _RECORDED_MAP_STAGE.option(record)(fn, X, U, params)


def stage_mapper(fn: Callable, params: Params, record: Optional[bool] = False) -> Callable:
    """``(X, U) ↦ map_stage(fn, X, U, params)`` for repeated calls with the same ``params`` (the steps of a
    rollout): the parameters are split into shared and batched ones once (a view of each shared one), not at every
    call; with ``record`` (``None``: once the calls are worth a trace), the calls are replayed as a loop from the
    operator graph of their layout (:meth:`~torchtraj.core.recorded.Recorded.loop`: split included, the
    parameters' products made once), the same numbers in fewer calls."""
    split = _split_params(params)
    if record is False:
        return lambda X, U: _map(fn, (X, U), params, split)
    calls, steps = trace_at(record), {}

    def mapped(X: Tensor, U: Tensor) -> Tensor:
        layout = (X.shape, X.stride(), X.dtype, U.shape, U.stride(), U.dtype)
        step = steps.get(layout)
        if step is None:
            step = _RECORDED_MAP_STAGE.loop(fn, X, U, params, calls=1, trace_at=calls, varying=2)
            if step is None:
                return _map(fn, (X, U), params, split)
            steps[layout] = step
        return step(X, U)

    return mapped


def map_points(fn: Callable, tensors: Sequence[Tensor], params: Params) -> Tensor:
    """``fn(*points, p)`` on ``tensors``, each ``(B, *E, n_i)`` with the same ``(B, *E)``, ``params`` batched over
    B: :func:`map_stage` and :func:`map_state` for any number of per-point tensors."""
    return _map(fn, tuple(tensors), params)


def map_state(fn: Callable, X: Tensor, params: Params) -> Tensor:
    """``fn(x, p)`` on ``X (B, *E, nx)`` with ``params`` batched over B."""
    return _map(fn, (X,), params)


def rollout(dynamics: Callable, x0: Tensor, U: Tensor, params: Params, record: Optional[bool] = False) -> Tensor:
    """Simulate ``x_{k+1} = f(x_k, u_k, p)`` from ``x0 (B, *E, nx)`` under ``U (B, *E, N, nu)`` (``record`` as
    :func:`closed_loop_rollout`'s).

    Returns ``X (B, *E, N+1, nx)``.
    """
    return closed_loop_rollout(dynamics, x0, U, params, record=record)[0]


def _closed_loop_step(dynamics: Callable, feedback: bool, x: Tensor, u: Tensor, xr, k, p: Params) -> tuple:
    """One trajectory's stage of :func:`closed_loop_rollout`: ``(x_{k+1}, u_k)`` with ``u_k = u + k (x − xr)``
    (``feedback``) or ``u``."""
    # a product and a sum: under the two vmap levels torch.addmv is 12 calls, these 7
    u = u + (k * (x - xr)).sum(-1) if feedback else u
    return dynamics(x, u, p), u


def _stage_step(dynamics: Callable, feedback: bool, x: Tensor, U: Tensor, X_ref: Tensor, K: Tensor, p: Params):
    """One stage of :func:`closed_loop_rollout`'s trajectories, ``(x_{k+1}, u_k)``, the parameters shared."""
    return vmap(lambda x, u, xr, k: _closed_loop_step(dynamics, feedback, x, u, xr, k, p))(x, U, X_ref, K)


_RECORDED_STAGE_STEP = Recorded(_stage_step)
_RECORDED_MAP_STAGE = Recorded(map_stage)


def closed_loop_rollout(dynamics: Callable, x0: Tensor, U: Tensor, params: Params, X_ref: Optional[Tensor] = None,
                        K: Optional[Tensor] = None, record: Optional[bool] = False) -> tuple[Tensor, Tensor]:
    """Simulate from ``x0 (B, *E, nx)`` under ``u_k = U_k + K_k (x_k − X_ref_k)`` (``U (B, *E, N, nu)``; the
    feedback ``X_ref (B, N+1, nx)``, ``K (B, N, nu, nx)`` is shared by the E trajectories of an instance, and
    ``u_k = U_k`` without it). Returns ``X (B, *E, N+1, nx)`` and the applied ``U (B, *E, N, nu)``.

    The loop over time runs *inside* one vmapped per-trajectory function, so vmap's fixed cost (wrapping
    and unwrapping its inputs) is paid once per rollout rather than once per step. With ``record`` (and every
    parameter shared; ``None``: once the stage is worth its trace), a stage is
    replayed from its operator graph, recorded once per signature (:mod:`~torchtraj.core.recorded`): the same
    numbers to the last bit in fewer, cheaper calls.
    """
    N = U.shape[-2]
    feedback = K is not None

    def simulate(x, Uk, Xr, Kk, p):
        # the stages' operands split by one call each, not indexed stage by stage
        Us, xs, us = Uk.unbind(0), [x], []
        Xrs, Ks = (Xr.unbind(0), Kk.unbind(0)) if feedback else ((None,) * N, (None,) * N)
        for k in range(N):
            x, u = _closed_loop_step(dynamics, feedback, x, Us[k], Xrs[k], Ks[k], p)
            xs.append(x)
            us.append(u)
        return torch.stack(xs), torch.stack(us)

    lead = x0.shape[:-1]
    B, E = lead[0], math.prod(lead[1:])
    if not feedback:
        X_ref = K = x0.new_zeros(B, 0)  # unused placeholders
    p, p_dims, all_shared = _split_params(params)
    x0 = x0.reshape(B, E, x0.shape[-1])
    U = U.reshape(B, E, N, U.shape[-1])
    if all_shared:
        # one vmap level over the B·E trajectories, the feedback repeated for each of an instance's E: a second
        # level costs a transposition of every batched intermediate (the pendulum's RK4 step: 91 calls, not 83)
        def repeated(t: Tensor) -> Tensor:
            return t.unsqueeze(1).expand(B, E, *t.shape[1:]).reshape(B * E, *t.shape[1:])

        inputs = (x0.reshape(B * E, -1), U.reshape(B * E, N, -1), repeated(X_ref), repeated(K))
        replayed = None
        if record is not False and not torch.compiler.is_compiling():
            replayed = _recorded_stages(dynamics, feedback, *inputs, p, trace_at(record))
        X, Us = replayed if replayed is not None else vmap(lambda x, Uk, Xr, Kk: simulate(x, Uk, Xr, Kk, p))(*inputs)
    else:
        per_trajectory = vmap(simulate, in_dims=(0, 0, None, None, None))  # over E, for one instance
        X, Us = vmap(per_trajectory, in_dims=(0, 0, 0, 0, p_dims))(x0, U, X_ref, K, p)
    return X.reshape(*lead, N + 1, X.shape[-1]), Us.reshape(*lead, N, Us.shape[-1])


def padded_rows(n: int) -> int:
    """The number of trajectories a recorded rollout of ``n`` runs: ``n`` up to 4, else the next of
    ``2^k`` and ``3 · 2^(k−1)``, so that the many batch sizes of the line searches' and the compacted batches' rows
    (every count of pending instances times the candidates) share a few records, each padded by at most half."""
    if n <= 4:
        return n
    power = 1 << (n - 1).bit_length()  # the next power of two
    return 3 * power // 4 if 3 * power // 4 >= n else power


def _pad_rows(t: Tensor, rows: int) -> Tensor:
    """``t (n, ...)`` with its last row repeated to ``rows`` rows (``t`` itself where ``rows = n``)."""
    extra = rows - t.shape[0]
    return t if extra == 0 else torch.cat([t, t[-1:].expand(extra, *t.shape[1:])])


def _recorded_stages(dynamics: Callable, feedback: bool, x: Tensor, U: Tensor, X_ref: Tensor, K: Tensor, p: Params,
                     calls: int) -> Optional[tuple]:
    """:func:`closed_loop_rollout`'s trajectories ``(X, U)``, each stage a call of the recorded :func:`_stage_step`
    (its stages' operands are views of one buffer each, which share a record); ``None`` while the stage is not
    worth its trace: the rollout's ``N`` stages count as ``N`` calls of the stage's signature, traced at the
    ``calls``-th, and until then (or where the trace failed) they run eager under one ``vmap``, whose fixed cost is
    paid once a rollout rather than once a stage. The trajectories are padded to :func:`padded_rows` (copies of the
    last one, whose results are dropped): each trajectory's arithmetic is its own, whatever the rows beside it."""
    N, n = U.shape[-2], x.shape[0]
    rows = padded_rows(n)
    x, U, X_ref, K = (_pad_rows(t, rows) for t in (x, U, X_ref, K))
    x = x.contiguous()  # as the stages' states are (a line search's candidates start from one expanded state)
    Us, xs, us = U.unbind(1), [x], []
    Xrs, Ks = (X_ref.unbind(1), K.unbind(1)) if feedback else ((X_ref,) * N, (K,) * N)
    step = _RECORDED_STAGE_STEP.loop(dynamics, feedback, x, Us[0], Xrs[0], Ks[0], p, calls=N, trace_at=calls,
                                     varying=4)  # the parameters' products are made once, not once a stage
    if step is None:
        return None
    layout = (x.shape, x.stride(), x.dtype)  # the record's: a stage whose state has another (a user's dynamics)
    for k in range(N):  # looks its own record up
        if (x.shape, x.stride(), x.dtype) == layout:
            x, u = step(x, Us[k], Xrs[k], Ks[k])
        else:
            x, u = _RECORDED_STAGE_STEP(dynamics, feedback, x, Us[k], Xrs[k], Ks[k], p, trace_at=calls)
        xs.append(x)
        us.append(u)
    X, Us = torch.stack(xs, 1), torch.stack(us, 1)
    return (X, Us) if rows == n else (X[:n], Us[:n])
