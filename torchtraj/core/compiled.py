"""Opt-in ``torch.compile`` of the solvers' per-iteration kernels (``ILQROptions.compile``).

In eager mode a solver iteration is a few thousand small PyTorch operations — a rollout is N dynamics calls,
the Riccati sweep N small factorisations — and at small batches their fixed per-operation cost, not the
arithmetic, is the time. Compiled by inductor into fused loops, a control step takes a fraction of its eager time
(``python -m torchtraj.bench --mpc --compile``; the figures are in ``docs/benchmarks.md``). The kernels:

* one iLQR iteration (:func:`torchtraj.solvers.ilqr.ilqr_step`: the ``torch.func`` expansion, the Riccati sweep of
  :mod:`torchtraj.riccati`, the line search's batched rollouts and the step acceptance) — one graph while the
  line search takes a single round of step sizes (``B ≤ 8192 / line_search_steps``), else one per round;
* the initial rollout, objective and violation, and the final gains and costates (iLQR) or cost and violation
  (ALTRO);
* per ALTRO iteration, the violation, the multiplier update and the objective under the new multipliers
  (:func:`torchtraj.solvers.altro.stages._measures`), and the MPC policy's own multiplier update.
* the interior point's, eILQR's and HM-iLQR's expansions, Newton steps (or backward passes and solves) and trial
  points (:mod:`torchtraj.solvers.ipm.kernels`, ``EILQROptions.compile``, ``HMILQROptions.compile``); eILQR's
  per-instance decisions ride in its kernels (:mod:`torchtraj.solvers.eilqr.verdicts`), so an iteration is about
  four compiled calls.

The loops over iterations, the masks and the host synchronisations stay in Python, so the solver's logic is the
same code in both modes and its answers agree to rounding (``tests/test_compiled.py``).

Costs: the first call of each kernel for a new problem, horizon, dtype or batch size it specialises to traces and
compiles it (tens of seconds; minutes for a whole ALTRO step on two cores), which pays off only for repeated solves —
an MPC policy, a training loop.

The batch dimension is compiled dynamic: before each call, dim 0 of the arguments' tensors that carry the batch is
marked with ``torch._dynamo.maybe_mark_dynamic`` (:func:`mark_batch`); every other size (horizon, state, control and
constraint sizes, the line search's step sizes) stays static, as the Riccati sweeps and rollouts unroll Python loops
over the horizon and choose their contractions by size (:func:`matmul`). Dynamo's automatic dynamic shapes are
off while a kernel compiles (:data:`STATIC_SIZES`, what ``torch.compile(dynamic=False)`` sets): they would compile
again at the second batch size seen, and make any other size that changed between two calls symbolic too.
``maybe_mark_dynamic``, not ``mark_dynamic``: a kernel whose traced code specialises the batch size does so without
an error, and compiles once per batch size as before. Dynamo specialises sizes 0 and 1, so B = 1 always has graphs of
its own; ``tt.solve`` tells its kernels the batch size (:func:`batch_of`), and a solve of one instance marks nothing
and runs each kernel's second compilation, whose buffers are on the stack (:data:`SINGLE_OPTIONS`,
:func:`single_instance`). The setting is made once a solve, by :func:`batch_of`, rather than around each call as
``dynamic=False`` makes it (two of Dynamo's settings changed and restored: about a tenth of a small kernel's call);
a kernel called outside a solve makes it around its call.

Every kernel of iLQR, ALTRO (its AL objective, violation and multiplier update) and the interior point is compiled
once for every B ≥ 2 (``tests/test_compiled.py``, ``tests/test_compiled_ipm.py``). Two things in their code keep it
so, because ``torch.func.vmap``'s batching rules in PyTorch 2.13 read concrete sizes of a vmapped tensor, which
specialises a graph to B: per-instance vectors are joined by :func:`~torchtraj.core.batching.concat` (zero pads and a
sum when traced) rather than ``torch.cat`` (the stacked constraint rows of
:class:`~torchtraj.core.constraints.Constraints` and of the augmented Lagrangian), and the expansions differentiate
the mapped functions by pullbacks outside ``vmap`` (:mod:`torchtraj.core.derivatives` for iLQR,
:mod:`torchtraj.core.one_pass` for the interior point and ALTRO) rather than by ``jacrev`` inside it, whose backward
operations (``slice_backward``, ``cat``) have the same effect. A user's function that concatenates per-instance
vectors with ``torch.cat`` specialises the kernels that evaluate it to B again (one compilation per batch size).

Dynamo guards each kernel's specialisation on everything its trace read, and at B = 1 checking the guards is a
share of a call's time, and about a third of a large kernel's guards are on module globals (the functions it calls
and their code). The kernels keep none on the globals of torch's and torchtraj's modules, of ``dataclasses`` and
the builtins (:func:`kept_guards`): a library's module-level values do not change while a process runs (a test that
patches one inside a kernel resets Dynamo first). Guards on everything else stay: the arguments' tensors, the
options' values, the problem's functions and their closures, and the globals of any other module (a constant in
the user's module that a problem's function reads, whose change compiles the kernel again).

Every kernel is compiled with Inductor's C++ wrapper and a graph pass that fuses the products of short contractions
that the library's code (:func:`matmul`) does not reach, those of the user's functions, into the kernel's loops
(:data:`OPTIONS`, :mod:`~torchtraj.core.short_products`); a kernel may add options of its own for its
batched graphs (:func:`batched_options`: the interior point's expansion, whose loops over the batch are faster without
masked vectors of a stage's two or three rows).

Each kernel keeps up to :data:`RECOMPILE_LIMIT` specialisations (problems × horizons × dtypes, and batch sizes where
the kernel specialises them) before falling back to eager: the first compiled kernel raises
``torch._dynamo.config.recompile_limit`` to it (a process-wide setting). A C++ compiler is needed on CPU (inductor's
requirement).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import types
from typing import Callable

import torch
from torch import Tensor

from . import batching, stack_buffers
from .constraints import Constraints
from .problem import Problem
from .short_products import ShortProducts

#: Contractions up to this length are written as broadcast products and sums when traced (:func:`matmul`, and the
#: user's products by :mod:`~torchtraj.core.short_products`).
FUSED_CONTRACTION = 8

#: The smallest batch a kernel's dynamic batch dimension serves: Dynamo specialises sizes 0 and 1 whatever the mark,
#: so a batch of one has graphs of its own (and a compiled solve does not compact its batch below this).
DYNAMIC_FROM = 2

#: The most stages a compiled rollout unrolls: a longer horizon is rolled out by the same kernel in
#: pieces of this many stages, so that its generated code stops growing with the horizon (the pendulum's rollout at
#: N = 100 was 1.2 MB of C++, the largest of the interior point's kernels; at N = 400 its compilation ran for half an
#: hour).
ROLLOUT_STAGES = 50

#: Specialisations kept per kernel (Dynamo's default of 8 is reached by three MPC tasks in one process).
RECOMPILE_LIMIT = 64

#: Inductor's options for every kernel: a C++ wrapper around its loops (no Python between them), and the user's
#: short products fused into them (:mod:`~torchtraj.core.short_products`).
OPTIONS = {"cpp_wrapper": True, "post_grad_custom_pre_pass": ShortProducts(FUSED_CONTRACTION)}

#: And for the graphs of a single instance (:func:`batch_of` below :data:`DYNAMIC_FROM`, sizes all static): the
#: buffers of a call on the stack (:mod:`~torchtraj.core.stack_buffers`), or pooled in one allocation where the
#: graph calls a library kernel. A B = 1 kernel's hundreds of tiny buffers are most of its time (``malloc`` and
#: tensor handles, not arithmetic; the figures are in ``docs/benchmarks.md``). Batched graphs keep the default.
SINGLE_OPTIONS = {**OPTIONS, "memory_planning": True, stack_buffers.OPTION: True}

#: Dynamo's settings for a kernel's compilation (module docstring): sizes static but for those marked dynamic, and no
#: automatic dynamic shapes; a context manager, entered once a solve (:func:`batch_of`). Dynamo's settings are
#: context-local, so the setting holds for the solve's thread alone.
STATIC_SIZES = functools.partial(torch._dynamo.config.patch, automatic_dynamic_shapes=False,
                                 assume_static_by_default=True)

_KERNELS: dict = {}


def batched_options(options: dict) -> Callable:
    """Decorate a kernel with Inductor options for its batched graphs, added to :data:`OPTIONS` (a single
    instance's graphs keep :data:`SINGLE_OPTIONS`): a setting measured to pay for that kernel alone."""
    return _marking("batched_options", options)


def single_options(options: dict) -> Callable:
    """Decorate a kernel with Inductor options for the graphs of a single instance, over :data:`SINGLE_OPTIONS`: a
    setting that such a kernel needs (its batched graphs keep theirs)."""
    return _marking("single_options", options)


def _marking(attribute: str, options: dict) -> Callable:
    def mark(fn: Callable) -> Callable:
        setattr(fn, attribute, options)
        return fn
    return mark


#: For the kernels that hold a factorisation with back-propagated rows, its stages unrolled (hundreds of buffers):
#: Inductor's memory planning, a single instance's option, raised a RecursionError on one of ALTRO's projection kernels.
unplanned_single = single_options({"memory_planning": False})


#: The batch size of the solve running in this context (:func:`batch_of`; 0: not told).
_BATCH: contextvars.ContextVar = contextvars.ContextVar("torchtraj_batch", default=0)


def kernel(fn: Callable, enabled: bool) -> Callable:
    """``fn`` itself, or (``enabled``) its compiled version, built once per function and shared by every call.

    ``fn`` must be a module-level function or an unbound method (``type(obj).method``, called with ``obj`` first),
    so that one compiled wrapper, and Dynamo's cache of its specialisations, serves every solve.
    """
    if not enabled:
        return fn
    compiled = _KERNELS.get(fn)
    if compiled is None:
        compiled = _KERNELS[fn] = _compile(fn)
    return compiled


def rollout_kernel(enabled: bool) -> Callable:
    """:func:`~torchtraj.core.batching.rollout` as a kernel (``enabled``), which unrolls at most
    :data:`ROLLOUT_STAGES` stages: a longer horizon's controls go through it in consecutive pieces, each from the last
    state of the one before (the same steps in the same order; at most two specialisations, the full piece and the
    last one); or the eager function itself."""
    step = kernel(batching.rollout, enabled)
    if not enabled:
        return step

    def in_pieces(dynamics: Callable, x0: Tensor, U: Tensor, params, record=False) -> Tensor:
        N = U.shape[-2]
        if N <= ROLLOUT_STAGES:
            return step(dynamics, x0, U, params, record)
        states, x = [x0.unsqueeze(-2)], _fresh(x0)
        for start in range(0, N, ROLLOUT_STAGES):
            X = step(dynamics, x, _fresh(U[..., start:start + ROLLOUT_STAGES, :]), params, record)
            states.append(X[..., 1:, :])
            x = _fresh(X[..., -1, :])
        return torch.cat(states, -2)
    return in_pieces


def _fresh(t: Tensor) -> Tensor:
    """A copy of ``t`` in the standard contiguous layout: the rollout's pieces share one specialisation, where a view
    keeps its parent's strides (even where ``.contiguous()`` accepts it, as a single instance's views)."""
    return t.clone(memory_format=torch.contiguous_format)


def _compile(fn: Callable) -> Callable:
    # a process-wide setting (a patch around each call would cost more than a small kernel), raised only, never
    # lowered
    config = torch._dynamo.config
    config.recompile_limit = max(config.recompile_limit, RECOMPILE_LIMIT)
    # new dicts: torch.compile pops the guard filter from the one it is given
    # dynamic=None: the static sizes are set once a solve (STATIC_SIZES), or around a call outside one
    compiled = torch.compile(fn, dynamic=None, options={**OPTIONS, **getattr(fn, "batched_options", {}),
                                                        "guard_filter_fn": kept_guards})
    single_options = {**SINGLE_OPTIONS, **getattr(fn, "single_options", {}), "guard_filter_fn": kept_guards}
    if not stack_buffers.install():  # Inductor's own stack wrapper would return outputs it overwrites
        single_options.pop(stack_buffers.OPTION)
    single = torch.compile(fn, dynamic=None, options=single_options)

    def batch_dynamic(*args, **kwargs):
        batch = _BATCH.get()
        if batch == 0:  # not told (outside tt.solve): the static sizes around this call
            with STATIC_SIZES():
                return _marked_call(compiled, args, kwargs)
        if batch < DYNAMIC_FROM:  # told a single instance: nothing to mark (mark_batch)
            return single(*args, **kwargs)
        return _marked_call(compiled, args, kwargs)

    return batch_dynamic


def _marked_call(compiled: Callable, args: tuple, kwargs: dict):
    """``compiled(*args, **kwargs)`` with the batch's tensors marked for that call alone (:func:`mark_batch`,
    :func:`unmark`)."""
    marked = mark_batch(args, kwargs)
    try:
        return compiled(*args, **kwargs)
    finally:
        unmark(marked)


#: How Dynamo names the sources of library globals: the modules of torchtraj and torch, ``dataclasses`` and the
#: builtins (a global of the kernel's own module, a torchtraj module, is ``G['name']``, with no import).
_LIBRARY_GLOBALS = ("G['__import_torchtraj_dot_", "G['__import_torchtraj']", "G['__import_torch_dot_",
                    "G['__import_torch']", "G['__import_dataclasses']", "G['__builtins_dict___")


def kept_guards(entries) -> list:
    """Dynamo's ``guard_filter_fn`` for every kernel: keep each guard but those on library globals (module docstring,
    :func:`library_global`)."""
    return [not (entry.is_global and library_global(entry.name)) for entry in entries]


def library_global(source: str) -> bool:
    """Whether a guard's ``source`` (Dynamo's name of the value it checks) is a global of torch, torchtraj,
    ``dataclasses``, the builtins or the kernel's own module, and not one of another module (the user's)."""
    start = source.find("G['")
    if start < 0:
        return False
    name = source[start:]
    return name.startswith(_LIBRARY_GLOBALS) or not name.startswith("G['__import_")


@contextlib.contextmanager
def batch_of(size: int):
    """Tell the kernels called inside that the solve's batch has ``size`` instances: below :data:`DYNAMIC_FROM`
    (a single instance, whose graphs Dynamo specialises anyway) :func:`mark_batch` marks nothing without walking
    the arguments, about a third of a small kernel's call. Dynamo's sizes are static inside (:data:`STATIC_SIZES`)."""
    token = _BATCH.set(size)
    try:
        with STATIC_SIZES():
            yield
    finally:
        _BATCH.reset(token)


def single_instance(t: Tensor) -> bool:
    """Whether ``t`` is traced for a single instance's graph: by ``torch.compile``, with a batch dimension (dim 0) of
    static size 1 (a batched graph holds a symbol there, or another size). Such a graph's buffers go on the stack
    where it calls no library kernel (:data:`SINGLE_OPTIONS`, :mod:`~torchtraj.core.stack_buffers`), so its code
    avoids those calls where an elementwise form exists."""
    return torch.compiler.is_compiling() and type(t.shape[0]) is int and t.shape[0] == 1


def mark_batch(*args) -> None:
    """Mark dim 0 of the tensors in ``args`` that carry the batch dynamic for ``torch.compile`` (nothing inside
    :func:`batch_of` a single instance).

    The tensors are those in ``args``' containers (tuples, lists, dicts) and in the
    attributes of the objects among them (an augmented Lagrangian's multipliers, the IPM's iterate and model
    dataclasses), except a :class:`~torchtraj.core.problem.Problem` or :class:`~torchtraj.core.constraints.Constraints`:
    their tensors (bounds, default parameters, knot masks) are the problem's, shared by every instance. The batch
    size B is the most common dim 0 among them (the iterates, multipliers and parameters all have it); a tensor whose
    dim 0 is another size (a knot mask ``(N, m)``, a vector of step sizes) stays static. Where such a size equals B by
    chance, its mark does no harm in that call: a marked dim gets a symbol of its own (no duck shaping), which the
    kernel's first use of it against a static size specialises, or which stays symbolic in a graph correct for any
    value. Returns the tensors it marked, whose marks :func:`unmark` takes off after the call.
    """
    if 0 < _BATCH.get() < DYNAMIC_FROM:
        return []
    tensors: list = []
    _collect(args, tensors, set())
    if not tensors:
        return []
    counts: dict = {}
    for t in tensors:
        counts[t.shape[0]] = counts.get(t.shape[0], 0) + 1
    batch = max(counts, key=counts.__getitem__)
    if batch < DYNAMIC_FROM:
        return []
    marked = []
    for t in tensors:
        if t.shape[0] == batch and not hasattr(t, _MARK):
            torch._dynamo.maybe_mark_dynamic(t, 0)
            marked.append(t)
    return marked


#: the attribute of a dim marked by ``maybe_mark_dynamic``, and Dynamo's other dim marks
_MARK = "_dynamo_weak_dynamic_indices"
_OTHER_MARKS = ("_dynamo_dynamic_indices", "_dynamo_unbacked_indices", "_dynamo_strict_unbacked_indices",
                "_dynamo_static_indices")


def unmark(tensors: list) -> None:
    """The marks of :func:`mark_batch` taken off ``tensors`` after their call. A mark is an attribute of the tensor
    object, and Dynamo guards on it: a tensor that outlives the call (a problem's knot mask ``(N, m)``, marked where
    the rows of a compacted batch happened to number N) would carry it into later calls, where it need not hold,
    and kernels compiled without it would compile again."""
    for t in tensors:
        delattr(t, _MARK)
        if not any(hasattr(t, name) for name in _OTHER_MARKS):
            delattr(t, "_has_dynamo_dim_marking")


#: values that hold no tensor: skipped before a call (most attributes of an options object or an iterate are these)
_LEAVES = frozenset({type(None), bool, int, float, str})


def _collect(value, tensors: list, seen: set) -> None:
    # by hand rather than with torch.utils._pytree, whose flattening was most of a call's cost for an ALTRO
    # iteration's arguments; a tensor is taken where its container is walked (most values are tensors: a call
    # each cost more than the rest of the walk), leaves are skipped by a set lookup per value
    if isinstance(value, Tensor):
        if value.dim():
            tensors.append(value)
        return
    if isinstance(value, dict):
        value = value.values()
    elif not isinstance(value, (tuple, list)):
        if (isinstance(value, (bool, int, float, str, Problem, Constraints, type, types.ModuleType))
                or callable(value) or not hasattr(value, "__dict__") or id(value) in seen):
            return
        seen.add(id(value))
        value = vars(value).values()
    for v in value:
        kind = type(v)
        if kind in _LEAVES:
            continue
        if kind is Tensor or isinstance(v, Tensor):
            if v.dim():
                tensors.append(v)
        else:
            _collect(v, tensors, seen)


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b``. Traced by ``torch.compile`` with a short contraction (the stage matrices of small systems), a
    broadcast product and a sum, which inductor fuses into its loops: as matmuls, the products of a Riccati sweep
    and a closed-loop rollout are hundreds of library calls per kernel, each with its own fixed cost."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        return (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
    if a.dim() == 3 and b.dim() == 3 and a.shape[0] == b.shape[0]:
        return torch.bmm(a, b)  # skips matmul's broadcasting and its reshapes: a third of its cost a small product
    return a @ b


def addmatmul(c: Tensor, a: Tensor, b: Tensor, alpha: float = 1.0) -> Tensor:
    """``c + alpha · a @ b`` for batches of matrices ``(B, m, k)``, ``(B, k, n)``: one fused library call eager
    (``torch.baddbmm``), a broadcast product and sum when traced with a short contraction, as :func:`matmul` (a
    ``baddbmm`` left in a compiled kernel is a library call of its own, with its checks of the operands)."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        product = (a.unsqueeze(-1) * b.unsqueeze(-3)).sum(-2)
        return c + product if alpha == 1.0 else c + alpha * product
    return torch.baddbmm(c, a, b, alpha=alpha)


def matvec(a: Tensor, v: Tensor) -> Tensor:
    """``a @ v`` for a batch of matrices ``a (..., m, n)`` and vectors ``v (..., n)``, as :func:`matmul`."""
    if torch.compiler.is_compiling() and a.shape[-1] <= FUSED_CONTRACTION:
        return (a * v.unsqueeze(-2)).sum(-1)
    return matmul(a, v.unsqueeze(-1)).squeeze(-1)
