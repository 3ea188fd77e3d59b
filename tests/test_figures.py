"""Every example's figure renders on a tiny run (``--quick``) and explains itself: a title on every panel, labelled
axes, a legend, and a file written. The examples build a ``matplotlib.figure.Figure`` (no pyplot, no global
backend), so the Agg canvas renders them whatever the machine's display.

The runs behind the figures take seconds to minutes of solver time on a shared CPU; the fastest stay in the default
run, the rest are ``slow``.
"""

import importlib.util
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")  # in the test extra; absent only from a bare install

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

#: example -> (the option naming its picture, marks); ordered by the time of their quick runs.
CASES = {
    "swing_up": ("--output", ()),
    "mpc_pendulum": ("--output", (pytest.mark.slow,)),
    "mpc_cartpole": ("--output", (pytest.mark.slow,)),
    "mpc_car": ("--output", (pytest.mark.slow,)),
    "gym_pendulum_v1": ("--output", (pytest.mark.slow,)),
    "car_escape": ("--output", (pytest.mark.slow,)),
    "learn_dynamics": ("--plot", (pytest.mark.slow,)),
    "learn_cost": ("--plot", (pytest.mark.slow,)),
}


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _shares_y(ax, other) -> bool:
    return ax is not other and ax.get_shared_y_axes().joined(ax, other)


def explains_itself(fig) -> list:
    """What a reader would miss in ``fig``: panels without a title, an axis label or a legend (a panel that
    shares its y axis with a labelled neighbour may leave the label, and the legend, to it)."""
    missing = []
    title = fig._suptitle.get_text() if fig._suptitle is not None else ""
    for i, ax in enumerate(fig.axes):
        neighbours = [o for o in fig.axes if _shares_y(ax, o)]
        if not (ax.get_title() or title):
            missing.append(f"panel {i}: no title")
        if not ax.get_xlabel():
            missing.append(f"panel {i}: no x label")
        if not ax.get_ylabel() and not any(o.get_ylabel() for o in neighbours):
            missing.append(f"panel {i}: no y label")
        if ax.get_legend() is None and not any(o.get_legend() is not None for o in neighbours):
            missing.append(f"panel {i}: no legend")
        for label in (ax.get_xlabel(), ax.get_ylabel()):
            if label and "[" not in label:
                missing.append(f"panel {i}: no unit in {label!r}")
    return missing


@pytest.mark.parametrize("name", [pytest.param(n, marks=m) for n, (_, m) in CASES.items()])
def test_example_figure_renders_and_explains_itself(name, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHTRAJ_PROGRESS", "0")
    path = tmp_path / f"{name}.png"
    result = _load(name).main(["--quick", CASES[name][0], str(path)])
    fig = result["figure"] if isinstance(result, dict) else result
    assert fig is not None and path.stat().st_size > 10_000
    assert explains_itself(fig) == []


def test_the_check_finds_what_is_missing():
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("time")
    assert explains_itself(fig) == ["panel 0: no title", "panel 0: no y label", "panel 0: no legend",
                                    "panel 0: no unit in 'time'"]
