r"""One large batch solved across the ranks of a ``torch.distributed`` process group.

A batch of B instances (initial states ``x0 (B, nx)``, guesses ``U0 (B, N, nu)`` / ``X0 (B, N+1, nx)``, parameters
with a leading batch dimension, warm-started ``duals``) is cut into W contiguous shards balanced by instance count:
rank r of W solves instances

.. math::

    [\,l_r, l_{r+1}), \qquad l_r = r \lfloor B / W \rfloor + \min(r,\ B \bmod W),

with :func:`torchtraj.solve` on its own device, exactly as a one-process solve would (each instance's iterations
only ever see that instance: the batch-isolation rule of the solvers, so the gathered answer is the one-process
answer). The shards' :class:`~torchtraj.Solution` fields are then gathered in instance order where asked
(``gather="all"``, one rank's index, or ``"none"`` to leave them sharded) with tensor collectives: per dtype, every
field of a shard is packed into one flat buffer, padded to the longest shard's and exchanged by ``all_gather`` /
``gather``; only the small metadata (shard sizes, field shapes, an ok flag and an error message) goes through
``all_gather_object``.

What is gathered: ``X``, ``U``, ``K``, ``cost``, ``max_violation``, ``status``, ``iterations``, ``costate``, every
block of ``multipliers`` and ``penalties``, the KKT residuals ``kkt`` and the :class:`~torchtraj.History`. Histories
are ``(B_r, T_r)`` with ``T_r`` the shard's own iteration count. After an instance stopped, the solvers record its
final values again at every later iteration, with step size 0 (no step was taken), so a shard's history is extended
to the largest ``T`` the same way, by its last column and a zero step size: what a one-process solve of the whole
batch records. Gathered tensors carry no gradients (collectives are not differentiated); to train through the solver
on several processes, let each rank call :func:`torchtraj.solve` on its share under ``DistributedDataParallel``
(``examples/learn_dynamics_ddp.py``).

Failures: every rank catches the exception of its own solve; the ranks exchange an ok flag and the message, and
then *every* rank raises a ``RuntimeError`` naming each failing rank and its reason, so no rank is left waiting in
a collective. A rank that never arrives (killed, hung) is caught by the process group's timeout, which
``init_process_group(timeout=...)`` sets (default 30 minutes for Gloo and NCCL; the tests use seconds).

Several machines: nothing here depends on the backend or the launcher. On one machine with CPU processes::

    torch.distributed.init_process_group("gloo")                  # under torchrun --nproc-per-node 2
    sol = torchtraj.distributed.solve(problem, x0, method="altro", gather="all")

On several GPU nodes the same code runs with ``init_process_group("nccl")``, the problem moved to the rank's GPU
(``problem.to(device=f"cuda:{local_rank}")``, ``torch.cuda.set_device(local_rank)``) and the launcher's arguments
``torchrun --nnodes 4 --nproc-per-node 8 --rdzv-backend c10d --rdzv-endpoint HOST:PORT ...``: the collectives
then move the packed buffers GPU to GPU. Without an initialised process group (or with one rank) :func:`solve` is
:func:`torchtraj.solve`.
"""

from __future__ import annotations

import math
import traceback
from typing import Optional, Union

import torch
import torch.distributed as dist
from torch import Tensor

from .core.batch import Batch
from .core.constraints import map_duals
from .core.problem import Problem
from .core.solution import History, Solution
from .solve import solve as solve_one

HISTORY_BASE = ("cost", "max_violation", "step_size", "regularization")
#: The :class:`~torchtraj.Solution` fields the gather carries (a field added to Solution belongs here; a test checks).
GATHERED = ("X", "U", "K", "cost", "max_violation", "status", "iterations", "history", "costate", "multipliers",
            "penalties", "method", "kkt")
#: What the solvers record for an instance after it stopped, where it is not its last value: no step taken.
STOPPED_FILL = {"history/step_size": 0.0}


def world() -> tuple:
    """``(rank, world size)`` of the default process group, ``(0, 1)`` without one."""
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def shard(count: int, rank: int, size: int) -> slice:
    """The instances ``[l_r, l_{r+1})`` of rank ``rank`` among ``size`` ranks (module docstring): contiguous, in
    order, the shard sizes differing by at most one."""
    base, extra = divmod(count, size)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (rank < extra))


def solve(problem: Problem, x0=None, method=None, U0=None, X0=None, options=None, duals: Optional[dict] = None,
          gather: Union[str, int] = "all") -> Optional[Solution]:
    """Solve a batch across the ranks of the default process group; every rank calls it with the same arguments.

    Args:
        problem, x0, method, U0, X0, options, duals: as for :func:`torchtraj.solve`, for the *whole* batch;
            tensors with a leading batch dimension B (``x0 (B, nx)``, ``U0 (B, N, nu)``, ``X0 (B, N+1, nx)``,
            batched parameters ``(B, ...)``, every tensor of ``duals`` with leading dimension B) are cut into
            shards (:func:`shard`), the others are shared.
        gather: ``"all"``: every rank returns the whole batch's :class:`~torchtraj.Solution`; a rank index (or
            ``"rank0"``): that rank returns it and the others ``None``; ``"none"``: each rank returns its own
            shard's solution (its instances are ``shard(B, rank, world size)``).

    Returns:
        The :class:`~torchtraj.Solution` of the whole batch in instance order (or of the shard, or ``None``, see
        ``gather``), equal to :func:`torchtraj.solve` of the whole batch in one process.

    Raises:
        RuntimeError: on every rank, when the solve of some rank's shard raised; it names the rank(s) and reasons.
    """
    rank, size = world()
    dst = _destination(gather, size)
    if size == 1:
        return solve_one(problem, x0, method, U0=U0, X0=X0, options=options, duals=duals)
    local, error = None, None
    try:
        batch = Batch.build(problem, x0, U0, X0, duals)
        part = shard(batch.B, rank, size)
        if part.stop > part.start:
            local = solve_one(_shard_problem(problem, part, batch.B), batch.x0[part], method, U0=batch.U0[part],
                              X0=None if X0 is None else batch.X0[part], options=options,
                              duals=_cut(duals, part, batch.B))
    except Exception as exc:  # every rank learns of it below, then all raise together
        error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=-3)}"
    return exchange(local, error, gather=dst, device=problem.device)[0]


def exchange(local: Optional[Solution], error: Optional[str], gather: Union[str, int] = "all",
             device=None) -> tuple:
    """The failure protocol and the gather of :func:`solve`, for a caller that solved its own part already.

    Every rank passes its part's solution (``None`` for an empty part) or the ``error`` text of its failure. Returns
    ``(solution, sizes)``: the parts concatenated in rank order (on every rank for ``"all"``, on rank ``gather``
    for an index, the rank's own part for ``"none"``; ``None`` elsewhere) and the list of part sizes per rank.
    Raises ``RuntimeError`` on every rank if some rank passed an ``error``.
    """
    rank, size = world()
    dst = _destination(gather, size)
    meta = _metadata(local, error)
    metas = [None] * size
    if size == 1:
        metas = [meta]
    else:
        dist.all_gather_object(metas, meta)
    failed = [(r, m["error"]) for r, m in enumerate(metas) if m["error"] is not None]
    if failed:
        raise RuntimeError("distributed solve failed on " + "; ".join(f"rank {r}: {why}" for r, why in failed))
    sizes = [m["size"] for m in metas]
    template = next((m for m in metas if m["size"]), None)
    if template is None:  # an empty batch everywhere
        return None, sizes
    for r, m in enumerate(metas):
        if m["size"] and m["fields"] != template["fields"]:
            raise RuntimeError(f"distributed solve: rank {r} returned the fields {m['fields']}, rank "
                               f"{metas.index(template)} {template['fields']}")
    steps = max(m["steps"] for m in metas)
    if dst == "none":
        steps = meta["steps"] if meta["size"] else 0
    spec = _spec(template["fields"], steps)
    device = device if local is None else local.X.device
    flat = _flatten(local, meta["size"], spec, steps, device)
    groups = sorted({dtype for _, _, dtype in spec})
    if dst == "none" or size == 1:  # nothing to move
        parts = [_unpack({d: _pack(flat, spec, d) for d in groups}, spec, meta["size"])]
        return _assemble(parts, spec, template["method"]), sizes
    gathered = {d: _collect(_pack(flat, spec, d), sizes, spec, d, dst, rank, size) for d in groups}
    if dst != "all" and rank != dst:
        return None, sizes
    parts = [_unpack({d: gathered[d][r] for d in groups}, spec, sizes[r]) for r in range(size) if sizes[r]]
    return _assemble(parts, spec, template["method"]), sizes


def _destination(gather, size: int):
    if gather in ("all", "none"):
        return gather
    if gather == "rank0":
        return 0
    if isinstance(gather, int) and 0 <= gather < size:
        return gather
    raise ValueError(f"gather must be 'all', 'none', 'rank0' or a rank in [0, {size}), got {gather!r}")


def _shard_problem(problem: Problem, part: slice, count: int) -> Problem:
    """``problem`` with its batched parameters cut to the shard; the shared ones stay as they are."""
    cut = {k: v[part] for k, v in problem.params.items()
           if v.dim() == len(problem.param_shapes.get(k, v.shape)) + 1 and v.shape[0] == count}
    return problem.with_params(**cut) if cut else problem


def _cut(duals: Optional[dict], part: slice, count: int) -> Optional[dict]:
    """Every tensor of the ``duals`` warm start with leading dimension ``count`` cut to ``part``."""
    if duals is None:
        return None
    return map_duals(duals, lambda t: t[part] if t.dim() and t.shape[0] == count else t)


def _fields(sol: Solution) -> dict:
    """The solution's tensors by flat name: the fields, ``multipliers/<block>``, ``penalties/<block>``,
    ``kkt/<residual>``, ``history/<name>``."""
    out = {k: getattr(sol, k) for k in ("X", "U", "K", "cost", "max_violation", "status", "iterations")}
    if sol.costate is not None:
        out["costate"] = sol.costate
    out.update({f"multipliers/{k}": v for k, v in sol.multipliers.items()})
    out.update({f"penalties/{k}": v for k, v in sol.penalties.items()})
    out.update({f"kkt/{k}": v for k, v in sol.kkt.items()})
    h = sol.history
    out.update({f"history/{k}": getattr(h, k) for k in HISTORY_BASE})
    out.update({f"history/extra/{k}": v for k, v in h.extra.items()})
    return out


def _metadata(local: Optional[Solution], error: Optional[str]) -> dict:
    if error is not None or local is None:
        return {"error": error, "size": 0, "fields": None, "steps": 0, "method": ""}
    fields = []
    for name, t in _fields(local).items():
        trailing = list(t.shape[2:]) if name.startswith("history/") else list(t.shape[1:])
        fields.append((name, trailing, str(t.dtype).removeprefix("torch.")))
    return {"error": None, "size": local.batch_size, "fields": fields, "steps": len(local.history),
            "method": local.method}


def _spec(fields: list, steps: int) -> list:
    """``[(name, trailing shape, dtype name)]`` with the histories' time dimension set to ``steps``."""
    return [(n, ([steps] if n.startswith("history/") else []) + list(s), d) for n, s, d in fields]


def _extend(t: Tensor, count: int, steps: int, fill: Optional[float] = None) -> Tensor:
    """A history ``(B, T, ...)`` extended to ``steps`` by repeating its last entry, or by ``fill`` where given
    (NaN where it has no entry)."""
    if t.shape[0] != count or t.dim() < 2:  # History.from_rows([]) of a solve without iterations
        t = torch.full((count, 0), float("nan"), dtype=t.dtype, device=t.device)
    have = t.shape[1]
    if have == steps:
        return t
    if have == 0:
        return torch.full((count, steps, *t.shape[2:]), float("nan"), dtype=t.dtype, device=t.device)
    tail = t[:, -1:].expand(count, steps - have, *t.shape[2:])
    return torch.cat([t, tail if fill is None else torch.full_like(tail, fill)], dim=1)


def _flatten(local: Optional[Solution], count: int, spec: list, steps: int, device) -> dict:
    """The local part's tensors by name, histories extended to ``steps``; empty tensors for an empty part."""
    if local is None:
        return {n: torch.empty((0, *s), dtype=getattr(torch, d), device=device) for n, s, d in spec}
    found = _fields(local)
    return {n: _extend(found[n], count, steps, STOPPED_FILL.get(n)) if n.startswith("history/") else found[n]
            for n, _, _ in spec}


def _wire(dtype_name: str) -> torch.dtype:
    """The dtype a field travels as (bool as uint8: not every backend reduces or gathers bool)."""
    return torch.uint8 if dtype_name == "bool" else getattr(torch, dtype_name)


def _pack(flat: dict, spec: list, dtype_name: str) -> Tensor:
    parts = [flat[n].reshape(-1).to(_wire(d)) for n, _, d in spec if d == dtype_name]
    return torch.cat(parts)


def _collect(buffer: Tensor, sizes: list, spec: list, dtype_name: str, dst, rank: int, size: int) -> list:
    """Every rank's buffer of one dtype, padded to the longest and gathered (all ranks, or ``dst`` only)."""
    per_instance = sum(math.prod(s) for _, s, d in spec if d == dtype_name)
    longest = max(sizes) * per_instance
    padded = torch.zeros(longest, dtype=buffer.dtype, device=buffer.device)
    padded[: buffer.numel()] = buffer
    if dst == "all":
        out = [torch.empty_like(padded) for _ in range(size)]
        dist.all_gather(out, padded)
    else:
        out = [torch.empty_like(padded) for _ in range(size)] if rank == dst else None
        dist.gather(padded, out, dst=dst)
    if out is None:
        return []
    return [o[: sizes[r] * per_instance] for r, o in enumerate(out)]


def _unpack(buffers: dict, spec: list, count: int) -> dict:
    offsets = dict.fromkeys(buffers, 0)
    out = {}
    for name, shape, d in spec:
        n = count * math.prod(shape)
        out[name] = buffers[d][offsets[d]: offsets[d] + n].reshape(count, *shape).to(getattr(torch, d))
        offsets[d] += n
    return out


def _assemble(parts: list, spec: list, method: str) -> Solution:
    """One :class:`~torchtraj.Solution` from the parts' tensors, concatenated in rank (= instance) order."""
    whole = {n: torch.cat([p[n] for p in parts]) for n, _, _ in spec}

    def block(prefix: str) -> dict:
        return {n[len(prefix):]: v for n, v in whole.items() if n.startswith(prefix)}

    extra = block("history/extra/")
    history = History(**{k: whole[f"history/{k}"] for k in HISTORY_BASE}, extra=extra)
    return Solution(X=whole["X"], U=whole["U"], K=whole["K"], cost=whole["cost"], max_violation=whole["max_violation"],
                    status=whole["status"], iterations=whole["iterations"], history=history,
                    costate=whole.get("costate"), multipliers=block("multipliers/"), penalties=block("penalties/"),
                    method=method, kkt=block("kkt/"))
