"""How the interior-point method runs its per-iteration kernels: eager, compiled, or replayed from CUDA graphs.

Every module of the IPM asks here, and only here, whether CUDA graphs are used (the crossover masks rows instead
of gathering them, finished instances stay in the batch): one answer for the whole solve, and one place to force
it (the tests force the masked crossover on a CPU by replacing :func:`graphs_used` in this module).
"""

from __future__ import annotations

import torch

from ...core.compiled import kernel
from ...core.graphs import graphed, graphs_used
from .options import IPOptions


def uses_graphs(opts: IPOptions, device: torch.device) -> bool:
    """Whether the solve replays CUDA graphs (:func:`~torchtraj.core.graphs.graphs_used`)."""
    return graphs_used(opts, device)


def compiled_kernels(opts: IPOptions, device: torch.device) -> bool:
    """Whether :func:`kernel_of` compiles the solve's kernels (``opts.compile``, and no CUDA graphs)."""
    return opts.compile and not uses_graphs(opts, device)


def eager_kernels(opts: IPOptions, device: torch.device) -> bool:
    """Whether :func:`kernel_of` returns every function itself: neither compiled nor replayed from CUDA graphs."""
    return not opts.compile and not uses_graphs(opts, device)


def kernel_of(fn, opts: IPOptions, device: torch.device):
    """``fn`` compiled (``opts.compile``), replayed from CUDA graphs (:func:`uses_graphs`), or itself."""
    if uses_graphs(opts, device):
        return graphed(fn)
    return kernel(fn, opts.compile)


def kernel_on_call(fn, opts: IPOptions, device: torch.device):
    """:func:`kernel_of` made at the first call: a kernel that a solve may not call (the barrier update where the
    iteration's start makes it, the expansion alone, the iteration's end where the line search's kernel makes it) is
    neither compiled nor counted among the kernels."""
    made = []

    def call(*args):
        if not made:
            made.append(kernel_of(fn, opts, device))
        return made[0](*args)
    return call
