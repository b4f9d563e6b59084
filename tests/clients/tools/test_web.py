"""pd-web without a browser: the per-session events the feed computes (in-memory bus, fake
clocks) and the HTTP server (static files, Server-Sent Events, state)."""

from __future__ import annotations

import json
import math
import time
import urllib.request

import numpy as np
import pytest

from pd_client.tools import pd_web
from pd_client.tools.web_feed import LiveFeed, ellipse_2sigma, position_layout
from pd_client.truth import Truth
from pd_service.scenarios import get_scenario
from pd_service.transport import InMemoryBus
from pd_service.wire import Command, Measurement, Prediction, encode, keys

EPOCH = 1_000_000_000_000
PERIOD = 50_000_000  # ns


class Clock:
    def __init__(self) -> None:
        self.ns = EPOCH + 120 * PERIOD
        self.mono = 100.0


def pred(session: str, step: int, x: np.ndarray, P: np.ndarray, seq: int = 0,
         made_ns: int = EPOCH) -> Prediction:
    return Prediction(session=session, seq=seq, step=step, t_ns=EPOCH + step * PERIOD, x=x, P=P,
                      newest_step=max(0, step - 10), made_ns=made_ns,
                      counters={"accepted": 7, "late": 2, "refused": 3})


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


def test_bad_payloads_are_counted_not_fatal(feed) -> None:
    f, t, out, _ = feed
    t.put(keys.prediction_key("paper"), b"\x00garbage")
    t.put(keys.sensor_key("paper", "camera"), b"\x93")
    other = pred("other", 1, np.zeros(4), np.eye(4))
    t.put(keys.prediction_key("paper"), encode(other))  # session in the message != key's
    assert out == [] and f.invalid == 3


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
    assert warn == ["sensor camera silent for 1.3 s"]
    clock.mono += 1.0
    warn = json.loads(f.tick())["sessions"]["paper"]["warn"]
    assert warn == ["no prediction for 1.8 s", "sensor camera silent for 2.3 s"]


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
    assert "clock: robot clock offset jumped" in tick["sessions"]["bot"]["warn"]
    warning[0] = ""
    f.poll_status(timeout=0.1)
    assert not any("clock" in w for w in json.loads(f.tick())["sessions"]["bot"]["warn"])
