"""Checks shared by the tests of batch work that must not change an answer (gathered rows, compaction) and of
compiled kernels, whose answers must be the eager ones to rounding."""

import dataclasses
import shutil

import pytest
import torch

import torchtraj as tt

#: the fields of a Solution and of its history that such a test compares
SOLUTION_FIELDS = ("X", "U", "K", "cost", "max_violation", "status", "iterations", "costate")
HISTORY_FIELDS = ("cost", "max_violation", "step_size", "regularization")


def assert_same_solutions(got, want):
    """Every field of the two solutions, their multipliers and their histories, bit for bit (NaN where NaN)."""
    def same(a, b, name):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=name)

    for name in SOLUTION_FIELDS:
        same(getattr(got, name), getattr(want, name), name)
    assert set(got.multipliers) == set(want.multipliers)
    for name in want.multipliers:
        same(got.multipliers[name], want.multipliers[name], name)
    for name in HISTORY_FIELDS:
        same(getattr(got.history, name), getattr(want.history, name), f"history.{name}")
    assert set(got.history.extra) == set(want.history.extra)
    for name in want.history.extra:
        same(got.history.extra[name], want.history.extra[name], f"history.{name}")


def assert_close_solutions(got, want, tol: float, costate_rtol: float = 0.0):
    """The same status and iterations, states, controls and costs within ``tol``, costates within ``tol`` plus
    ``costate_rtol`` of their size: a compiled solve against an eager one, whose fused kernels round otherwise."""
    assert torch.equal(got.status, want.status) and torch.equal(got.iterations, want.iterations)
    for name in ("X", "U", "cost"):
        torch.testing.assert_close(getattr(got, name), getattr(want, name), atol=tol, rtol=0, msg=name)
    torch.testing.assert_close(got.costate, want.costate, atol=tol, rtol=costate_rtol, msg="costate")


#: a compiled solve on a CPU needs a C++ compiler (torch.compile's inductor backend)
needs_compiler = pytest.mark.skipif(not any(shutil.which(c) for c in ("g++", "c++", "clang++")),
                                    reason="torch.compile's CPU backend needs a C++ compiler")


def assert_compiled_matches_eager(problem, x0, method: str, options, tol: float, costate_rtol: float = 0.0):
    """``options`` with ``compile=True`` solve ``x0`` as ``options`` do, to ``tol`` (:func:`assert_close_solutions`):
    inductor's fused arithmetic rounds otherwise than the library calls, the iterations stay the same. The eager
    solve must converge on every instance."""
    compiled = tt.solve(problem, x0, method, options=dataclasses.replace(options, compile=True))
    eager = tt.solve(problem, x0, method, options=options)
    assert bool((eager.status == tt.Status.CONVERGED).all())
    assert_close_solutions(compiled, eager, tol, costate_rtol)


def assert_one_graph_per_kernel(capture, kernels: set) -> None:
    """What a solve with compiled kernels captured (``capture``, the ``dynamo_capture`` fixture): no graph break,
    exactly the kernel functions ``kernels`` compiled, and one graph for each frame Dynamo compiled (each kernel at
    least once)."""
    from torchtraj.core import compiled

    assert not dict(capture["graph_break"]), dict(capture["graph_break"])
    assert set(compiled._KERNELS) == kernels, set(compiled._KERNELS)
    frames, graphs = capture["frames"]["total"], capture["stats"]["unique_graphs"]
    assert frames == graphs >= len(kernels), (frames, graphs)


def assert_compiled_steps_apply_eager_controls(problem, x0, method: str, steps: int = 2) -> None:
    """``steps`` control steps of ``tt.MPC(problem, method, 2, compile=True)`` from the states ``x0`` (moved a little
    after each) apply the eager controller's controls to 1e-9, each spending its budget (``MAX_ITERATIONS``)."""
    import torch

    controllers = tt.MPC(problem, method, 2, compile=True), tt.MPC(problem, method, 2)
    x = x0
    for _ in range(steps):
        u, expected = (mpc(x) for mpc in controllers)
        torch.testing.assert_close(u, expected, rtol=0, atol=1e-9)
        assert (controllers[0].status == tt.Status.MAX_ITERATIONS).all()
        x = x + 0.02
