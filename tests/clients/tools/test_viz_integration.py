"""Over real Zenoh on loopback with the real daemon, simulator and operator processes:
pd-viz serves the predicted pose (checked against the daemon's Prediction for the same
step, through a Foxglove WebSocket client), an MCAP recording of the run reads back, and
pd-replay with the recorded spec reproduces every published prediction to 1e-9."""

from __future__ import annotations

import pytest

pytest.importorskip("foxglove")
pytest.importorskip("mcap")
pytest.importorskip("websockets")
pytest.importorskip("google.protobuf")

from pd_client import Admin, Display  # noqa: E402
from pd_client.tools import pd_replay  # noqa: E402
from pd_client.tools.mcap_log import McapRecorder  # noqa: E402
from pd_client.tools.pd_viz import VizServer  # noqa: E402

from .foxglove_ws import FoxgloveClient  # noqa: E402
from .test_integration import Procs, _open_when_listening, free_port  # noqa: E402

pytestmark = pytest.mark.integration
STEPS = 120


@pytest.fixture
def procs(tmp_path):
    p = Procs(tmp_path)
    yield p
    p.stop_all()


def test_viz_mcap_and_replay_over_zenoh(procs, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    daemon = procs.start("daemon", "-m", "pd_service", "--listen", endpoint,
                         "--state-dir", str(tmp_path / "state"), "--instance", "vtest")
    transport = _open_when_listening(endpoint, daemon)
    client = server = None
    try:
        with Admin(transport) as admin:
            admin.wait_for_service(timeout=20)
        display = Display(transport, "paper", truth=True, history=STEPS * 2)
        published: dict[int, list] = {}  # t_ns -> the daemon's Predictions of that step
        display.on_prediction(lambda p: published.setdefault(p.t_ns, []).append(p))
        rec = McapRecorder(transport, ["paper"], tmp_path / "run.mcap", status_every=0.5)
        server = VizServer(transport, ["paper"], port=0)
        client = FoxgloveClient(server.url)
        client.wait_channels(["/paper/pose", "/paper/error"])
        client.subscribe(["/paper/pose", "/paper/error"])
        zenoh = ["--connect", endpoint]
        procs.start("operator", "-m", "pd_client.tools", "operator", *zenoh,
                    "--session", "paper", "--steps", str(STEPS))
        sim = procs.start("sim", "-m", "pd_client.tools", "sim", *zenoh, "--direct",
                          "--create-session", "--session", "paper", "--time-scale", "4",
                          "--steps", str(STEPS), "--progress", "0")
        while sim.poll() is None:
            client.pump(0.2)
        assert sim.returncode == 0, procs.log("sim")
        display.wait_pair(min_step=STEPS, timeout=10)
        client.pump(1.0)
        rec.close()
        Pose = client.protobuf_class("/paper/pose")
        poses = [Pose.FromString(d) for _, d in client.messages.get("/paper/pose", [])]
        assert len(poses) >= STEPS // 2
        matched = 0
        # once the truth named the states (p1, v1, p2, v2) the position is (p1, p2); before
        # that pd-viz shows states 0 and 1
        for pose in poses[len(poses) // 2:]:
            t_ns = pose.timestamp.seconds * 1_000_000_000 + pose.timestamp.nanos
            # the daemon may publish several predictions of one step (one per round that
            # accepted a packet, and the tick): the pose is one of them, exactly
            cands = [(p.x[0], p.x[2]) for p in published.get(t_ns, [])]
            if cands:
                assert (pose.pose.position.x, pose.pose.position.y) in cands
                matched += 1
        assert matched >= STEPS // 4
        assert client.messages.get("/paper/error")  # prediction - truth, once truth came

        recs = pd_replay.load(tmp_path / "run.mcap")
        r = recs["paper"]
        assert r.specs and len(r.predictions) >= STEPS and r.sensors and r.commands
        res = pd_replay.replay(r)
        dx, dp = res.max_abs_diff()
        assert dx <= 1e-9 and dp <= 1e-9, (dx, dp, res.diverged, res.missing_inputs)
        assert res.diverged == 0
        display.close()
    finally:
        if client is not None:
            client.close()
        if server is not None:
            server.close()
        transport.close()
