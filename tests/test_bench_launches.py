"""``python -m torchtraj.bench --launches`` and ``--cuda-graphs`` on the timing rows: the profiler's events are
tallied by kind, the flags are refused where they count or change nothing, and on a GPU the count is of a real solve."""

import io
from types import SimpleNamespace

import pytest
import torch

from torchtraj import problems
from torchtraj.bench import launches
from torchtraj.bench.__main__ import main
from torchtraj.core import graphs

CPU, CUDA = torch.autograd.DeviceType.CPU, torch.autograd.DeviceType.CUDA


def event(name, device_type=CPU, count=1):
    return SimpleNamespace(key=name, device_type=device_type, count=count)


def test_events_are_tallied_by_kind_and_count():
    events = [event("cudaLaunchKernel", count=7), event("cuLaunchKernel", count=2), event("cudaGraphLaunch", count=3),
              event("cudaMemcpyAsync", count=4), event("cudaStreamSynchronize", count=5),
              event("void gemv_kernel<double>", CUDA, 40), event("Memcpy DtoH (Device -> Pinned)", CUDA, 4),
              event("Memset (Device)", CUDA), event("aten::add", count=11), event("cudaGetDevice", count=9)]
    counted = launches.tally(events)
    assert (counted.kernel_launches, counted.graph_launches, counted.copy_launches, counted.waits) == (9, 3, 4, 5)
    assert (counted.kernels, counted.copies, counted.host_launches) == (40, 5, 16)
    text = launches.line("pendulum", "ipm", 8, counted, 4)
    assert "4 host launch calls an iteration (kernels 2, graph replays 0.8, copies and fills 1.0)" in text
    assert "10 kernels ran on the GPU an iteration, 1.2 waits" in text


def test_launches_are_counted_on_a_cuda_device_only():
    with pytest.raises(ValueError, match="CUDA device"):
        launches.count(lambda: None, torch.device("cpu"))


@pytest.mark.parametrize("argv", [["--launches"], ["--launches", "--device", "cuda", "--ops"],
                                  ["--method", "eilqr", "--cuda-graphs"], ["--method", "ipm", "--cuda-graphs", "--ops"],
                                  ["--method", "ipm", "--cuda-graphs", "--compile"]])
def test_the_flags_are_refused_where_they_would_count_or_change_nothing(argv, capsys):
    with pytest.raises(SystemExit) as exited:
        main(argv, out=io.StringIO())
    assert exited.value.code == 2
    flag = "--launches" if "--launches" in argv else "--cuda-graphs"
    assert f"{flag} goes with" in capsys.readouterr().err


def test_cuda_graphs_on_the_timing_rows_run_the_ipm_eager_on_a_cpu():
    out = io.StringIO()
    before = graphs.captures()
    code = main(["--method", "ipm", "--problems", "pendulum", "--batch", "2", "--no-reference", "--cuda-graphs",
                 "--iterations", "8", "--warmup-iterations", "2"], out=out)
    text = out.getvalue()
    row = next(line for line in text.splitlines() if line.startswith("pendulum "))
    assert code == 0 and row.split()[1:4] == ["ipm", "2", "2"], text
    assert graphs.captures() == before and "CUDA graphs" not in text


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_solve_on_a_gpu_launches_kernels_every_iteration():
    import torchtraj as tt

    problem = problems.get("pendulum", device="cuda")
    x0 = problems.sample_x0("pendulum", 4, 0)
    solution, counted = launches.count(lambda: tt.solve(problem, x0, "ipm", options=tt.IPOptions(iterations=5)),
                                       problem.device)
    assert counted.kernels >= 5 * 100 and counted.kernel_launches >= counted.kernels // 2
    assert int(solution.iterations.max()) == 5
