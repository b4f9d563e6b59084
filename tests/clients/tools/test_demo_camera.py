"""``pd-demo`` (what ``make demo`` runs) starts the camera robot out of the box: its live view
(pd-web) receives the ``rover`` session's camera frames, 500 ms late through pd-link's
``video`` rule, each with the ghost drawn from the daemon's prediction. The demo's processes,
as a user starts them; stopped by Ctrl-C once a ghost was seen."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from pd_client.tools.pd_demo import CAMERA_SESSION, has_viz
from tests.clients.tools.test_startup import BOUND_S, process, tool

pytestmark = pytest.mark.integration


@pytest.mark.skipif(not has_viz(), reason="the camera robot needs the viz extra (Pillow)")
def test_the_demo_shows_the_ghost_on_the_delayed_video(tmp_path: Path) -> None:
    argv = [tool("pd-demo"), "--out", str(tmp_path / "demo"), "--no-viz", "--web-port", "0",
            "--steps", "2000"]
    with process(argv, start_new_session=True) as (p, out):
        assert out.wait_for("pd-web: live view at"), out.text  # pd-web listens
        url = re.search(r"live view at (http://127\.0\.0\.1:\d+/)", out.text)
        assert url, out.text
        frame = None
        deadline = time.monotonic() + 2 * BOUND_S
        with urllib.request.urlopen(url.group(1) + "events", timeout=BOUND_S) as events:
            for raw in events:
                line = raw.decode().strip()
                if line.startswith("data: "):
                    ev = json.loads(line[6:])
                    if ev.get("type") == "frame" and ev["s"] == CAMERA_SESSION and ev["ghost"]:
                        frame = ev
                        break
                if time.monotonic() > deadline:
                    break
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(BOUND_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"pd-demo still running {BOUND_S:g} s after Ctrl-C\n{out.text}")
    assert frame is not None, f"no frame with a ghost from {CAMERA_SESSION}\n{out.text}"
    assert frame["age_ms"] >= 450.0  # captured at least the video rule's 500 ms earlier
    g = frame["ghost"]
    assert len(g["px"]) == 5 and g["k"] > frame["k"]  # the outline, at a later step
    print(f"\nrover frame captured at step {frame['k']:.0f}, {frame['age_ms']:.0f} ms old; "
          f"ghost of the prediction of step {g['k']} at {g['pose']}")
