"""``pd-demo`` (what ``make demo`` runs) starts the camera robot out of the box: its live view
(pd-web) receives the ``rover`` session's camera frames, 500 ms late through pd-link's
``video`` rule, each with the ghost drawn from the daemon's prediction. ``pd-demo --ros2``
(``make demo-ros2``): the ROS 2 robot's camera, CompressedImage + CameraInfo 400 ms late,
made into frames by pd-ros2. The demo's processes, as a user starts them; stopped by Ctrl-C
once a ghost was seen."""

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

from pd_client.tools.pd_demo import CAMERA_SESSION, ROS2_SESSION, has_viz
from tests.clients.tools.test_startup import BOUND_S, process, tool

pytestmark = pytest.mark.integration


@pytest.mark.skipif(not has_viz(), reason="the camera robot needs the viz extra (Pillow)")
@pytest.mark.parametrize(("variant", "session", "video_ms"), [
    ([], CAMERA_SESSION, 500.0), (["--ros2"], ROS2_SESSION, 400.0)])
def test_the_demo_shows_the_ghost_on_the_delayed_video(tmp_path: Path, variant, session,
                                                       video_ms) -> None:
    if variant:
        pytest.importorskip("rosbags")
    argv = [tool("pd-demo"), *variant, "--out", str(tmp_path / "demo"), "--no-viz",
            "--web-port", "0", "--steps", "2000"]
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
                    if ev.get("type") == "frame" and ev["s"] == session and ev["ghost"]:
                        frame = ev
                        break
                if time.monotonic() > deadline:
                    break
        os.killpg(p.pid, signal.SIGINT)
        try:
            p.wait(BOUND_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"pd-demo still running {BOUND_S:g} s after Ctrl-C\n{out.text}")
    assert frame is not None, f"no frame with a ghost from {session}\n{out.text}"
    assert frame["age_ms"] >= video_ms - 50.0  # captured at least the video rule's delay ago
    g = frame["ghost"]
    assert len(g["px"]) == 5 and g["k"] > frame["k"]  # the outline, at a later step
    print(f"\n{session} frame captured at step {frame['k']:.0f}, {frame['age_ms']:.0f} ms old; "
          f"ghost of the prediction of step {g['k']} at {g['pose']}")
