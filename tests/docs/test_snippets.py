"""Every code block of README.md, docs/*.md, deploy/README.md that a reader would run does run,
against a daemon (``python -m pd_service``) on loopback.

The marking convention (the fence's info string):

- ```` ```python ````: a program. It runs as a script of its own (a fresh interpreter, the
  repository's environment, a temporary working directory) and must exit 0 within
  :data:`BLOCK_TIMEOUT_S` (a block that hangs at exit fails too).
- ```` ```python outline ````: an API outline whose placeholders the reader fills in
  (``spec``, ``p1``, ``...``); compiled (its syntax checked), not run. A page's runnable
  example of the same API is elsewhere (the README's SDK block, service.md's raw-key one).
- ```` ```sh run ````: shell commands that run (``bash -e``) in a temporary directory that
  holds the repository's ``examples/`` and ``deploy/``, with the environment's executables
  (``pd-admin``, ...) on PATH; they must exit 0 within :data:`BLOCK_TIMEOUT_S`.
- ```` ```sh ```` (and ``bash``, ``console``): a command reference (starting daemons, the
  demo, benchmarks, deployments): not run.

In every block that runs, ``tcp/127.0.0.1:7447`` is replaced by the test daemon's endpoint
(so the test never needs port 7447 free); a block that should reach the daemon must name
that endpoint. Any other word after the language is an error (a misspelt marker must not
skip a block silently), and every ``deploy/...`` or ``examples/...`` path named in any
block must exist (a renamed file breaks its snippets).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ..service.procs import Daemon, watched_daemon

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "deploy" / "README.md"]
BLOCK_TIMEOUT_S = 90.0
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
_FENCE = re.compile(r"^```([a-z0-9]*)([^\n]*)\n(.*?)^```", re.S | re.M)
_SHELLS = ("sh", "bash", "console", "shell")
_PATH = re.compile(r"(?<![\w/.-])((?:deploy|examples)/[\w./-]*\w)")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    lang: str
    marker: str
    code: str

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks() -> list[Block]:
    out = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        for m in _FENCE.finditer(text):
            out.append(Block(page, text.count("\n", 0, m.start()) + 1, m.group(1),
                             m.group(2).strip(), m.group(3)))
    return out


ALL = blocks()
PYTHON = [b for b in ALL if b.lang == "python" and b.marker == ""]
OUTLINES = [b for b in ALL if b.lang == "python" and b.marker == "outline"]
SHELL_RUN = [b for b in ALL if b.lang in _SHELLS and b.marker == "run"]


def test_every_marker_is_known():
    known = {("python", ""), ("python", "outline"), *((s, m) for s in _SHELLS for m in ("", "run"))}
    bad = [(b.id, b.lang, b.marker) for b in ALL
           if b.lang in ("python", *_SHELLS) and (b.lang, b.marker) not in known]
    assert not bad, f"unknown fence markers (see this module's docstring): {bad}"


def test_the_convention_is_in_use():
    """Not vacuous: programs, outlines and runnable shell blocks all exist."""
    assert len(PYTHON) >= 5 and OUTLINES and SHELL_RUN


#: Paths the documented commands create (git-ignored), not files of the repository.
MADE_BY_COMMANDS = {"deploy/certs"}  # deploy/make_certs.py's output


def test_every_file_a_block_names_exists():
    missing = sorted({f"{b.id}: {p}" for b in ALL for p in _PATH.findall(b.code)
                      if p not in MADE_BY_COMMANDS and not (ROOT / p).exists()})
    assert not missing, f"files named in code blocks that do not exist: {missing}"


@pytest.mark.parametrize("block", OUTLINES, ids=lambda b: b.id)
def test_outlines_compile(block: Block):
    compile(block.code, block.id, "exec")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """One daemon for the module's blocks, seen alive by this process' own peer."""
    with watched_daemon("snippets", tmp_path_factory.mktemp("snippets") / "state") as d:
        yield d


def _run(argv: list[str], code: str, daemon: Daemon, cwd: Path) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    try:
        r = subprocess.run([*argv, code.replace(DEFAULT_ENDPOINT, daemon.endpoint)],
                           capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S, cwd=cwd,
                           env=env)
    except subprocess.TimeoutExpired as exc:
        raise AssertionError(f"did not end within {BLOCK_TIMEOUT_S} s; output:\n"
                             f"{exc.stdout!r}\n{exc.stderr!r}") from None
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout}\n{r.stderr}"


@pytest.mark.integration
@pytest.mark.parametrize("block", PYTHON, ids=lambda b: b.id)
def test_python_blocks_run(block: Block, daemon: Daemon, tmp_path: Path):
    _run([sys.executable, "-c"], block.code, daemon, tmp_path)


@pytest.mark.integration
@pytest.mark.parametrize("block", SHELL_RUN, ids=lambda b: b.id)
def test_runnable_shell_blocks_run(block: Block, daemon: Daemon, tmp_path: Path):
    for d in ("examples", "deploy"):
        (tmp_path / d).symlink_to(ROOT / d)
    _run(["bash", "-e", "-c"], block.code, daemon, tmp_path)
