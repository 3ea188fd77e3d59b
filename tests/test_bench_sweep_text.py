"""The horizon table's line (torchtraj.bench.ops_text.format_sweep): a horizon without a counted iteration reads
``-``, one whose solve raised ``ERROR``."""

from torchtraj.bench.ops import Count
from torchtraj.bench.ops_text import format_sweep


def test_a_horizon_without_an_iteration_reads_a_dash_and_an_error_reads_error():
    counted = Count("pendulum", "ipm", 25, 5, calls=2431, iterations=1)
    failed = Count("pendulum", "ipm", 100, 5, error="RuntimeError: boom")
    line = format_sweep("ipm", [counted, failed], None, [25, 50, 100])
    assert line.split() == ["ipm", "2431", "-", "ERROR", "-"]
