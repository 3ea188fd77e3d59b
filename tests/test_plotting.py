"""torchtraj.plotting: the figures draw each instance's own history and trajectories, coloured by its status."""

import pytest
import torch
from test_figures import explains_itself

import torchtraj as tt

pytest.importorskip("matplotlib")


@pytest.fixture(scope="module")
def solved():
    problem = tt.problems.get("double_integrator")
    # the third instance starts where its state bound cannot be kept: it ends locally infeasible
    x0 = problem.x0 + torch.tensor([[0.0, 0.0], [0.5, 0.0], [-0.5, 0.2]], dtype=problem.dtype)
    return problem, tt.solve(problem, x0, method="ipm")


def test_convergence_draws_each_instance_up_to_its_own_last_iteration(solved):
    from matplotlib.colors import to_rgba

    from torchtraj import plotting

    problem, sol = solved
    converged = (sol.status == tt.Status.CONVERGED).tolist()
    assert converged == [True, True, False]
    fig = plotting.convergence(sol)
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == ["cost", "largest constraint violation", "stationarity residual", "step size"]
    cost_ax, violation_ax = fig.axes[0], fig.axes[1]
    assert violation_ax.get_yscale() == "log" and cost_ax.get_yscale() == "linear"
    rows = len(sol.history)  # the third instance's restoration phase counts iterations that record no row
    assert int(sol.iterations[2]) > rows
    for i, line in enumerate(cost_ax.get_lines()):
        count = min(int(sol.iterations[i]), rows)
        x, y = line.get_data()
        assert list(x) == list(range(1, count + 1))
        assert torch.equal(torch.as_tensor(y), sol.history.cost[i, :count])
        colour = plotting.CONVERGED_COLOUR if converged[i] else plotting.FAILED_COLOUR
        assert to_rgba(line.get_color(), 0.5) == to_rgba(colour, 0.5)
    assert len(cost_ax.get_lines()) == 3
    _, violation = violation_ax.get_lines()[2].get_data()
    assert violation.min() >= plotting.LOG_FLOOR
    assert "2 of 3 instance(s) converged" in fig._suptitle.get_text()
    assert explains_itself(fig) == []  # the examples' standard: titles, labels with units, legends
    legend = [text.get_text() for text in cost_ax.get_legend().get_texts()]
    assert legend == ["converged", "not converged"]


def test_trajectories_draw_states_controls_and_bounds(solved):
    from torchtraj import plotting

    problem, sol = solved
    fig = plotting.trajectories(sol, problem)
    nx, nu = sol.X.shape[-1], sol.U.shape[-1]
    shown = [ax for ax in fig.axes if ax.axison]
    assert [ax.get_title() for ax in shown] == ([f"state x[{j}]" for j in range(nx)]
                                                + [f"control u[{j}]" for j in range(nu)])
    assert explains_itself(fig) == []
    x0_ax, u0_ax = shown[0], shown[nx]
    times = torch.arange(problem.horizon + 1, dtype=torch.float64) * problem.dt
    drawn = [line for line in x0_ax.get_lines() if len(line.get_xdata()) > 2]
    for i, line in enumerate(drawn):
        assert torch.allclose(torch.as_tensor(line.get_xdata()), times)
        assert torch.equal(torch.as_tensor(line.get_ydata()), sol.X[i, :, 0])
    assert len(drawn) == 3
    bounds = {line.get_ydata()[0] for line in u0_ax.get_lines() if len(line.get_xdata()) == 2}
    expected = {float(b[0]) for b in (problem.u_lower, problem.u_upper) if b is not None}
    assert bounds == expected and u0_ax.get_xlabel() == "time t [s]"
    assert "bound" in [text.get_text() for text in u0_ax.get_legend().get_texts()]
    assert plotting.trajectories(sol).axes[0].get_xlabel() == "knot k [index]"


def test_without_matplotlib_the_error_says_what_to_install(solved, monkeypatch):
    import sys

    from torchtraj import plotting

    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # an import of it raises ImportError
    with pytest.raises(ImportError, match=r'pip install "torchtraj\[plot\]"'):
        plotting.convergence(solved[1])
