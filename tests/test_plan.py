"""``python -m torchtraj.plan``: the written solutions are :func:`torchtraj.solve`'s for the same initial states, and a
run killed after some of its chunks resumes to exactly the uninterrupted result (every instance once, in order).

The kill is the command's test hook (``_TORCHTRAJ_PLAN_EXIT_AFTER_CHUNKS``: ``os._exit`` right after the k-th chunk
file, as a SIGKILL there would leave it). The quick runs use ALTRO with three outer iterations on the double
integrator; the two-process run under ``torchrun`` is the slow one.
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

import torchtraj as tt
from torchtraj import plan

ROOT = Path(__file__).resolve().parent.parent
COUNT, CHUNK = 10, 3  # four chunks, the last one short
ARGS = ["--problem", "double_integrator", "--count", str(COUNT), "--method", "altro", "--iterations", "3",
        "--chunk-size", str(CHUNK), "--no-progress"]
FIELDS = ("x0", "X", "U", "K", "cost", "max_violation", "status", "iterations", "costate")


def _command(out: Path, exit_after: int = 0, launcher=(sys.executable, "-m")) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    if exit_after:
        env[plan.EXIT_AFTER_ENV] = str(exit_after)
    return subprocess.run([*launcher, "torchtraj.plan", *ARGS, "--out", str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)


def _load(path: Path) -> dict:
    return torch.load(path, weights_only=True)


def assert_same_output(a: dict, b: dict) -> None:
    for k in FIELDS:
        assert torch.equal(a[k], b[k]), k
    for group in plan.GROUPS:
        assert a[group].keys() == b[group].keys()
        assert all(torch.equal(a[group][k], b[group][k]) for k in a[group]), group


def _reference() -> tt.Solution:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return tt.solve(tt.problems.get("double_integrator"), tt.problems.sample_x0("double_integrator", COUNT, 0),
                        "altro", options=tt.problems.altro_options("double_integrator", iterations_outer=3))


def test_a_killed_run_resumes_to_the_uninterrupted_result(tmp_path, monkeypatch):
    out = tmp_path / "plans.pt"
    killed = _command(out, exit_after=2)
    assert killed.returncode == 17, killed.stderr
    parts = Path(f"{out}.parts")
    assert not out.exists()
    assert sorted(p.name for p in parts.glob("chunk-*.pt")) == [
        "chunk-000000000-000000003.pt", "chunk-000000003-000000006.pt"]
    assert not list(parts.glob(".*.tmp"))  # written whole or not at all

    solved = []
    original = plan.solve_chunk
    monkeypatch.setattr(plan, "solve_chunk",
                        lambda problem, x0, *a: solved.append(len(x0)) or original(problem, x0, *a))
    assert plan.main([*ARGS, "--out", str(out)]) == 0
    assert solved == [3, 1]  # only the two chunks the killed run had not written
    assert not parts.exists()
    resumed = _load(out)

    solved.clear()
    assert plan.main([*ARGS, "--out", str(tmp_path / "whole.pt")]) == 0
    assert solved == [3, 3, 3, 1]
    assert_same_output(resumed, _load(tmp_path / "whole.pt"))

    # the instances in order, each once, and what one tt.solve of the whole batch gives
    assert torch.equal(resumed["x0"], tt.problems.sample_x0("double_integrator", COUNT, seed=0))
    want = _reference()
    for k in FIELDS[1:]:
        assert torch.equal(resumed[k], getattr(want, k)), k
    for group in plan.GROUPS:
        assert resumed[group].keys() == getattr(want, group).keys()
        assert all(torch.equal(resumed[group][k], v) for k, v in getattr(want, group).items()), group
    summary = resumed["summary"]
    assert summary["count"] == COUNT
    assert summary["converged_fraction"] == pytest.approx(float(want.converged.double().mean()))
    assert summary["cost_quantiles"][0.5] == pytest.approx(float(want.cost.median()), rel=0.2)

    solved.clear()
    assert plan.main([*ARGS, "--out", str(out)]) == 0 and solved == []  # complete: nothing to do


@pytest.mark.filterwarnings("ignore:method .ilqr. ignores the constraints")
def test_initial_states_from_a_file_and_settings_that_do_not_match(tmp_path):
    x0 = tt.problems.sample_x0("double_integrator", 2, seed=5).flip(0)
    torch.save(x0, tmp_path / "x0.pt")
    args = ["--problem", "double_integrator", "--count", "2", "--method", "ilqr", "--no-progress",
            "--x0", str(tmp_path / "x0.pt"), "--out", str(tmp_path / "a.pt")]
    assert plan.main(args) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = tt.solve(tt.problems.get("double_integrator"), x0, "ilqr")
    got = _load(tmp_path / "a.pt")
    assert torch.equal(got["x0"], x0) and torch.equal(got["U"], want.U) and torch.equal(got["status"], want.status)
    torch.save(x0.flip(0), tmp_path / "other.pt")
    other = [str(tmp_path / "other.pt") if a == str(tmp_path / "x0.pt") else a for a in args]
    with pytest.raises(ValueError, match="another command"):  # the same --out, other initial states
        plan.main(other)
    with pytest.raises(ValueError, match="shape"):
        plan.main([*args[:3], "3", *args[4:]])

@pytest.mark.slow
def test_two_processes_under_torchrun_killed_and_resumed(tmp_path):
    torchrun = (str(Path(sys.executable).with_name("torchrun")), "--nproc-per-node", "2", "-m")
    out = tmp_path / "plans.pt"
    killed = _command(out, exit_after=2, launcher=torchrun)
    assert killed.returncode != 0 and not out.exists()
    assert len(list(Path(f"{out}.parts").glob("chunk-*.pt"))) == 2
    resumed = _command(out, launcher=torchrun)
    assert resumed.returncode == 0, resumed.stderr
    assert plan.main([*ARGS, "--out", str(tmp_path / "whole.pt")]) == 0
    assert_same_output(_load(out), _load(tmp_path / "whole.pt"))
