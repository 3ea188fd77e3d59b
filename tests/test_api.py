"""What a newcomer meets first: ``dir(tt)``, the reprs of a problem and a solution, ``help(tt.MPC)``, a summary of
a differentiable solve, the benchmark's ``--help``, the package description, and the progress bar."""

import io
import pydoc
import sys
import tomllib
import warnings
from pathlib import Path

import pytest
import torch

import torchtraj as tt
from torchtraj import solvers
from torchtraj.core.progress import Progress
from torchtraj.core.solution import History, Solution

ROOT = Path(__file__).resolve().parent.parent


def test_dir_lists_the_public_names_and_the_lazy_modules():
    names = dir(tt)
    assert {"problems", "models", "envs", "solve", "Problem", "MPC", "Solution", "Status"} <= set(names)
    assert set(tt.__all__) <= set(names)


def _solution(cost: torch.Tensor) -> Solution:
    B, N = cost.shape[0], 4
    status = torch.tensor([0, 1, 0][:B])
    return Solution(X=torch.zeros(B, N + 1, 2), U=torch.zeros(B, N, 1), K=torch.zeros(B, N, 1, 2), cost=cost,
                    max_violation=torch.tensor([1e-9, 2e-3, 0.0][:B]), status=status,
                    iterations=torch.tensor([3, 50, 4][:B]), history=History.from_rows([]), method="altro")


def test_problem_repr_is_a_summary_not_the_tensors():
    text = repr(tt.problems.get("car_3obs"))
    assert text == ("Problem('car_3obs', nx=3, nu=2, N=100, dt=0.05, float64, constraints=[u bounds, state_ineq, "
                    "terminal_eq], params={goal: (3,), Q: (3, 3), R: (2, 2), Qf: (3, 3), obstacles: (3, 3)})")


def test_solution_repr_counts_statuses_and_gives_ranges():
    text = repr(_solution(torch.tensor([1.5, 2.0, 3.25])))
    assert text == "Solution('altro', B=3, converged: 2, max_iterations: 1, cost 1.5..3.25, max violation 0.002)"


def test_summary_of_a_differentiable_cost_does_not_warn():
    cost = torch.tensor([1.5, 2.0], requires_grad=True) * 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        text = _solution(cost).summary()
    assert "cost 1.5..2" in text and "converged: 1, max_iterations: 1" in text


def test_help_of_mpc_leads_with_its_own_docstring():
    text = pydoc.render_doc(tt.MPC, renderer=pydoc.plaintext)
    first_line = tt.MPC.__doc__.strip().splitlines()[0]
    assert first_line in text
    assert text.index(first_line) < text.index("Method resolution order")


def _bench_parsers():
    from torchtraj.bench import __main__ as bench_main
    from torchtraj.bench import mpc

    return [bench_main.parser(), mpc.parser()]


@pytest.mark.parametrize("which", [0, 1])
def test_bench_help_states_every_default_once_and_every_option_has_help(which):
    parser = _bench_parsers()[which]
    for action in parser._actions:
        assert action.help, f"{action.option_strings} has no help text"
    lines = parser.format_help().replace("\n", " ")
    assert "(default: None)" not in lines and "(default: False)" not in lines
    for action in parser._actions:
        text = action.help or ""
        assert text.count("(default:") + text.count("; default:") <= 1, action.option_strings


def test_package_description_names_the_built_methods_only():
    description = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["description"]
    spelled = {"ilqr": "iLQR", "altro": "ALTRO", "ipm": "interior point", "hm-ilqr": "HM-iLQR", "eilqr": "eILQR"}
    assert set(spelled) <= set(solvers.names())
    assert all(word in description for word in spelled.values()) and "planned" not in description


# ---------------------------------------------------------------------------------------------- progress
class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_in_a_log_prints_a_line_per_tenth_and_the_end(monkeypatch):
    monkeypatch.delenv("TORCHTRAJ_PROGRESS", raising=False)
    out = io.StringIO()
    with Progress(20, "solve", stream=out) as bar:
        for k in range(20):
            bar.update(converged=torch.tensor([True, k >= 10]), violation=torch.tensor([1e-3, 2e-6]))
    lines = out.getvalue().splitlines()
    assert len(lines) == 11 and "\r" not in out.getvalue()  # tenths 0.05 .. 0.95, then the final line
    assert lines[-1].startswith("solve  [####################]  20/20 steps  converged 100%  violation 1.0e-03")
    assert "converged 50%" in lines[0]


def test_progress_on_a_terminal_redraws_in_place_and_write_clears_it(monkeypatch):
    monkeypatch.delenv("TORCHTRAJ_PROGRESS", raising=False)
    out = _Terminal()
    bar = Progress(4, "bench", unit="rows", stream=out, min_interval=0.0)
    bar.update(loss=0.5)
    bar.write("a table row")
    bar.update()
    bar.close()
    text = out.getvalue()
    assert text.startswith("\r\033[Kbench  [#####") and "loss 0.5" in text
    assert "\r\033[Ka table row\n" in text and text.endswith("\n")


def test_progress_off_draws_and_reads_nothing(monkeypatch):
    monkeypatch.delenv("TORCHTRAJ_PROGRESS", raising=False)
    out = io.StringIO()
    unreadable = torch.empty(3, device="meta")  # reading its value raises: the bar must not try
    bar = Progress(3, stream=out, enabled=False)
    bar.update(converged=unreadable, violation=unreadable)
    bar.close()
    assert out.getvalue() == ""
    monkeypatch.setenv("TORCHTRAJ_PROGRESS", "0")
    forced_off = Progress(3, stream=out)
    forced_off.update()
    forced_off.close()
    assert out.getvalue() == "" and sys.stderr is not out
