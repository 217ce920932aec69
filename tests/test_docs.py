"""Every ```python code block of README.md and of the documentation pages
(docs/**/*.md) runs as written.

Each block runs on its own, in a fresh namespace: nothing carries over from
one block to the next, on the same page either, so every block holds its
own imports and data (as RoMa's and kornia's snippets do). The blocks share
this process, so a block that uses a torchrot submodule which ``import
torchrot`` does not load (``torchrot.testing``, ``torchrot.apps``, ...) must
import it itself; that is checked before the block runs. Blocks run with one
torch thread; the thread count and the state of torch's CPU random
generator are restored after each.

A block counts if its fence's info string is ``python`` or ``py``, or a
MyST ``{code-block}`` / ``{code}`` directive with the argument ``python``;
blocks of other languages (``bash``, ``none``, ...) are not run. A failure
names the file and the line: the block is compiled with the file's own line
numbers, so the traceback points into the Markdown file.

Sphinx is not needed: the pages are read as Markdown. The docstrings'
``>>>`` examples are run by ``.ci/docs`` (``sphinx -b doctest``).
"""
from __future__ import annotations

import ast
import functools
import importlib.util
import pathlib
import re
import subprocess
import sys
import traceback
from dataclasses import dataclass

import pytest
import torch

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
PYTHON = {"python", "py", "python3"}

_FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})(?P<info>.*)$")


@dataclass(frozen=True)
class Block:
    path: pathlib.Path
    line: int  # 1-based line of the block's first code line
    code: str

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def _is_python(info: str) -> bool:
    words = info.strip().split()
    if not words:
        return False
    if words[0] in ("{code-block}", "{code}", "{code-cell}"):
        return len(words) > 1 and words[1] in PYTHON
    return words[0] in PYTHON


def code_blocks(path: pathlib.Path) -> list[Block]:
    """The Python blocks of a Markdown file, with the line of their first code line."""
    lines = path.read_text(encoding="utf-8").splitlines()
    blocks = []
    i = 0
    while i < len(lines):
        match = _FENCE.match(lines[i])
        if not match:
            i += 1
            continue
        indent, fence, info = len(match["indent"]), match["fence"], match["info"]
        closing = re.compile(rf"^ *{re.escape(fence[0])}{{{len(fence)},}}\s*$")
        start = i + 1
        end = start
        while end < len(lines) and not closing.match(lines[end]):
            end += 1
        if _is_python(info):
            body = lines[start:end]
            first = start
            # a MyST directive's options (":caption: ...") precede its code
            while first < end and lines[first].strip().startswith(":") and info.strip().startswith("{"):
                first += 1
            code = "\n".join(line[indent:] if line[:indent].strip() == "" else line for line in body[first - start:])
            blocks.append(Block(path, first + 1, code))
        i = end + 1
    return blocks


def _all_blocks() -> list[Block]:
    return [block for page in PAGES for block in code_blocks(page)]


def _params():
    return [pytest.param(block, id=block.where) for block in _all_blocks()]


@functools.cache
def _loaded_by_import() -> frozenset[str]:
    """The torchrot submodules that a bare ``import torchrot`` loads, in a fresh interpreter."""
    code = "import sys, torchrot; print(' '.join(m for m in sys.modules if m.startswith('torchrot.')))"
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout
    return frozenset(out.split())


def unimported_submodules(code: str) -> list[str]:
    """``torchrot.<sub>`` attributes a block uses without importing them: they
    exist only where something else imported the submodule first (as the
    test session does), so the block would fail on its own."""
    tree = ast.parse(code)
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            imported.add(node.module)
            imported.update(f"{node.module}.{alias.name}" for alias in node.names)
    missing = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "torchrot":
            name = f"torchrot.{node.attr}"
            if (name not in _loaded_by_import() and name not in imported
                    and importlib.util.find_spec(name) is not None):
                missing.append(name)
    return sorted(set(missing))


def run_block(block: Block) -> None:
    """Runs one block in a fresh namespace; on an exception, fails naming the
    file, the line and the failing line's text, with the traceback."""
    missing = unimported_submodules(block.code)
    if missing:
        pytest.fail(f"{block.where}: the code block uses {', '.join(missing)} without importing it "
                    f"(import torchrot does not load it): add `import {missing[0]}`", pytrace=False)
    # Padded so that the compiled code's line numbers are the file's.
    source = "\n" * (block.line - 1) + block.code
    try:
        code = compile(source, str(block.path), "exec")
        exec(code, {"__name__": "__docs__"})
    except Exception as error:  # noqa: BLE001  (any failure of a block is the test's failure)
        frames = [frame for frame in traceback.extract_tb(error.__traceback__) if frame.filename == str(block.path)]
        line = frames[-1].lineno if frames else getattr(error, "lineno", None) or block.line
        text = block.path.read_text(encoding="utf-8").splitlines()[line - 1].strip()
        details = "".join(traceback.format_exception(error))
        pytest.fail(f"{block.path.relative_to(ROOT)}:{line}: the code block starting at line {block.line} raised "
                    f"{type(error).__name__}: {error}\n    {text}\n\n{details}", pytrace=False)


@pytest.mark.parametrize("block", _params())
def test_code_block_runs(block: Block) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small examples: one thread keeps the suite's CPU use predictable
    try:
        with torch.random.fork_rng(devices=[]):  # a block may seed torch's generator: restored after it
            run_block(block)
    finally:
        torch.set_num_threads(threads)


def test_pages_have_code_blocks() -> None:
    """The collection itself: every page with a ```python fence yields its blocks."""
    pages = {block.path for block in _all_blocks()}
    assert ROOT / "README.md" in pages
    assert any(path.parent.name == "docs" for path in pages), "no Python block found under docs/"


def _two_commands(page: pathlib.Path) -> list[str]:
    """The lines of ``page`` that install torchrot and run the main job or the tests."""
    return [line for line in page.read_text().splitlines()
            if line.startswith("pip install torch==") and ("torchrot bench" in line or "pytest" in line)]


def test_installation_page_gives_the_readme_commands() -> None:
    """docs/installation.md repeats the README's two commands (the site stands
    alone); .ci/run runs the README's test command as it stands there."""
    readme = _two_commands(ROOT / "README.md")
    assert len(readme) == 2 and any("pytest" in line for line in readme)
    assert _two_commands(ROOT / "docs" / "installation.md") == readme
