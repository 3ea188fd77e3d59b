"""A single instance's compiled kernels keep their intermediate buffers on the stack (torchtraj.core.stack_buffers),
return outputs of their own that the next call does not overwrite, and leave every other compilation as it was."""

import re
import shutil

import pytest
import torch

import torchtraj as tt
from torchtraj.core import compiled, stack_buffers

pytest.importorskip("torch._inductor")
pytestmark = pytest.mark.skipif(not any(shutil.which(c) for c in ("g++", "c++", "clang++")),
                                reason="torch.compile's CPU backend needs a C++ compiler")


def stages(P, A):
    """A short recursion with a stacked output, a view of an intermediate and a final state."""
    outs = []
    for _ in range(6):
        P = (A.unsqueeze(-1) * P.unsqueeze(-3)).sum(-2) + 0.125
        outs.append(2.0 * P)
    return P, torch.stack(outs, 1), outs[2].transpose(-1, -2)


def _code(fn, *args):
    from torch._inductor.utils import run_and_get_code
    out, sources = run_and_get_code(fn, *args)
    return out, "\n".join(sources)


@pytest.fixture
def fresh_kernels(monkeypatch):
    monkeypatch.setattr(compiled, "_KERNELS", {})
    torch._dynamo.reset()
    yield
    torch._dynamo.reset()


def test_a_single_instance_kernel_has_stack_buffers_and_outputs_of_its_own(fresh_kernels):
    if not stack_buffers.install():
        pytest.skip("this torch's Inductor has no stack-allocating C++ wrapper")
    kernel = compiled.kernel(stages, True)
    A = torch.tensor([[[1.0, 0.05], [0.0, 1.0]]], dtype=torch.float64)
    P = torch.eye(2, dtype=torch.float64).unsqueeze(0)
    with torch.inference_mode(), compiled.batch_of(1):
        first, code = _code(kernel, P, A)
        kept = [t.clone() for t in first]
        second = kernel(3.0 * P, A)
    assert "ArrayRefTensor<double>" in code  # intermediate buffers on the stack
    for before, now in zip(kept, first):  # the second call wrote nothing into the first's outputs
        assert torch.equal(before, now)
    for out, expected in zip(first, stages(P, A)):
        assert torch.equal(out, expected)
    for out, expected in zip(second, stages(3.0 * P, A)):
        assert torch.equal(out, expected)
    assert first[0].data_ptr() != second[0].data_ptr()


def test_batched_kernels_and_other_compilations_keep_heap_buffers(fresh_kernels):
    stack_buffers.install()
    A = torch.tensor([[1.0, 0.05], [0.0, 1.0]], dtype=torch.float64).expand(3, 2, 2)
    P = torch.eye(2, dtype=torch.float64).expand(3, 2, 2)
    with torch.inference_mode():
        with compiled.batch_of(3):
            out, batched = _code(compiled.kernel(stages, True), P, A)
        other, plain = _code(torch.compile(stages, options={"cpp_wrapper": True}), P, A)
    assert "ArrayRefTensor" not in batched and "ArrayRefTensor" not in plain
    for a, b, expected in zip(out, other, stages(P, A)):
        assert torch.equal(a, expected) and torch.equal(b, expected)


def _terminal_terms(T, M):
    from torchtraj.riccati import range_space
    return range_space._suffix_sums(T), range_space._pseudo_inverse(M, 1e-10)


def test_the_range_space_terms_of_a_single_instance_call_no_library_kernel(fresh_kernels):
    """In a single instance's kernel the range-space method's reversed cumulative sum is stage-by-stage additions
    (the same order as ``cumsum``'s, the same bits) and its pseudo-inverse Jacobi rotations (LAPACK's to rounding), so
    that the kernel keeps its buffers on the stack; a batched kernel keeps the library calls."""
    if not stack_buffers.install():
        pytest.skip("this torch's Inductor has no stack-allocating C++ wrapper")
    g = torch.Generator().manual_seed(0)
    T = torch.randn(1, 7, 2, 2, generator=g, dtype=torch.float64)
    R = torch.randn(1, 3, 3, generator=g, dtype=torch.float64)
    M = R @ R.mT
    kernel = compiled.kernel(_terminal_terms, True)
    with torch.inference_mode():
        with compiled.batch_of(1):
            (sums, (inverse, finite)), code = _code(kernel, T, M)
        with compiled.batch_of(2):
            _, batched = _code(kernel, T.expand(2, -1, -1, -1).clone(), M.expand(2, -1, -1).clone())
    assert "ArrayRefTensor<double>" in code and "aoti_torch_cpu_cumsum" not in code and "eigh" not in code
    assert "ArrayRefTensor" not in batched and "cumsum" in batched
    expected_sums, (expected_inverse, _) = _terminal_terms(T, M)
    assert torch.equal(sums, expected_sums)
    torch.testing.assert_close(inverse, expected_inverse, rtol=1e-12, atol=1e-12)
    assert bool(finite.all())


def test_without_the_chooser_single_instance_graphs_ask_for_no_stack(monkeypatch):
    """Where the chooser could not be installed (another torch's Inductor, or a process that registered Inductor's
    stack wrapper itself, which would return outputs it overwrites), a single instance's options leave the stack
    out."""
    seen = []

    def recorded(fn, dynamic, options):
        seen.append(options)
        return fn

    monkeypatch.setattr(torch, "compile", recorded)
    monkeypatch.setattr(stack_buffers, "install", lambda: False)
    compiled._compile(stages)
    assert stack_buffers.OPTION not in seen[1] and seen[1]["memory_planning"]
    monkeypatch.setattr(stack_buffers, "install", lambda: True)
    compiled._compile(stages)
    assert seen[3][stack_buffers.OPTION]


def _outputs_on_the_stack(code: str) -> list:
    """The outputs of the generated wrappers in ``code`` whose C++ variable is, or comes by reuses and views from, a
    stack array: Inductor returns those over a thread-local buffer that its next call overwrites."""
    found = []
    for wrapper in code.split("inductor_entry_impl(")[1:]:
        stack = set(re.findall(r"ArrayRefTensor<\w+> (buf\d+)\(", wrapper))
        source = dict(re.findall(r"auto (buf\d+) = std::move\((buf\d+)\)", wrapper))
        views = r"auto (buf\d+) = wrap_with_raii_handle_if_needed\(reinterpret_tensor_wrapper\((buf\d+),"
        source.update(re.findall(views, wrapper))
        for name in set(re.findall(r"ThreadLocalCachedOutputTensor<std::decay_t<decltype\((buf\d+)\)>>", wrapper)):
            root = name
            while root in source and root not in stack:
                root = source[root]
            if root in stack:
                found.append(name)
    return found


@pytest.mark.slow  # compiling eILQR's and the interior point's single-instance kernels: minutes on two cores
@pytest.mark.parametrize("method", ["eilqr", "ipm"])
def test_compiled_single_instance_solves_repeat_and_match_eager(method, fresh_kernels):
    """A compiled solve of one instance, twice: its kernels return no output over a stack array (their wrappers'
    code), the second solve is the first to the last bit (an output overwritten by the next call of its kernel would
    change the later iterations), and both are the eager solve's to rounding."""
    from torch._inductor.utils import run_and_get_code

    problem = tt.problems.get("pendulum")
    options = {"eilqr": tt.EILQROptions, "ipm": tt.IPOptions}[method](compile=True)
    first, sources = run_and_get_code(lambda: tt.solve(problem, method=method, options=options))
    assert "ArrayRefTensor<double>" in "\n".join(sources)
    assert _outputs_on_the_stack("\n".join(sources)) == []
    second = tt.solve(problem, method=method, options=options)
    assert torch.equal(first.U, second.U) and torch.equal(first.iterations, second.iterations)
    eager = tt.solve(problem, method=method)
    assert torch.equal(first.status, eager.status) and torch.equal(first.iterations, eager.iterations)
    torch.testing.assert_close(first.U, eager.U, atol=1e-9, rtol=0)
