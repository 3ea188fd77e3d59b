"""Shared fixtures: reference optima copied from the problem set's IPOPT / FATROP runs (tests/data)."""

import json
import os
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: takes more than a few seconds; select with -m slow")
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # one of several worker processes (addopts' `-n 2`): one thread each, not two per worker on two cores
        import torch

        torch.set_num_threads(1)


@pytest.fixture(scope="session")
def reference() -> dict:
    """``reference[problem][solver]`` with ``cost``, ``iterations``, ``max_violation`` (and ``X``, ``U``
    for IPOPT), plus ``reference["pendulum_batch_seed0_ipopt"]`` (costs, iterations of 64 instances)."""
    with open(DATA / "reference.json") as f:
        return json.load(f)


@pytest.fixture
def dynamo_capture(monkeypatch):
    """``torch.compile`` as Dynamo's capture alone (its ``"eager"`` backend: the graphs run as captured, in seconds,
    no inductor; the kernels' guard filter kept), with no compiled kernel or graph left from an earlier test. Yields
    Dynamo's counters, cleared."""
    import torch
    from torch._dynamo.utils import counters

    from torchtraj.core import compiled

    original = torch.compile

    def captured(fn, **kwargs):  # the kernels' guard filter kept (compiled.kept_guards)
        options = kwargs.get("options") or {}
        kept = {"guard_filter_fn": options["guard_filter_fn"]} if "guard_filter_fn" in options else None
        return original(fn, backend="eager", dynamic=kwargs.get("dynamic", False), options=kept)

    monkeypatch.setattr(torch, "compile", captured)
    monkeypatch.setattr(compiled, "_KERNELS", {})
    torch._dynamo.reset()
    counters.clear()
    yield counters
    torch._dynamo.reset()
