"""Every ```python block of README.md and doc/**/*.md runs, so the docs cannot drift from the
code.

The blocks of one Markdown file run in order in one namespace, like a notebook: a block may use
what an earlier block of its file made. Each block is its own case, named ``FILE:LINE`` (the
line of its opening fence); running one alone runs the blocks before it first. Tracebacks give
the Markdown file and its line numbers.

They run in a temporary directory that mirrors the repository root (a link to each top-level
entry), so a relative path such as ``config/hdl64.yaml`` resolves as from the root while the
files an example writes (``map.npz``) stay out of the work tree. Only fences whose info string
is ``python`` (or ``py``, ``python3``) run; ``bash``, ``yaml``, ``text``, ``cpp`` and unlabelled
blocks do not. The examples make their own data with the simulator; an optional package an
example needs that is missing (small-gicp, gtsam, ...) skips it with the reason.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from project_paths import ROOT

_RUN = frozenset({'python', 'py', 'python3'})
_FENCE = re.compile(r'^(\s*)(`{3,}|~{3,})(.*)$')
# Packages of the extras: an example that needs a missing one is skipped, not failed.
_OPTIONAL = frozenset({'small_gicp', 'gtsam', 'kiss_icp', 'rclpy', 'matplotlib'})


@dataclass(frozen=True)
class Block:
    """One fenced block to run.

    Attributes:
        path: the Markdown file.
        line: 1-based line of its opening fence.
        code: its text, dedented by the fence's indent.
    """

    path: Path
    line: int
    code: str

    @property
    def name(self) -> str:
        """``FILE:LINE``, the file relative to the root when it lies under it."""
        try:
            rel = self.path.relative_to(ROOT)
        except ValueError:
            rel = self.path
        return f'{rel}:{self.line}'


def markdown_files(root: Path) -> list[Path]:
    """README.md and every .md file under doc/, in a stable order."""
    out = [root / 'README.md'] if (root / 'README.md').is_file() else []
    doc = root / 'doc'
    if doc.is_dir():
        out += sorted(p for p in doc.rglob('*.md') if p.is_file())
    return out


def python_blocks(path: Path) -> list[Block]:
    """The runnable blocks of one Markdown file, in order (fences of ``` or ~~~, closed by
    a fence of the same character at least as long; an unclosed one runs to the end)."""
    lines = path.read_text(encoding='utf-8').splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        opening = _FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        indent, fence, info = opening.groups()
        j = i + 1
        while j < len(lines) and not _closes(lines[j], fence):
            j += 1
        words = info.strip().split()
        if words and words[0].lower() in _RUN:
            body = [line[len(indent):] if line.startswith(indent) else line.lstrip()
                    for line in lines[i + 1:j]]
            out.append(Block(path, i + 1, '\n'.join(body) + '\n'))
        i = j + 1
    return out


def _closes(line: str, fence: str) -> bool:
    text = line.strip()
    return len(text) >= len(fence) and set(text) == {fence[0]}


@dataclass
class _Notebook:
    """The blocks of one file and the namespace they share, as a script pasted from them."""

    blocks: list[Block]
    namespace: dict[str, Any] = field(default_factory=lambda: {'__name__': '__main__'})
    done: int = 0
    stopped: str | None = None  # why the later blocks cannot run
    skipped: bool = False

    def run_through(self, index: int) -> None:
        """Run the blocks up to ``index`` that have not run yet, in order."""
        while self.done <= index:
            if self.stopped is not None:
                (pytest.skip if self.skipped else pytest.fail)(self.stopped)
            block = self.blocks[self.done]
            self.done += 1
            try:
                # Blank lines first, so tracebacks give the Markdown file's line numbers.
                code = compile('\n' * block.line + block.code, str(block.path), 'exec')
                exec(code, self.namespace)
            except ModuleNotFoundError as err:
                self.stopped = f'not run: {block.name} needs {err.name}, which is not installed'
                self.skipped = err.name in _OPTIONAL
                if not self.skipped:
                    raise
                pytest.skip(self.stopped)
            except BaseException:
                self.stopped = f'not run: {block.name} failed before it'
                raise


BLOCKS = [b for path in markdown_files(ROOT) for b in python_blocks(path)]
_NOTEBOOKS: dict[Path, _Notebook] = {}


@pytest.fixture(scope='module')
def mirror(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory that looks like the repository root, where the examples may write."""
    out = tmp_path_factory.mktemp('docs')
    for entry in ROOT.iterdir():
        if not entry.name.startswith('.'):
            (out / entry.name).symlink_to(entry)
    return out


@pytest.mark.slow
@pytest.mark.parametrize('block', BLOCKS, ids=[b.name for b in BLOCKS])
def test_python_block_runs(block: Block, mirror: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(mirror)
    book = _NOTEBOOKS.setdefault(
        block.path, _Notebook([b for b in BLOCKS if b.path == block.path]))
    book.run_through(book.blocks.index(block))


def test_blocks_of_readme_and_every_doc_file_are_found(tmp_path: Path) -> None:
    (tmp_path / 'README.md').write_text(
        '# x\n```python\na = 1\n```\n```bash\nexit 1\n```\n```\nnot run\n```\n')
    deep = tmp_path / 'doc' / 'guide'
    deep.mkdir(parents=True)
    (deep / 'use.md').write_text(
        'text\n\n  ~~~~ py title\n  b = a + 1\n  ```\n  c = 2\n  ~~~~\n- item\n'
        '  ```python\n  d = 3\n  ```\n')
    (tmp_path / 'doc' / 'notes.txt').write_text('```python\nnot markdown\n```\n')
    files = markdown_files(tmp_path)
    assert files == [tmp_path / 'README.md', deep / 'use.md']
    blocks = [b for path in files for b in python_blocks(path)]
    assert [(b.path.name, b.line, b.code) for b in blocks] == [
        ('README.md', 2, 'a = 1\n'), ('use.md', 3, 'b = a + 1\n```\nc = 2\n'),
        ('use.md', 9, 'd = 3\n')]
    # The repository's own files are collected the same way.
    assert markdown_files(ROOT)[0] == ROOT / 'README.md'
    assert any(b.path == ROOT / 'README.md' for b in BLOCKS)


_LINK = re.compile(r'\]\(([^)\s#]+)(?:#[^)]*)?\)')


def test_relative_links_resolve() -> None:
    """Every relative link of README.md and doc/ names a file that exists: a page that quotes a
    bench report links to a report a script wrote, not to one that was never run."""
    broken = []
    for md in markdown_files(ROOT):
        for n, line in enumerate(md.read_text().splitlines(), 1):
            for target in _LINK.findall(line):
                if '://' in target or target.startswith('mailto:'):
                    continue
                if not (md.parent / target).exists():
                    broken.append(f'{md.relative_to(ROOT)}:{n}: {target}')
    assert not broken, '\n'.join(broken)
