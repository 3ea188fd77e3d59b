"""Run a function on several local processes joined in a Gloo process group, without ever hanging.

``run(fn, world, *args)`` spawns ``world`` processes (``torch.multiprocessing``, spawn start method) that each call
``fn(rank, world, *args)`` inside ``init_process_group("gloo", tcp://127.0.0.1:<free port>)`` with a short
collective timeout; the parent waits at most ``timeout`` seconds, then kills them and fails.
"""

from __future__ import annotations

import datetime
import os
import socket
import time

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

#: The process group's collective timeout: a rank that never arrives fails the others within it.
COLLECTIVE_TIMEOUT_S = 60


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _entry(rank: int, world: int, port: int, fn, args) -> None:
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=world,
                            timeout=datetime.timedelta(seconds=COLLECTIVE_TIMEOUT_S))
    try:
        fn(rank, world, *args)
        # every rank past its last collective before any tears its Gloo context down: a rank that destroyed its
        # group while the other was still in one once aborted it (SIGABRT, "terminate called without an active
        # exception") in a full test run
        dist.barrier()
    finally:
        dist.destroy_process_group()


def run(fn, world: int, *args, timeout: float = 300) -> None:
    """``fn(rank, world, *args)`` on ``world`` processes; raises if one fails or the whole takes over ``timeout``."""
    context = mp.start_processes(_entry, args=(world, free_port(), fn, args), nprocs=world, join=False,
                                 start_method="spawn")
    deadline = time.monotonic() + timeout
    while not context.join(timeout=1.0):
        if time.monotonic() > deadline:
            for p in context.processes:
                if p.is_alive():
                    p.kill()
            raise TimeoutError(f"the {world} ranks did not finish within {timeout} s")
