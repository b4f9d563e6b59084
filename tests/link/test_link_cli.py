"""pd-link as a separate process, through real Zenoh on loopback."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pd_service.wire import keys

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000


def pd_link(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pd_service.link", *args],
        cwd=ROOT,
        env=os.environ | {"PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


class StderrWatcher:
    """Reads the child's stderr in a thread; ``wait_for(text)`` waits for a line with it."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stderr:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait_for(self, text: str, timeout: float = 20.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not any(text in line for line in self.lines):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True


@pytest.mark.integration
def test_bad_config_exits_2_with_a_clear_message(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[[downlink]]\ndelay = "10 steps"\n')
    proc = pd_link("--config", str(cfg), "--connect", "tcp/127.0.0.1:9")
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2
    assert "step_ms" in err and "bad configuration" in err


@pytest.mark.integration
def test_paper_link_end_to_end(zenoh_pair, collector_factory):
    test_s, _, endpoint = zenoh_pair
    got = collector_factory()
    sub = test_s.declare_subscriber(keys.sensors_of("cli"), got)
    sub_cmd = test_s.declare_subscriber(keys.robot_command_key("cli"), got)
    proc = pd_link("--config", str(ROOT / "deploy" / "link-paper.toml"), "--connect", endpoint,
                   "--instance", "itest", "--log-format", "json")  # fmt: skip
    watch = StderrWatcher(proc)
    try:
        assert watch.wait_for("pd-link ready"), "\n".join(watch.lines)
        cam = test_s.declare_publisher(keys.robot_sensor_key("cli", "camera"))
        rng = test_s.declare_publisher(keys.robot_sensor_key("cli", "ranger"))
        imu = test_s.declare_publisher(keys.robot_sensor_key("cli", "imu"))
        cmd = test_s.declare_publisher(keys.command_key("cli"))
        # wait until the other-sensors rule (no delay) relays a probe: all routes are up
        for i in range(200):
            imu.put(b"probe-%d" % i)
            if got.wait_for(lambda items: len(items) > 0, 0.05):
                break
        got.ignore_prefix = b"probe"
        got.clear()
        while not (cam.matching_status.matching and cmd.matching_status.matching):
            time.sleep(0.01)

        sent: dict[bytes, int] = {}
        for i in range(10):
            for name, pub in (("cam", cam), ("rng", rng), ("cmd", cmd)):
                payload = b"%s-%d" % (name.encode(), i)
                sent[payload] = time.monotonic_ns()
                pub.put(payload)
            time.sleep(0.01)
        assert got.wait_for(lambda items: len(items) >= 30, 10.0)
        delays: dict[bytes, list[float]] = {b"cam": [], b"rng": [], b"cmd": []}
        for t, _key, payload in got.items:
            delays[payload.split(b"-")[0]].append((t - sent[payload]) / MS)
        summary = {k.decode(): round(float(np.median(v)), 2) for k, v in delays.items()}
        print(f"measured median delays (ms): {summary}; configured cam 500, rng 600, cmd 500")
        for name, configured in ((b"cam", 500), (b"rng", 600), (b"cmd", 500)):
            assert len(delays[name]) == 10
            assert min(delays[name]) >= configured - 1  # never early
            assert np.median(delays[name]) < configured + 80  # loose: loaded 2-core machine
        keys_seen = {key for _, key, _ in got.items}
        assert keys_seen == {keys.sensor_key("cli", "camera"), keys.sensor_key("cli", "ranger"),
                             keys.robot_command_key("cli")}

        deadline = time.monotonic() + 5  # counters move just after put(): poll briefly
        while True:
            replies = list(test_s.get(keys.link_stats_key("itest"), timeout=10.0))
            stats = json.loads(replies[0].ok.payload.to_bytes())
            by_name = {r["name"]: r for r in stats["rules"]}
            done = by_name["camera"]["forwarded"] >= 10 and by_name["commands"]["forwarded"] >= 10
            if done or time.monotonic() > deadline:
                break
            time.sleep(0.02)
        assert by_name["camera"]["forwarded"] == 10 and by_name["commands"]["forwarded"] == 10
        assert 499 <= by_name["ranger"]["delay_ms"]["p50"] < 680

        # replace the rules at runtime: the camera now goes through in ~0 ms
        new = {"downlink": [{"name": "camera-fast", "match": "robot/*/*/sensor/camera"}]}
        replies = list(test_s.get(keys.link_rules_key("itest"),
                                  payload=json.dumps(new).encode(), timeout=10.0))  # fmt: skip
        assert json.loads(replies[0].ok.payload.to_bytes())["generation"] == 2
        got.clear()
        t0 = time.monotonic_ns()
        cam.put(b"fast")
        assert got.wait_for(lambda items: len(items) == 1, 5.0)
        assert (got.items[0][0] - t0) / MS < 300
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
            sub.undeclare()
            sub_cmd.undeclare()
    assert proc.returncode == 0, "\n".join(watch.lines)
    assert watch.wait_for("pd-link stopped", 1.0)
    json.loads(watch.lines[0])  # --log-format json gives JSON lines
