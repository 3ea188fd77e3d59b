"""Every code block of the README and of ``docs/`` is run or checked here, so none can rot.

- ``python`` blocks of one page run in order in one namespace, as a reader pastes them one after another (in a
  temporary working directory, matplotlib on its Agg backend). A block preceded by the comment
  ``<!-- docs-test: slow -->`` runs only with ``-m slow``; the default run executes every other block.
- ``bash`` blocks are commands: ``pip install`` lines must name extras that ``pyproject.toml`` declares,
  ``python examples/X.py`` must name an example that exists, and the arguments of ``python -m torchtraj.bench``,
  ``python -m torchtraj.plan`` and ``torchrun ... -m torchtraj.plan`` must parse with the command's own parser
  (running them is the benchmark's and CI's business). Any other command fails the test, so a new kind of
  command is taught here before it is documented.
- ``text`` blocks are printed output and are not run.
- Links to files resolve inside the repository, and no page points outside it.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SLOW_MARK = "<!-- docs-test: slow -->"
FENCE = re.compile(r"^```(\w*)\s*$")


def code_blocks(page: Path) -> list:
    """``(language, code, first line number, slow)`` for every fenced block of ``page``."""
    lines = page.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        opening = FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        previous = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        blocks.append((opening.group(1) or "text", "\n".join(lines[i + 1:end]), i + 2, previous == SLOW_MARK))
        i = end + 1
    return blocks


def _page_id(page: Path) -> str:
    return str(page.relative_to(ROOT))


def _run_python_blocks(page: Path, tmp_path, monkeypatch, include_slow: bool) -> int:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    namespace = {"__name__": "__docs__"}
    ran = 0
    for language, code, line, slow in code_blocks(page):
        if language != "python" or (slow and not include_slow):
            continue
        exec(compile(code, f"{_page_id(page)}:{line}", "exec"), namespace)
        ran += 1
    return ran


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_python_blocks_run(page, tmp_path, monkeypatch):
    _run_python_blocks(page, tmp_path, monkeypatch, include_slow=False)


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_python_blocks_run_including_the_slow_ones(page, tmp_path, monkeypatch):
    _run_python_blocks(page, tmp_path, monkeypatch, include_slow=True)


def _extras() -> set:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return set(tomllib.load(f)["project"]["optional-dependencies"])


def _check_command(words: list) -> None:
    """Raise ``AssertionError`` unless the command is one the docs may show and its arguments are valid."""
    if words[:2] == ["pip", "install"] or words[:4] == ["python", "-m", "pip", "install"]:
        for word in words:
            extras = re.fullmatch(r"""["']?(?:-e\s*)?\.\[([\w,-]+)\]["']?""", word)
            if extras:
                missing = set(extras.group(1).split(",")) - _extras()
                assert not missing, f"pyproject.toml declares no extra {missing}"
        return
    if words[:2] == ["python", "-m"] and words[2] in ("venv", "pytest"):
        return
    if words[0] in ("source", "cd", "git", "export"):
        return
    if words[0] == "python" and words[1].startswith("examples/"):
        assert (ROOT / words[1]).is_file(), f"no example {words[1]}"
        return
    if words[0] == "torchrun":
        module = words.index("-m")
        words = ["python", *words[module:]]
    if words[:3] == ["python", "-m", "torchtraj.bench"]:
        from torchtraj.bench import mpc
        from torchtraj.bench.__main__ import parser

        arguments = words[3:]
        if "--mpc" in arguments:  # the MPC runs have a parser of their own
            mpc.parser().parse_args([a for a in arguments if a != "--mpc"])
        elif "--scale-out" in arguments:  # so do the scale-out runs
            from torchtraj.bench import scale_out

            scale_out.parser().parse_args([a for a in arguments if a != "--scale-out"])
        else:
            parser().parse_args(arguments)
        return
    if words[:3] == ["python", "-m", "torchtraj.plan"]:
        from torchtraj.plan import parser

        parser().parse_args(words[3:])
        return
    raise AssertionError(f"the docs test does not know the command {' '.join(words)!r}")


def _commands(code: str) -> list:
    """The commands of a shell block: continuation lines joined, ``&&`` chains split, comments dropped."""
    text = code.replace("\\\n", " ")
    commands = []
    for line in text.splitlines():
        line = line.split(" #")[0].strip()
        if not line or line.startswith("#"):
            continue
        for part in line.split("&&"):
            words = shlex.split(part)
            while words and "=" in words[0] and not words[0].startswith("-"):  # VAR=value prefixes
                words = words[1:]
            if words:
                commands.append(words)
    return commands


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_shell_blocks_name_real_commands(page):
    for language, code, line, _ in code_blocks(page):
        if language not in ("bash", "sh", "shell", "console"):
            continue
        for words in _commands(code):
            try:
                _check_command(words)
            except SystemExit as exit_:  # argparse's verdict on bad arguments
                raise AssertionError(f"{_page_id(page)}:{line}: {' '.join(words)!r} does not parse") from exit_


@pytest.mark.parametrize("page", PAGES, ids=_page_id)
def test_links_stay_inside_the_repository(page):
    text = page.read_text()
    assert "../shared" not in text and "PROBLEMS.md" not in text and "papers/" not in text
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if re.match(r"\w+://", target):
            continue
        assert (page.parent / target).resolve().exists(), f"{_page_id(page)} links to a missing {target}"
        assert ROOT in (page.parent / target).resolve().parents, f"{_page_id(page)} links outside: {target}"


def test_the_marker_and_fences_are_read(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("text\n\n<!-- docs-test: slow -->\n```python\nx = 1\n```\n\n"
                    "```bash\npip install -e \".[nope]\"\n```\n")
    blocks = code_blocks(page)
    assert [(b[0], b[1], b[3]) for b in blocks] == [("python", "x = 1", True),
                                                    ("bash", 'pip install -e ".[nope]"', False)]
    with pytest.raises(AssertionError, match="no extra"):
        _check_command(_commands(blocks[1][1])[0])
    with pytest.raises(AssertionError, match="does not know"):
        _check_command(["make", "all"])
    with pytest.raises(SystemExit):
        _check_command(["python", "-m", "torchtraj.bench", "--no-such-option"])
