"""Shared fixtures: reference optima copied from the problem set's IPOPT / FATROP runs (tests/data)."""

import json
from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: takes more than a few seconds; select with -m slow")


@pytest.fixture(scope="session")
def reference() -> dict:
    """``reference[problem][solver]`` with ``cost``, ``iterations``, ``max_violation`` (and ``X``, ``U``
    for IPOPT), plus ``reference["pendulum_batch_seed0_ipopt"]`` (costs, iterations of 64 instances)."""
    with open(DATA / "reference.json") as f:
        return json.load(f)
