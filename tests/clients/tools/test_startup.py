"""Start-up and shutdown as a user meets them, each in its own processes:

- a tool started before the daemon retries with backoff (said on stderr) and then works;
  without a daemon it gives up after ``--connect-wait`` with a clear message, no Rust path;
- a snippet that subscribes through the SDK and returns exits (with and without closing);
- Ctrl-C (SIGINT to pd-demo's process group, as a terminal sends it) stops pd-demo and all
  its processes, and it prints nothing the interrupted run did not do.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from pd_service.transport import ZenohTransport, zenoh_config

pytestmark = pytest.mark.integration

BIN = Path(sys.executable).parent
ENV = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONWARNINGS": "ignore"}
#: Bound of every wait for a process (s): a hang fails the test instead of stalling the suite.
BOUND_S = 60.0


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class Lines:
    """A process's output lines, read on a thread; ``wait_for(text)`` blocks until a line
    containing ``text`` arrives (False if the process ended first or the bound passed)."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._done = False
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        for line in stream:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._done = True
            self._cond.notify_all()

    def wait_for(self, text: str, timeout: float = BOUND_S) -> bool:
        with self._cond:
            return self._cond.wait_for(
                lambda: any(text in ln for ln in self.lines) or self._done, timeout) and any(
                text in ln for ln in self.lines)

    @property
    def text(self) -> str:
        with self._cond:
            return "\n".join(self.lines)


@contextmanager
def process(argv: list[str], **kw) -> Iterator[tuple[subprocess.Popen, Lines]]:
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         env=ENV, **kw)
    try:
        yield p, Lines(p.stdout)
    finally:
        if p.poll() is None:
            p.kill()
        p.wait()


def tool(name: str) -> str:
    exe = BIN / name
    if not exe.exists():
        pytest.skip(f"{name} is not installed in this venv")
    return str(exe)


def test_a_tool_started_before_the_daemon_retries_then_works(tmp_path: Path) -> None:
    endpoint = free_endpoint()
    sim = [tool("pd-robot-sim"), "--connect", endpoint, "--session", "early",
           "--create-session", "--create-only", "--connect-wait", "45"]
    with process(sim) as (p, out):
        assert out.wait_for("retrying in"), out.text
        assert ".rs:" not in out.text, out.text
        with process([tool("pd-service"), "--listen", endpoint, "--state-dir",
                      str(tmp_path / "state"), "--instance", "late"]) as (daemon, dout):
            assert p.wait(BOUND_S) == 0, f"{out.text}\n--- daemon\n{dout.text}"


def test_pd_ros2_started_before_the_daemon_retries_then_serves(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    endpoint = free_endpoint()
    with process([tool("pd-ros2"), "--connect", endpoint, "--connect-wait", "45",
                  "--instance", "early"]) as (bridge, out):
        assert out.wait_for("no answer yet"), out.text
        with process([tool("pd-service"), "--listen", endpoint, "--state-dir",
                      str(tmp_path / "state"), "--instance", "late"]) as (_daemon, dout):
            assert out.wait_for("event=ready"), f"{out.text}\n--- daemon\n{dout.text}"
            bridge.send_signal(signal.SIGTERM)
            assert bridge.wait(BOUND_S) == 0, out.text


def test_a_tool_without_a_daemon_gives_up_with_a_clear_message() -> None:
    done = subprocess.run([tool("pd-display"), "--connect", free_endpoint(), "--connect-wait",
                           "1"], capture_output=True, text=True, timeout=BOUND_S, env=ENV)
    assert done.returncode == 1
    assert "retried for 1 s" in done.stderr and "cannot open a Zenoh client session" in \
        done.stderr, done.stderr
    assert ".rs:" not in done.stderr, done.stderr


SNIPPET = """
import sys
from pd_client import Display
{open}
d.on_prediction(lambda p: None)
print("subscribed", flush=True)
{close}
"""


@pytest.mark.parametrize("style", ["context-manager", "left-open"])
def test_a_snippet_that_subscribes_and_returns_exits(style: str) -> None:
    endpoint = free_endpoint()
    code = SNIPPET.format(
        open=f"with Display.connect('s1', endpoint={endpoint!r}) as d:" if style ==
        "context-manager" else f"d = Display.connect('s1', endpoint={endpoint!r})",
        close="")
    if style == "context-manager":  # the body of the with block, indented
        head, body = code.split(":\n", 1)
        code = head + ":\n" + textwrap.indent(body, "    ")
    with ZenohTransport(zenoh_config(mode="peer", listen=[endpoint])):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=BOUND_S, env=ENV)
    assert done.returncode == 0, done.stderr
    assert "subscribed" in done.stdout


def test_ctrl_c_stops_pd_demo_promptly_and_truthfully(tmp_path: Path) -> None:
    argv = [tool("pd-demo"), "--out", str(tmp_path / "demo"), "--no-viz", "--no-web",
            "--steps", "2000"]
    with process(argv, start_new_session=True) as (p, out):
        assert out.wait_for("recording"), out.text  # mid-run: every process is up
        os.killpg(p.pid, signal.SIGINT)  # what a Ctrl-C in its terminal sends
        try:
            code = p.wait(BOUND_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"pd-demo still running {BOUND_S:g} s after Ctrl-C\n{out.text}")
        text = out.text
    assert code == 130, text
    assert "interrupted" in text
    for false_claim in ("whole run", "final state for", "simulation done"):
        assert false_claim not in text, text
    # no process of the demo is left behind
    leftover = subprocess.run(["pgrep", "-f", str(tmp_path / "demo")], capture_output=True,
                              text=True)
    assert leftover.stdout.strip() == "", leftover.stdout
