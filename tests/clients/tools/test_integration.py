"""Real processes over real Zenoh on loopback: the daemon (``python -m pd_service``), the
simulated robot and the scripted operator (``python -m pd_client.tools sim|operator``), and, in
this process, a Display and a Recorder. Checks that predictions arrive and track the truth.

The robot publishes straight on the service's keys (``--direct``: no link emulator; the
link's delays are covered by the demo's own integration tests). Time scale 4: 240 steps of
12.5 ms.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pd_client import Admin, Display, ServiceUnavailable, connect
from pd_client.tools.pd_record import Recorder
from pd_client.tools.record_csv import summarize

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
STEPS = 240
WARMUP = 40


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Procs:
    """Child processes, stopped by pid (SIGTERM, then SIGKILL) at the end."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, *args: str) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "w")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        p = subprocess.Popen([sys.executable, *args], stdout=log, stderr=subprocess.STDOUT,
                             cwd=ROOT, env=env)
        self.procs.append((name, p))
        return p

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text()

    def stop_all(self) -> None:
        for _, p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for _, p in reversed(self.procs):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


def _open_when_listening(endpoint: str, daemon: subprocess.Popen, timeout: float = 20.0):
    deadline = time.monotonic() + timeout
    while True:
        try:
            return connect(endpoint, "client")
        except ServiceUnavailable:
            if daemon.poll() is not None or time.monotonic() > deadline:
                raise
            time.sleep(0.1)  # the daemon is still starting: nothing listens yet


@pytest.fixture
def procs(tmp_path):
    p = Procs(tmp_path)
    yield p
    p.stop_all()


def test_sim_daemon_display_over_zenoh(procs, tmp_path):
    pytest.importorskip("pd_service.service.__main__")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    daemon = procs.start("daemon", "-m", "pd_service", "--listen", endpoint,
                         "--state-dir", str(tmp_path / "state"), "--instance", "itest")
    transport = _open_when_listening(endpoint, daemon)
    try:
        with Admin(transport) as admin:
            assert admin.wait_for_service(timeout=20) == ["itest"]
        display = Display(transport, "paper", truth=True, history=STEPS * 2)
        recorder = Recorder(transport, ["paper"], tmp_path / "rec")
        zenoh = ["--connect", endpoint]
        operator = procs.start("operator", "-m", "pd_client.tools", "operator", *zenoh,
                               "--session", "paper", "--steps", str(STEPS))
        sim = procs.start("sim", "-m", "pd_client.tools", "sim", *zenoh, "--direct",
                          "--create-session", "--session", "paper", "--time-scale", "4",
                          "--steps", str(STEPS), "--progress", "0")
        display.wait(1, timeout=30)  # predictions arrive ...
        viewer = procs.start("display", "-m", "pd_client.tools", "display", *zenoh,
                             "--session", "paper", "--count", "5", "--plain")
        while sim.poll() is None:
            recorder.poll(timeout=0.2)
        assert sim.returncode == 0, procs.log("sim")
        # ... and the prediction for the last step meets its truth. A daemon held up past a
        # step's tick (a slow or loaded machine) skips that step's prediction and counts it in
        # steps_missed at its next one: once a prediction past the last step is in, the newest
        # pair is at most that many steps before it.
        deadline = time.monotonic() + 30
        while display.latest().step <= STEPS and time.monotonic() < deadline:
            display.wait(display.stats().received + 1, timeout=30)
        missed = display.latest().counters.get("steps_missed", 0)
        display.wait_pair(min_step=STEPS - missed, timeout=10)
        recorder.poll(timeout=0.5)
        recorder.close()
        assert operator.wait(20) == 0, procs.log("operator")
        assert viewer.wait(20) == 0, procs.log("display")
        assert "newest prediction" in procs.log("display")

        # The predictions track the truth: pair each prediction with the truth at its target
        # step, from WARMUP steps after the first prediction made with a measurement (on a
        # slow machine the robot's first samples come later than step 0).
        first = next((s for s in range(STEPS + 1) if (p := display.prediction_for(s)) is not None
                      and p.newest_step is not None), STEPS + 1)
        start = first + WARMUP
        why = (f"first prediction with data for step {first}; {missed} steps missed; sim: "
               f"{procs.log('sim').strip().splitlines()[-1:]}; counters: "
               f"{display.latest().counters}")
        assert start <= STEPS - 100, why  # at least 100 steps to judge
        errs, sds = [], []
        for step in range(start, STEPS + 1):
            p, t = display.prediction_for(step), display.truth_at(step)
            if p is not None and t is not None:
                errs.append(p.x - t.x)
                sds.append(np.sqrt(np.diag(p.P)))
        errs, sds = np.array(errs), np.array(sds)
        # a few may be lost, not many (those the daemon skipped are not lost)
        assert len(errs) >= 0.9 * (STEPS + 1 - start - missed), why
        rms = np.sqrt(np.mean(errs**2, axis=0))
        assert rms[0] < 0.5 and rms[2] < 0.5, (rms, why)  # positions p1, p2 (m)
        assert np.mean(np.abs(errs) <= 4 * sds) > 0.95, why
        latest = display.latest()
        assert latest.counters.get("accepted", 0) > 0
        assert latest.counters.get("commands_accepted", 0) > 0
        # The only refusals: samples that came too late (a slow start's first steps, which the
        # robot publishes at once), each counted; the display saw no invalid message.
        refused = latest.counters.get("refused", 0)
        assert refused == latest.counters.get("late", 0), why
        stats = display.stats()
        assert stats.invalid == 0 and stats.errors <= refused, stats.last_error

        summary = summarize(tmp_path / "rec" / "paper.csv", warmup=start)
        assert summary["rows"] >= 0.9 * (STEPS + 1 - start - missed), why
        assert math.isclose(summary["rms_p1"], rms[0], rel_tol=0.2)
        assert summary["mean_var_p2"] < 0.2
        display.close()
    finally:
        transport.close()
