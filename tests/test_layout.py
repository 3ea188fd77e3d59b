"""The package's layout keeps its architecture: layers import downwards, solvers never import each other, no import
cycle (also none hidden inside a function), and every file reads in one sitting.

The layers, bottom to top: ``core`` (problem, constraints, batching, derivatives, solution, status) → ``riccati``
(the LQR core) → ``kkt`` (the linear-quadratic model and the Newton step with held rows) → ``globalization`` and
``iterations`` (pieces several solvers share) → ``solvers`` (one folder or file each) → ``differentiation`` →
``solve`` (``tt.solve``) → ``control`` (MPC) → ``distributed`` (one batch over a process group); the package's
``__init__`` sits on top, ``bench`` and ``plan`` (command-line tools over the problem set) beside it.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "torchtraj"

#: The layers in order: a module may import from its own layer and those before it, never from a later one.
LAYERS = ("core", "riccati", "kkt", "globalization", "iterations", "solvers", "differentiation", "solve", "control",
          "distributed")

#: The largest file the layout allows, in lines.
MAX_LINES = 400


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def _imports(path: Path) -> set:
    """The torchtraj modules that ``path`` imports anywhere in its body (functions included)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.startswith("torchtraj")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("torchtraj"):
                target = node.module
            else:
                continue
            for alias in node.names:  # `from . import crossover` imports a module, not the package
                child = f"{target}.{alias.name}"
                found.add(child if _is_module(child) else target)
    return found - {name}


def _graph() -> dict:
    return {_module_name(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def _layer(module: str):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def test_the_import_graph_has_no_cycle():
    graph = _graph()
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in graph:
                continue
            if state.get(nxt) == "open":
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node)


def test_layers_import_only_downwards():
    wrong = []
    for module, imported in _graph().items():
        own = _layer(module)
        if own is None:
            continue
        for target in imported:
            other = _layer(target)
            if other is not None and LAYERS.index(other) > LAYERS.index(own):
                wrong.append(f"{module} imports {target}")
            if other is None and target != "torchtraj" and target.split(".")[1] not in ("models", "integrators"):
                wrong.append(f"{module} imports {target}, which sits above the layers")
    assert not wrong, "\n".join(wrong)


def test_no_solver_imports_another_solver():
    wrong = []
    for module, imported in _graph().items():
        parts = module.split(".")
        if len(parts) < 3 or parts[1] != "solvers":
            continue
        for target in imported:
            t = target.split(".")
            if len(t) >= 3 and t[1] == "solvers" and t[2] != parts[2] and t[2] != "base":
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_every_file_reads_in_one_sitting():
    long = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


def test_the_checks_see_a_cycle_and_an_upward_import(tmp_path, monkeypatch):
    """The checks can fail: a fake package with a cycle hidden in a function and a layer importing upwards."""
    pkg = tmp_path / "torchtraj"
    (pkg / "core").mkdir(parents=True)
    (pkg / "solvers").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "core" / "__init__.py").write_text("")
    (pkg / "solvers" / "__init__.py").write_text("")
    (pkg / "core" / "a.py").write_text("def f():\n    from ..solvers import b\n")
    (pkg / "solvers" / "b.py").write_text("from ..core import a\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", pkg)
    with pytest.raises(pytest.fail.Exception, match="import cycle"):
        test_the_import_graph_has_no_cycle()
    with pytest.raises(AssertionError, match="torchtraj.core.a imports torchtraj.solvers.b"):
        test_layers_import_only_downwards()
