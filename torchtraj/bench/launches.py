"""CUDA kernel launches of a solve, counted by the torch profiler (``python -m torchtraj.bench --launches``).

On a GPU an eager iteration costs its launches: each kernel is a host call (Python, the dispatcher, the CUDA
runtime) of a few microseconds, whatever the batch, so at a moderate batch the launches, not the arithmetic, set
the time. The profiler (CUPTI, ``ProfilerActivity.CUDA``) sees both sides:

- on the host, the runtime and driver calls that start work on the GPU: kernel launches (``cudaLaunchKernel`` and
  its variants), CUDA graph replays (``cudaGraphLaunch``: one call, many kernels), and asynchronous copies and fills;
  and the calls that wait for the GPU (stream, event and device synchronisations, blocking copies);
- on the GPU, every kernel that ran, a graph's kernels included, and the copies and fills.

:func:`count` runs a function under the profiler and tallies its events (:func:`tally`); :func:`line` writes the
tally per iteration of the batch's loop (its longest instance's iterations: the loop runs until the last instance
ends). With ``--launches --device cuda`` the bench solves each problem's largest batch once more under the profiler,
after its timed rows (:func:`report`). Profiling adds its own overhead, so the profiled run is not a timing to
quote.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Callable, Iterable

import torch

#: host calls that launch one kernel each
KERNEL_LAUNCHES = frozenset({"cudaLaunchKernel", "cudaLaunchKernelExC", "cudaLaunchCooperativeKernel",
                             "cuLaunchKernel", "cuLaunchKernelEx"})
#: host calls that replay a captured CUDA graph
GRAPH_LAUNCHES = frozenset({"cudaGraphLaunch", "cuGraphLaunch"})
#: host calls that start an asynchronous copy or fill
COPY_LAUNCHES = frozenset({"cudaMemcpyAsync", "cudaMemsetAsync", "cudaMemcpy2DAsync", "cuMemcpyAsync",
                           "cuMemsetD8Async", "cuMemsetD32Async"})
#: host calls that wait for the GPU
WAITS = frozenset({"cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy",
                   "cuStreamSynchronize", "cuCtxSynchronize"})


@dataclass
class Launches:
    """What one profiled run started on the GPU (counts over the whole run)."""

    kernel_launches: int = 0  # host calls that launch one kernel
    graph_launches: int = 0  # host calls that replay a CUDA graph
    copy_launches: int = 0  # host calls that start a copy or a fill
    waits: int = 0  # host calls that wait for the GPU
    kernels: int = 0  # kernels that ran on the GPU, those of graphs included
    copies: int = 0  # copies and fills that ran on the GPU

    @property
    def host_launches(self) -> int:
        """Every host call that started work on the GPU."""
        return self.kernel_launches + self.graph_launches + self.copy_launches


def _on_gpu(event) -> bool:
    return getattr(event, "device_type", None) == torch.autograd.DeviceType.CUDA


def tally(events: Iterable) -> Launches:
    """The :class:`Launches` of profiler events (``torch.profiler.profile(...).events()``: each has ``name`` and
    ``device_type``; events averaged by name, with a ``count``, are counted ``count`` times)."""
    out = Launches()
    for event in events:
        name, times = event.name if hasattr(event, "name") else event.key, getattr(event, "count", 1)
        if _on_gpu(event):
            if name.startswith(("Memcpy", "Memset")):
                out.copies += times
            else:
                out.kernels += times
        elif name in KERNEL_LAUNCHES:
            out.kernel_launches += times
        elif name in GRAPH_LAUNCHES:
            out.graph_launches += times
        elif name in COPY_LAUNCHES:
            out.copy_launches += times
        elif name in WAITS:
            out.waits += times
    return out


def count(fn: Callable, device: torch.device):
    """``(fn(), Launches)``: ``fn`` run once under the profiler, the GPU synchronised before the profile ends."""
    device = torch.device(device)
    if device.type != "cuda":
        raise ValueError(f"kernel launches are counted on a CUDA device, not {device}")
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize(device)
    # the CPU activity as well: the runtime calls are host events, which some builds record under it alone
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        result = fn()
        torch.cuda.synchronize(device)
    return result, tally(prof.key_averages())


def line(name: str, method: str, batch: int, launches: Launches, iterations: int) -> str:
    """One report line: the counts per iteration of the batch's loop (``iterations``: its longest instance's)."""
    per = max(iterations, 1)
    return (f"  launches ({name}, {method}, B={batch}, {iterations} iterations of the batch's loop, profiled run): "
            f"{launches.host_launches / per:,.0f} host launch calls an iteration (kernels "
            f"{launches.kernel_launches / per:,.0f}, graph replays {launches.graph_launches / per:,.1f}, copies and "
            f"fills {launches.copy_launches / per:,.1f}), {launches.kernels / per:,.0f} kernels ran on the GPU an "
            f"iteration, {launches.waits / per:,.1f} waits for the GPU an iteration")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--launches`` flag of ``python -m torchtraj.bench``'s timing rows."""
    p.add_argument("--launches", action="store_true",
                   help="with --device cuda: after each problem's rows, solve its largest batch once more under the "
                        "torch profiler and print the CUDA launches an iteration (torchtraj.bench.launches)")


def check(p: argparse.ArgumentParser, args) -> None:
    """Refuse ``--launches`` where nothing is launched (``p.error``)."""
    if args.launches and (args.device != "cuda" or args.ops or args.grad or args.profile):
        p.error("--launches goes with --device cuda and the timing rows (not --ops, --grad or --profile)")


def report(problem, method: str, batch: int, run: Callable) -> str:
    """:func:`line` of ``run()``, a solve of ``batch`` instances of ``problem`` returning its solution."""
    solution, launches = count(run, problem.device)
    return line(problem.name, method, batch, launches, int(solution.iterations.max()))
