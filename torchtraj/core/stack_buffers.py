"""A single instance's compiled kernels with their intermediate buffers on the C++ stack.

At a batch of one a compiled kernel's arithmetic takes microseconds; its time goes to the tensor handles of its
buffers. Inductor's C++ wrapper makes a heap tensor for every intermediate buffer, and another for every view of
one (a stage's slot in a stacked output): the interior point's Newton step at B = 1 made about 800 a call.
Inductor has a wrapper that places the buffers of static shape on the stack instead, a plain array each (the
option ``aot_inductor.allow_stack_allocation`` of AOTInductor). But Inductor picks that wrapper once per process,
when it registers its backends, and it returns an output placed on the stack as a tensor over a thread-local
buffer that its next call overwrites: right for an exported model's runner, which copies its outputs; wrong for a
kernel whose outputs outlive the call.

:func:`install` registers :class:`_Chooser` as the CPU's C++ wrapper. For a graph compiled with
``aot_inductor.allow_stack_allocation`` (:data:`~torchtraj.core.compiled.SINGLE_OPTIONS`) it picks
:class:`_StackWrapper`: Inductor's stack-allocating wrapper, except that the buffers an output is or views stay
heap tensors, which the caller owns. For every other graph it picks Inductor's own wrapper, so no other
compilation in the process changes. Inductor keeps the heap for a whole graph that calls a library kernel (an
extern or fallback call, such as ``cumsum`` or an eigensolver) or holds more than 100 KB of buffers; such a graph
runs as before, with its buffers pooled where ``memory_planning`` asks for it.
"""

from __future__ import annotations

import functools
import logging

logger = logging.getLogger("torchtraj")

#: The Inductor option that asks for stack-allocated buffers (the compiled kernels' single-instance options).
OPTION = "aot_inductor.allow_stack_allocation"


@functools.cache
def install() -> bool:
    """Register :class:`_Chooser` as the CPU's C++ wrapper (once a process); whether stack allocation is available
    (``False`` on a torch whose Inductor lacks the classes it builds on: its kernels then run with heap buffers)."""
    try:
        chooser = _chooser_class()
        from torch._inductor.codegen import common
        from torch._inductor.codegen.cpp_wrapper_cpu import CppWrapperCpu

        common.init_backend_registration()
        entry = common.device_codegens["cpu"]
        if entry.cpp_wrapper_codegen is CppWrapperCpu:
            entry.cpp_wrapper_codegen = chooser
        ok = entry.cpp_wrapper_codegen is chooser
    except (ImportError, AttributeError, KeyError) as error:  # another torch release's Inductor
        logger.debug("torchtraj: no stack-allocated kernel buffers (%s)", error)
        ok = False
    return ok


def _chooser_class() -> type:
    from torch._inductor import config
    from torch._inductor.codegen.cpp_wrapper_cpu import CppWrapperCpu
    from torch._inductor.codegen.cpp_wrapper_cpu_array_ref import CppWrapperCpuArrayRef
    from torch._inductor.codegen.wrapper import EfficientPeakEstimate, ReuseLine
    from torch._inductor.virtualized import V

    class _StackWrapper(CppWrapperCpuArrayRef):
        """Inductor's stack-allocating C++ wrapper, but for the buffers that a graph output is or views: those are
        heap tensors, owned by the caller after the call."""

        @staticmethod
        def create(is_subgraph, subgraph_name, parent_wrapper, partition_signatures=None):
            return _StackWrapper()

        def __init__(self):
            super().__init__()
            self._on_stack = set()  # buffers that take over a stack array, under a view or not
            self._heap = None  # the outputs and the buffers whose storage an output takes over (memory_plan_reuse)
            self._outputs = None  # the outputs' buffers and those they view, once the graph's outputs are known

        def _output_buffers(self) -> set:
            if self._outputs is None:
                names = set(V.graph.get_output_names())
                for node in V.graph.graph_outputs:
                    unwrap = getattr(node, "unwrap_view", None)
                    try:
                        names.add((unwrap() if unwrap is not None else node).get_name())
                    except (AttributeError, NotImplementedError):
                        pass
                self._outputs = names
            return self._outputs

        def memory_plan_reuse(self):
            super().memory_plan_reuse()
            # an output may take over the storage of a buffer that died before it (a reuse, or a kernel writing it in
            # place of its input), through a chain of such reuses: the chain's first buffer stays on the heap
            taken_from = {line.reused_as.get_name(): line.node.get_name() for line in self.lines
                          if isinstance(line, ReuseLine)}
            heap = set(self._output_buffers())
            for name in list(heap):
                while name in taken_from:
                    name = taken_from[name]
                    heap.add(name)
            self._heap = heap

        def can_stack_allocate_buffer(self, buffer) -> bool:
            heap = self._output_buffers() if self._heap is None else self._heap
            return super().can_stack_allocate_buffer(buffer) and buffer.get_name() not in heap

        def make_buffer_reuse(self, old, new, delete_old: bool):
            if old.get_name() in self.stack_allocated_buffers or old.get_name() in self._on_stack:
                self._on_stack.add(new.get_name())
            return super().make_buffer_reuse(old, new, delete_old)

        def memory_plan(self):
            # asked for a planned pool (memory_planning): the stack instead where no library call gave it up,
            # Inductor's pool where one did
            if self.allow_stack_allocation:
                if config.allow_buffer_reuse:  # as Inductor's wrapper sets up its unplanned reuse
                    self.estimate_peak = EfficientPeakEstimate()
                return self.memory_plan_reuse()
            return super().memory_plan()

        def generate_return(self, output_refs):
            stacked = sorted(name for name in self._output_buffers()
                             if name in self.stack_allocated_buffers or name in self._on_stack)
            if stacked:  # it would alias a thread-local buffer that the next call overwrites
                raise RuntimeError(f"torchtraj: a compiled kernel's outputs {stacked} are on the stack")
            return super().generate_return(output_refs)

    class _Chooser(CppWrapperCpu):
        """Inductor's C++ wrapper for the CPU, or :class:`_StackWrapper` for a graph compiled with :data:`OPTION`."""

        @staticmethod
        def create(is_subgraph, subgraph_name, parent_wrapper, partition_signatures=None):
            if config.aot_inductor.allow_stack_allocation and not is_subgraph:
                return _StackWrapper()
            return CppWrapperCpu.create(is_subgraph, subgraph_name, parent_wrapper, partition_signatures)

    return _Chooser
