"""Evaluating per-instance user functions on batches, with ``torch.func.vmap``.

User functions see one instance: ``f(x (nx,), u (nu,), p)``. Solvers hold tensors shaped
``(B, *E, n)``: a batch dimension B (to which the parameters ``p`` belong) followed by any
number of extra dimensions E (time steps, line-search candidates). :func:`map_stage` and
:func:`map_state` flatten E, vmap over it with ``p`` held fixed, vmap again over B with
``p`` batched, and restore the shape. No Python loop over the batch.
"""

from __future__ import annotations

from typing import Callable, Mapping

import torch
from torch import Tensor
from torch.func import vmap

Params = Mapping[str, Tensor]


def _map(fn: Callable, tensors: tuple, params: Params) -> Tensor:
    lead = tensors[0].shape[:-1]
    B = lead[0]
    E = 1
    for n in lead[1:]:
        E *= n
    # a parameter expanded from one instance (stride 0, or B = 1) is shared: it is not mapped
    shared = {k for k, v in params.items() if v.shape[0] == 1 or v.stride(0) == 0}
    p = {k: (v[0] if k in shared else v) for k, v in params.items()}
    p_dims = {k: (None if k in shared else 0) for k in params}
    n_in = len(tensors)
    if len(shared) == len(params):
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


def map_state(fn: Callable, X: Tensor, params: Params) -> Tensor:
    """``fn(x, p)`` on ``X (B, *E, nx)`` with ``params`` batched over B."""
    return _map(fn, (X,), params)


def rollout(dynamics: Callable, x0: Tensor, U: Tensor, params: Params) -> Tensor:
    """Simulate ``x_{k+1} = f(x_k, u_k, p)`` from ``x0 (B, *E, nx)`` under ``U (B, *E, N, nu)``.

    Returns ``X (B, *E, N+1, nx)``.
    """
    x = x0
    xs = [x]
    for k in range(U.shape[-2]):
        x = map_stage(dynamics, x, U[..., k, :], params)
        xs.append(x)
    return torch.stack(xs, -2)
