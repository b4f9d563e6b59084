"""pd-web without a browser: the per-session events the feed computes (in-memory bus, fake
clocks) and the HTTP server (static files, Server-Sent Events, state)."""

from __future__ import annotations

import json
import math
import shutil
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from pd_client.tools import pd_web
from pd_client.tools.web_fanout import Fanout
from pd_client.tools.web_feed import LiveFeed, ellipse_2sigma, position_layout
from pd_client.truth import Truth
from pd_service.scenarios import get_scenario
from pd_service.transport import InMemoryBus
from pd_service.wire import Command, Measurement, Prediction, encode, keys
from pd_service.wire.path import PredictedPath

EPOCH = 1_000_000_000_000
PERIOD = 50_000_000  # ns


class Clock:
    def __init__(self) -> None:
        self.ns = EPOCH + 120 * PERIOD
        self.mono = 100.0


def pred(session: str, step: int, x: np.ndarray, P: np.ndarray, seq: int = 0,
         made_ns: int = EPOCH, term: int = 0) -> Prediction:
    return Prediction(session=session, seq=seq, step=step, t_ns=EPOCH + step * PERIOD, x=x, P=P,
                      newest_step=max(0, step - 10), made_ns=made_ns,
                      counters={"accepted": 7, "late": 2, "refused": 3}, term=term)


@pytest.fixture
def feed():
    bus = InMemoryBus()
    t = bus.transport()
    out: list[dict] = []
    clock = Clock()
    f = LiveFeed(t, lambda text: out.append(json.loads(text)), stale_s=1.0,
                 now_ns=lambda: clock.ns, mono=lambda: clock.mono)
    spec = get_scenario("paper").spec("paper", EPOCH)
    f._view("paper").spec = spec
    yield f, t, out, clock
    f.close()


def test_position_layout() -> None:
    assert position_layout(["p1", "v1", "p2", "v2"], 4) == ("axis", [0, 2])
    assert position_layout(["x", "y", "theta", "vx", "vy", "omega"], 6) == ("plane", [0, 1])
    assert position_layout(["px", "py", "vx", "vy"], 4) == ("plane", [0, 1])
    assert position_layout(None, 3) == ("axis", [0])
    assert position_layout(["a", "b"], 3) == ("axis", [0])  # names of another length: unused


def test_ellipse_2sigma_axes_and_angle() -> None:
    a, b, ang = ellipse_2sigma(np.diag([4.0, 1.0]))
    assert (a, b) == pytest.approx((4.0, 2.0))
    assert math.cos(ang) ** 2 == pytest.approx(1.0)  # major axis along x
    # rotated by 30 degrees: C = R diag(9, 1) R^T
    th = math.radians(30)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    a, b, ang = ellipse_2sigma(R @ np.diag([9.0, 1.0]) @ R.T)
    assert (a, b) == pytest.approx((6.0, 2.0))
    assert math.tan(ang) == pytest.approx(math.tan(th))


def test_prediction_event_has_what_the_page_draws(feed) -> None:
    f, t, out, clock = feed
    names = ["p1", "v1", "p2", "v2"]
    t.put(keys.truth_key("paper"), encode(Truth(session="paper", step=130, t_ns=EPOCH + 130 * PERIOD,
                                                x=np.array([1.0, 0.5, 9.0, 0.0]), names=names)))
    # the camera measures p1 and p2 directly (rows e_0, e_2 of H); sampled at 110
    t.put(keys.sensor_key("paper", "camera"),
          encode(Measurement(session="paper", sensor="camera", seq=1, step=110, z=np.array([0.9, 8.8]))))
    t.put(keys.sensor_key("paper", "ranger"),
          encode(Measurement(session="paper", sensor="ranger", seq=1, step=108, z=np.array([7.9]))))
    t.put(keys.command_key("paper"), encode(Command(session="paper", seq=4, step=131, u=np.array([0.5]))))
    P = np.diag([0.04, 0.01, 0.09, 0.01])
    x = np.array([1.1, 0.5, 9.2, 0.0])
    t.put(keys.prediction_key("paper"), encode(pred("paper", 130, x, P, seq=5)))
    assert len(out) == 1
    ev = out[0]
    assert ev["type"] == "pred" and ev["s"] == "paper" and ev["k"] == 130 and ev["seq"] == 5
    assert ev["layout"] == "axis" and ev["pos"] == [0, 2] and ev["names"] == names
    assert ev["x"] == x.tolist() and ev["var"] == np.diag(P).tolist()
    assert ev["now"] == 120 and ev["lead"] == 10 and ev["period_ms"] == 50.0
    assert ev["meas"]["camera"]["p"] == {"p1": 0.9, "p2": 8.8} and ev["meas"]["camera"]["k"] == 110
    assert ev["meas"]["camera"]["age_ms"] == pytest.approx(10 * 50.0)  # now 120, sampled 110
    assert "ranger" not in ev["meas"]  # p2 - p1 is not a position
    assert set(ev["delay_ms"]) == {"camera", "ranger"} and ev["delay_ms"]["camera"] > 0
    assert ev["truth"] == {"k": 130, "p": [1.0, 9.0]}
    assert ev["err"]["k"] == 130 and ev["err"]["e"] == pytest.approx((x - [1.0, 0.5, 9.0, 0.0]).tolist())
    assert ev["c"] == {"accepted": 7, "late": 2, "future": 0, "refused": 3}
    assert ev["cmd"] == {"k": 131, "u": [0.5]}
    assert ev["ell"] is None and ev["i"] == 1


def test_planar_event_has_the_ellipse(feed) -> None:
    f, t, out, _ = feed
    t.put(keys.truth_key("omni"), encode(Truth(session="omni", step=3, t_ns=EPOCH, x=np.zeros(6),
                                               names=["x", "y", "theta", "vx", "vy", "omega"])))
    P = np.eye(6)
    P[:2, :2] = [[4.0, 0.0], [0.0, 1.0]]
    t.put(keys.prediction_key("omni"), encode(pred("omni", 5, np.arange(6.0), P)))
    ev = out[-1]
    assert ev["layout"] == "plane" and ev["pos"] == [0, 1]
    assert ev["ell"][:4] == pytest.approx([0.0, 1.0, 4.0, 2.0])
    assert ev["now"] is None and ev["meas"] == {}  # no spec known for this session


def _path(session: str, steps: list[int], indices: list[int], X: np.ndarray, P: np.ndarray,
          seq: int = 5) -> bytes:
    return encode(PredictedPath(session=session, seq=seq, steps=steps, period_ns=PERIOD,
                                t0_ns=EPOCH + steps[0] * PERIOD, indices=indices, X=X, P=P,
                                newest_step=steps[0], made_ns=EPOCH))


def test_path_event_carries_the_page_positions_and_their_band(feed) -> None:
    f, t, out, _ = feed
    names = ["p1", "v1", "p2", "v2"]
    t.put(keys.truth_key("paper"), encode(Truth(session="paper", step=1, t_ns=EPOCH, x=np.zeros(4),
                                                names=names)))
    t.put(keys.prediction_key("paper"), encode(pred("paper", 130, np.arange(4.0), np.eye(4))))
    # components [2, 0] (the page's p1, p2 in another order) and v1
    X = np.array([[9.0, 1.0, 0.1], [9.5, 1.2, 0.2]])
    C = [np.diag([0.09, 0.04, 0.01]), np.diag([0.16, 0.25, 0.01])]
    t.put(keys.path_key("paper"), _path("paper", [125, 130], [2, 0, 1], X,
                                        np.array([c.reshape(-1) for c in C])))
    ev = out[-1]
    assert ev["type"] == "path" and ev["s"] == "paper" and ev["seq"] == 5 and ev["k"] == [125, 130]
    assert ev["p"] == [[1.0, 9.0], [1.2, 9.5]]  # page order: p1, p2
    np.testing.assert_allclose(ev["sd"], [[0.2, 0.3], [0.5, 0.4]], rtol=1e-12)
    assert ev["ell"] is None and ev["i"] == 2
    # a path without p2: counted, not drawn
    t.put(keys.path_key("paper"), _path("paper", [125], [0], np.array([[1.0]]), np.array([[1.0]])))
    assert out[-1] is ev and f.views["paper"].paths_unshown == 1
    assert json.loads(f.tick())["sessions"]["paper"]["paths_unshown"] == 1


def test_planar_path_event_has_an_ellipse_per_step(feed) -> None:
    f, t, out, _ = feed
    t.put(keys.truth_key("omni"), encode(Truth(session="omni", step=3, t_ns=EPOCH, x=np.zeros(6),
                                               names=["x", "y", "theta", "vx", "vy", "omega"])))
    t.put(keys.prediction_key("omni"), encode(pred("omni", 5, np.arange(6.0), np.eye(6))))
    P = np.array([[4.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 1.0]])
    t.put(keys.path_key("omni"), _path("omni", [3, 5], [0, 1], np.array([[0.0, 1.0], [0.5, 1.5]]), P))
    ev = out[-1]
    assert ev["type"] == "path" and len(ev["ell"]) == 2
    assert ev["ell"][0][:4] == pytest.approx([0.0, 1.0, 4.0, 2.0])
    assert ev["ell"][1][:4] == pytest.approx([0.5, 1.5, 2.0, 2.0])


def test_frame_event_registers_the_ghost_in_the_frames_own_view(feed) -> None:
    """The ghost is the newest prediction's pose, projected with the frame's capture-time
    view (its centre and scale): u = w/2 + s (x - cx), v = h/2 - s (y - cy)."""
    from pd_client.tools.camera_view import outline, render

    f, t, out, clock = feed
    f._view("omni").spec = get_scenario("omni").spec("omni", EPOCH).model_copy(
        update={"period_ns": PERIOD})
    names = ["x", "y", "theta", "vx", "vy", "omega"]
    t.put(keys.truth_key("omni"), encode(Truth(session="omni", step=3, t_ns=EPOCH, x=np.zeros(6),
                                               names=names)))
    # a frame before any prediction: no ghost
    t.put(keys.camera_key("omni"), encode(render("omni", 0, EPOCH, 1.0, 2.0, 0.0)))
    assert out[-1]["type"] == "frame" and out[-1]["ghost"] is None and "i" not in out[-1]
    x = np.array([1.5, 1.75, 0.3, 0.0, 0.0, 0.0])
    P = np.eye(6) * 0.01
    P[0, 0] = 0.04
    t.put(keys.prediction_key("omni"), encode(pred("omni", 130, x, P, seq=9)))
    t.put(keys.path_key("omni"), _path("omni", [120, 130], [0, 1], np.array([[1.0, 2.0], [1.5, 1.75]]),
                                       np.array([[0.01, 0, 0, 0.01], [0.04, 0, 0, 0.01]])))
    frame = render("omni", 1, EPOCH + 110 * PERIOD, 1.0, 2.0, 0.0)  # captured at step 110
    clock.ns = EPOCH + 125 * PERIOD
    t.put(keys.camera_key("omni"), encode(frame))
    ev = out[-1]
    assert ev["type"] == "frame" and ev["seq"] == 1 and ev["k"] == 110.0 and ev["img"] == frame.data
    g = ev["ghost"]
    assert g["seq"] == 9 and g["k"] == 130 and g["pose"] == [1.5, 1.75, 0.3]
    want = [[160 + 40 * (u - 1.0), 120 - 40 * (v - 2.0)] for u, v in outline(1.5, 1.75, 0.3)]
    np.testing.assert_allclose(g["px"], want, rtol=0, atol=1e-9)
    assert g["ell"][:4] == pytest.approx([180.0, 130.0, 16.0, 8.0])
    assert ev["path_px"] == [[160.0, 120.0], [180.0, 130.0]]


def test_frame_event_of_a_perspective_camera(feed) -> None:
    """A frame with a pinhole view: the ghost is the outline projected by the camera at the
    robot's capture pose (CameraFrame.project, checked against OpenCV in tests/wire), the
    ellipse a projected polygon (``ell_px``, ``ell`` null); a predicted pose behind the camera
    gets no ghost and is counted (``ghosts_unshown`` in the tick)."""
    import base64

    from pd_client.tools.camera_view import ellipse_points, outline
    from pd_service.wire.camera import CameraFrame
    from pd_service.wire.pinhole import CameraMount, PinholeView

    f, t, out, clock = feed
    f._view("omni").spec = get_scenario("omni").spec("omni", EPOCH).model_copy(
        update={"period_ns": PERIOD})
    t.put(keys.truth_key("omni"), encode(Truth(session="omni", step=3, t_ns=EPOCH, x=np.zeros(6),
                                               names=["x", "y", "theta", "vx", "vy", "omega"])))
    x = np.array([2.0, 0.5, 0.3, 0.0, 0.0, 0.0])
    P = np.eye(6) * 0.01
    t.put(keys.prediction_key("omni"), encode(pred("omni", 130, x, P, seq=9)))
    view = PinholeView(K=[300.0, 0.0, 160.0, 0.0, 300.0, 120.0, 0.0, 0.0, 1.0],
                       mount=CameraMount(z=1.0, pitch=0.4), body_x=0.0, body_y=0.0, body_yaw=0.0)
    frame = CameraFrame(session="omni", seq=4, t_ns=EPOCH + 110 * PERIOD, format="png",
                        data=base64.b64encode(b"\x89PNG....").decode(), width=320, height=240,
                        pinhole=view)
    t.put(keys.camera_key("omni"), encode(frame))
    ev = out[-1]
    assert ev["type"] == "frame" and ev["fmt"] == "png"
    g = ev["ghost"]
    assert g["ell"] is None and g["seq"] == 9
    assert g["px"] == frame.project(outline(2.0, 0.5, 0.3))
    assert g["ell_px"] == frame.project(np.array(ellipse_points((2.0, 0.5), P[:2, :2])))
    u, v = g["px"][0]
    assert 0 < u < 320 and 120 < v < 240  # ahead and below the horizon, in the image
    # the robot predicted behind the camera: no ghost, counted
    t.put(keys.prediction_key("omni"), encode(pred("omni", 131, -x, P, seq=10)))
    t.put(keys.camera_key("omni"), encode(frame))
    assert out[-1]["type"] == "frame" and out[-1]["ghost"] is None
    assert f._view("omni").ghosts_unshown == 1


def test_bad_payloads_are_counted_not_fatal(feed) -> None:
    f, t, out, _ = feed
    t.put(keys.prediction_key("paper"), b"\x00garbage")
    t.put(keys.sensor_key("paper", "camera"), b"\x93")
    other = pred("other", 1, np.zeros(4), np.eye(4))
    t.put(keys.prediction_key("paper"), encode(other))  # session in the message != key's
    assert out == [] and f.invalid == 3


def test_an_older_owners_predictions_make_no_event(feed) -> None:
    """Two owners of one session (a partition between instances) interleaved on its key:
    the page gets the newest term's predictions only; the others are counted (``st``)."""
    f, t, out, _ = feed
    P = np.diag([0.04, 0.01, 0.09, 0.01])
    for seq, term in ((0, 5), (1, 5), (30, 9), (2, 5), (31, 9), (3, 5)):
        t.put(keys.prediction_key("paper"), encode(pred("paper", 130 + seq % 30, np.zeros(4),
                                                        P, seq=seq, term=term)))
    assert [(e["seq"], e["term"]) for e in out] == [(0, 5), (1, 5), (30, 9), (31, 9)]
    assert out[-1]["st"] == 1 and f.views["paper"].stale_term == 2
    assert json.loads(f.tick())["sessions"]["paper"]["st"] == 2


def test_warnings_when_predictions_stop_and_a_sensor_goes_silent(feed) -> None:
    f, t, out, clock = feed
    t.put(keys.sensor_key("paper", "camera"),
          encode(Measurement(session="paper", sensor="camera", seq=1, step=110, z=np.array([0.9, 8.8]))))
    t.put(keys.prediction_key("paper"), encode(pred("paper", 130, np.zeros(4), np.eye(4))))
    tick = json.loads(f.tick())
    assert tick["sessions"]["paper"]["warn"] == [] and tick["list"] == ["paper"]
    clock.mono += 0.5
    t.put(keys.prediction_key("paper"), encode(pred("paper", 131, np.zeros(4), np.eye(4))))
    clock.mono += 0.8  # camera: 1.3 s without a sample; predictions: 0.8 s
    warn = json.loads(f.tick())["sessions"]["paper"]["warn"]
    assert warn == [["sensor camera silent", pytest.approx(1.3)]]
    clock.mono += 1.0
    warn = json.loads(f.tick())["sessions"]["paper"]["warn"]
    assert warn == [["no prediction", pytest.approx(1.8)], ["sensor camera silent", pytest.approx(2.3)]]


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=5) as r:
        return bytes(r.read())


def test_server_serves_page_events_and_state() -> None:
    bus = InMemoryBus()
    t = bus.transport()
    server = pd_web.WebServer(t, "127.0.0.1", 0, tick_s=0.2).start()
    try:
        html = _get(server.url).decode()
        assert '<script src="app.js">' in html and "http" not in html.split("<body>")[1]
        assert _get(server.url + "app.js").startswith(b"// pd-web page")
        assert b"--bg" in _get(server.url + "style.css")
        assert pd_web.page_weight() == sum(map(len, pd_web.static_files().values())) < 40_000
        # a prediction before the page connects comes in its snapshot, one after it live
        t.put(keys.prediction_key("s1"), encode(pred("s1", 7, np.zeros(2), np.eye(2))))
        events = []
        with urllib.request.urlopen(server.url + "events", timeout=5) as stream:
            assert stream.headers["Content-Type"] == "text/event-stream"
            deadline = time.monotonic() + 5
            sent_live = False
            while time.monotonic() < deadline:
                line = stream.readline().decode().strip()
                if not line.startswith("data: "):
                    continue
                ev = json.loads(line[6:])
                events.append(ev)
                if ev["type"] == "tick" and not sent_live:
                    sent_live = True
                    t.put(keys.prediction_key("s1"), encode(pred("s1", 8, np.ones(2), np.eye(2), seq=1)))
                if ev["type"] == "pred" and ev["k"] == 8:
                    break
        kinds = [e["type"] for e in events]
        assert kinds[0] == "hello" and kinds[1] == "tick"
        preds = [e for e in events if e["type"] == "pred"]
        assert [(e["k"], e["i"]) for e in preds] == [(7, 1), (8, 2)]
        state = json.loads(_get(server.url + "state.json"))
        assert state["sessions"] == {"s1": 2} and state["published"] >= 2
        assert state["max_clients"] == pd_web.MAX_CLIENTS and state["refused"] == 0
        with pytest.raises(urllib.error.HTTPError):
            _get(server.url + "nothing-here")
    finally:
        server.close()


def test_spec_from_a_config_put_and_from_a_query(feed) -> None:
    f, t, out, clock = feed
    spec = get_scenario("maneuver").spec("man", EPOCH)
    t.put(keys.config_key("man"), encode(spec))
    assert f.views["man"].spec == spec
    later = get_scenario("paper").spec("late", EPOCH)
    served = t.queryable(keys.config_key("late"), lambda q: q.reply(keys.config_key("late"), encode(later)))
    t.put(keys.prediction_key("late"), encode(pred("late", 3, np.zeros(4), np.eye(4))))
    assert f.views["late"].spec is None
    f.poll_status(timeout=0.1)
    assert f.views["late"].spec == later
    served.close()
    t.put(keys.config_key("man"), b"junk")
    assert f.invalid == 1 and f.views["man"].spec == spec


def test_a_robot_clock_warning_from_the_daemon_joins_the_session_warnings(feed) -> None:
    from pd_service.wire import ClockStatus, SessionStatus

    f, t, out, clock = feed
    spec = get_scenario("paper").spec("bot", EPOCH).model_copy(update={"robot_clock": "estimated"})
    t.put(keys.config_key("bot"), encode(spec))
    warning = ["robot clock offset jumped"]

    def answer(q) -> None:
        st = SessionStatus(session="bot", instance="a", state="active", now_step=5, published=1,
                           latency_p50_us=1.0, latency_p99_us=2.0,
                           clock=ClockStatus(known=True, offset_ns=10, uncertainty_ns=5,
                                             drift_ppm=0.0, age_s=0.1, steps=1,
                                             warning=warning[0]))
        q.reply(keys.status_key("bot"), encode(st))

    t.queryable(keys.status_key("bot"), answer)
    f.poll_status(timeout=0.1)
    tick = json.loads(f.tick())
    assert "clock: robot clock offset jumped" in [w for w, _ in tick["sessions"]["bot"]["warn"]]
    warning[0] = ""
    f.poll_status(timeout=0.1)
    assert not any("clock" in w for w, _ in json.loads(f.tick())["sessions"]["bot"]["warn"])


# --- serving many pages ----------------------------------------------------------------------

_RECEIVED: dict[int, int] = {}


def _received(sock: socket.socket) -> int:
    return _RECEIVED.get(sock.fileno(), 0)


def _read_events(sock: socket.socket, want: int, timeout: float = 10.0) -> list[bytes]:
    """The ``data:`` payloads of the first ``want`` events on a Server-Sent Events socket."""
    sock.settimeout(timeout)
    chunks: list[bytes] = []
    count = 0
    while count < want:
        chunk = sock.recv(1 << 16)
        assert chunk, "stream closed early"
        chunks.append(chunk)
        count += chunk.count(b"\n\n")
        _RECEIVED[sock.fileno()] = count
    return [e[len(b"data: "):] for e in b"".join(chunks).split(b"\n\n")[:want]]


def test_fanout_batches_once_and_cuts_only_the_page_that_does_not_read() -> None:
    fan = Fanout(max_clients=3, buffer_limit=256 << 10).start()
    pages = [socket.socketpair() for _ in range(2)]
    try:
        for ours, _ in pages:
            assert fan.reserve()
            fan.attach(ours, b"data: first\n\n")
        reader, idle = pages[0][1], pages[1][1]
        idle.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        n, body = 3000, b"x" * 1000
        got: list[bytes] = []
        t = threading.Thread(target=lambda: got.extend(_read_events(reader, n + 1)))
        t.start()
        for i in range(n):
            fan.publish(b'{"i":%d,"pad":"%s"}' % (i, body))
            if i % 100 == 99:  # the reader keeps up (its bytes stay under the limit)
                deadline = time.monotonic() + 10
                while fan.published - _received(reader) > 100 and time.monotonic() < deadline:
                    time.sleep(0.005)
        t.join(20)
        assert got[0] == b"first"
        assert [json.loads(e)["i"] for e in got[1:]] == list(range(n))  # all, in order
        assert fan.published == n and fan.batches < n  # joined into batches, not one per event
        # the idle page's unsent bytes passed the limit: closed, counted, its place given back
        assert fan.cut == 1 and fan.listeners == 1
        idle.settimeout(5)
        while idle.recv(1 << 16):
            pass  # EOF: the fan-out closed it
        assert fan.reserve() and fan.reserve() and not fan.reserve() and fan.refused == 1
    finally:
        fan.close()
        for a, b in pages:
            a.close()
            b.close()


def _events_request(url: str, host: str | None = None) -> socket.socket:
    h, port = url.split("//")[1].rstrip("/").split(":")
    sock = socket.create_connection((h, int(port)), timeout=5)
    sock.sendall(f"GET /events HTTP/1.1\r\nHost: {host or f'{h}:{port}'}\r\n\r\n".encode())
    return sock


def _status_and_body(sock: socket.socket) -> tuple[int, bytes]:
    sock.settimeout(5)
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(4096)
        if not chunk:
            break
        buf += chunk
    head, _, body = buf.partition(b"\r\n\r\n")
    length = [int(h.split(b":")[1]) for h in head.lower().split(b"\r\n") if h.startswith(b"content-length:")]
    while length and len(body) < length[0]:
        body += sock.recv(4096)
    return int(head.split()[1]), body


def test_page_cap_refuses_with_503_and_a_reason() -> None:
    bus = InMemoryBus()
    server = pd_web.WebServer(bus.transport(), "127.0.0.1", 0, max_clients=2).start()
    socks = []
    try:
        for _ in range(2):
            socks.append(_events_request(server.url))
            assert _status_and_body(socks[-1])[0] == 200
        with pytest.raises(urllib.error.HTTPError) as err:
            _get(server.url + "events")
        assert err.value.code == 503
        assert b"2 pages are connected" in err.value.read()
        assert json.loads(_get(server.url + "state.json"))["refused"] == 1
        socks.pop().close()  # a page leaves: its place is free again
        deadline = time.monotonic() + 10
        while server.fanout.listeners != 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        socks.append(_events_request(server.url))
        assert _status_and_body(socks[-1])[0] == 200
    finally:
        for s in socks:
            s.close()
        server.close()


def test_host_header_is_checked_against_dns_rebinding() -> None:
    bus = InMemoryBus()
    server = pd_web.WebServer(bus.transport(), "127.0.0.1", 0, allow_hosts=["Display.Lab"]).start()
    port = server.httpd.server_address[1]
    try:
        for host, status in ((f"evil.example:{port}", 403), ("evil.example", 403),
                             (f"localhost:{port}", 200), (f"127.0.0.1:{port}", 200),
                             ("[::1]:80", 200), (f"display.lab.:{port}", 200)):
            sock = _events_request(server.url, host) if status == 403 else None
            if sock is None:  # a page request with that Host
                sock = socket.create_connection(("127.0.0.1", port), timeout=5)
                sock.sendall(f"GET / HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
            code, body = _status_and_body(sock)
            sock.close()
            assert code == status, (host, code)
            if status == 403:
                assert b"DNS rebinding" in body
        assert server.state()["hosts_refused"] == 2 and server.fanout.listeners == 0
    finally:
        server.close()


@pytest.mark.skipif(shutil.which("ss") is None, reason="needs ss (iproute2) to read the backlog")
def test_listen_backlog_takes_a_burst() -> None:
    bus = InMemoryBus()
    server = pd_web.WebServer(bus.transport(), "127.0.0.1", 0)
    try:
        port = server.httpd.server_address[1]
        out = subprocess.run(["ss", "-ltnH", f"sport = :{port}"], capture_output=True, text=True,
                             check=True).stdout.split()
        assert out[0] == "LISTEN" and int(out[2]) == pd_web.LISTEN_BACKLOG >= 128  # Send-Q
    finally:
        server.close()


def test_a_client_that_leaves_early_logs_one_line(capsys) -> None:
    bus = InMemoryBus()
    server = pd_web.WebServer(bus.transport(), "127.0.0.1", 0)
    server.files["app.js"] = b"//" + b"x" * (16 << 20)  # more than the sockets buffer
    server.start()
    try:
        sock = socket.create_connection(("127.0.0.1", server.httpd.server_address[1]), timeout=5)
        sock.sendall(b"GET /app.js HTTP/1.1\r\nHost: localhost\r\n\r\n")
        assert sock.recv(16)  # the server is writing
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        sock.close()  # a reset, mid-reply
        deadline = time.monotonic() + 10
        err = ""
        while "left before" not in err and time.monotonic() < deadline:
            time.sleep(0.05)
            err += capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "left before its reply was written" in lines[0], err
        assert "Traceback" not in err
    finally:
        server.close()
