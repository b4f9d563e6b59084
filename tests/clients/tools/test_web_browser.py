"""pd-web in a real browser: headless Chromium (Debian's ``chromium`` + ``chromium-driver``,
driven by Selenium) loads the page.

1. A short chain over real Zenoh on a free loopback port (daemon, simulated robot, operator,
   and ``pd-web`` itself as a process): the page updates live, the values it shows (read
   from the DOM's data-* attributes) are the daemon's predictions for the same step (this
   test subscribes to ``pd/paper/prediction`` too), pause freezes it, and a warning appears
   when the robot simulator is stopped, and the page keeps its last state when pd-web
   stops. Screenshots: ``out/web/live.png``, ``out/web/warning.png``.
2. Names: a session named ``constructor`` is shown like any other; a name carrying markup
   is written as text.
3. Load: 10 pages and 200 idle connections while 10 sessions publish at 20 Hz each (an
   in-process server on the in-memory bus): every event reaches every page, in order; the
   lag (page receipt - server send) is printed, not asserted.

``make test`` installs chromium and chromium-driver when they are missing and it can (root,
apt-get); otherwise this module skips and says why.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import time
import urllib.request

import numpy as np
import pytest

from pd_client import Admin, Display
from pd_client.tools import pd_web
from pd_service.transport import InMemoryBus
from pd_service.wire import Prediction, decode, encode, keys
from pd_service.wire.path import PredictedPath
from pd_service.wire.truth import Truth

from .test_integration import ROOT, Procs, _open_when_listening, free_port

pytestmark = pytest.mark.integration

CHROMIUM = os.environ.get("PD_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("PD_CHROMEDRIVER", "/usr/bin/chromedriver")
OUT = ROOT.parent / "out" / "web"  # ROOT is tests/


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not (os.path.isfile(p) and os.access(p, os.X_OK))]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed: `make test` installs Debian's chromium "
                    "and chromium-driver with apt-get when run as root (it could not here)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium (a dev dependency) "
                                    "is not installed: pip install -e '.[dev]'")
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                 "--window-size=1400,1000",
                 f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}"):
        opts.add_argument(flag)
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
    driver.set_script_timeout(10)
    yield driver
    driver.quit()


def wait_until(what: str, check, timeout: float = 30.0, every: float = 0.1):
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


READ_VALUES = """
const tb = document.getElementById('values');
return {session: tb.dataset.session || null, k: tb.dataset.k || null, seq: tb.dataset.seq || null,
        rows: Array.from(tb.rows).map((r) => Object.assign({}, r.dataset)),
        warn: document.getElementById('warn').hidden ? '' : document.getElementById('warn').dataset.warn,
        stats: Object.assign({}, document.getElementById('stats').dataset)};
"""


def read(driver) -> dict:
    return driver.execute_script(READ_VALUES)


def silent_age(warn: str) -> float:
    """Seconds of "sensor camera silent for <s> s" in the banner."""
    m = re.search(r"sensor camera silent for ([0-9.]+) s", warn)
    assert m, warn
    return float(m.group(1))


@pytest.fixture
def procs(tmp_path):
    p = Procs(tmp_path)
    yield p
    p.stop_all()


def test_live_chain_in_the_browser(browser, procs, tmp_path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zenoh = ["--connect", endpoint]
    daemon = procs.start("daemon", "-m", "pd_service", "--listen", endpoint,
                         "--state-dir", str(tmp_path / "state"), "--instance", "wtest")
    transport = _open_when_listening(endpoint, daemon)
    try:
        with Admin(transport) as admin:
            admin.wait_for_service(timeout=20)
        port = free_port()
        web = procs.start("web", "-m", "pd_client.tools", "web", "--port", str(port), *zenoh)
        url = f"http://127.0.0.1:{port}/"
        by_seq: dict[int, Prediction] = {}
        display = Display(transport, "paper", truth=True)
        display.on_prediction(lambda p: by_seq.__setitem__(p.seq, p))
        paths: dict[int, PredictedPath] = {}
        transport.subscribe(keys.path_key("paper"), lambda s: (lambda p: paths.__setitem__(
            p.seq, p))(decode(bytes(s.payload), PredictedPath)))
        procs.start("operator", "-m", "pd_client.tools", "operator", *zenoh, "--session", "paper",
                    "--steps", "1200")
        sim = procs.start("sim", "-m", "pd_client.tools", "sim", *zenoh, "--direct",
                          "--create-session", "--session", "paper", "--steps", "1200",
                          "--progress", "0", "--path", "1")
        display.wait(1, timeout=30)

        def page_up() -> bool:
            assert web.poll() is None, procs.log("web")
            try:
                urllib.request.urlopen(url, timeout=1).close()
                return True
            except OSError:
                return False

        wait_until("pd-web to serve", page_up)
        browser.get(url)
        first = wait_until("the page's first prediction", lambda: read(browser)["k"] and read(browser))
        assert first["session"] == "paper"

        # Live: the target step advances, and what the page shows is the daemon's prediction
        # of that seq, value for value (JSON and JS numbers round-trip doubles exactly).
        checked, steps = 0, set()
        deadline = time.monotonic() + 30
        while checked < 8 and time.monotonic() < deadline:
            v = read(browser)
            seq, k = int(v["seq"]), int(v["k"])
            p = wait_until(f"prediction seq {seq} here", lambda s=seq: by_seq.get(s), timeout=5)
            assert p.step == k
            names = [r["name"] for r in v["rows"]]
            assert names == ["p1", "p2"]
            for row, i in zip(v["rows"], (0, 2), strict=True):
                assert float(row["x"]) == p.x[i]
                assert float(row["sd"]) == pytest.approx(np.sqrt(p.P[i, i]), rel=1e-12)
            steps.add(k)
            checked += 1
            time.sleep(0.3)
        assert checked == 8 and len(steps) >= 4, steps  # compared 8 frames over >= 4 steps

        # The predicted path the plan view drew is the daemon's, point for point, and ends at
        # the prediction of the same seq.
        def drawn_path() -> dict | None:
            got = browser.execute_script(
                "return Object.assign({}, document.getElementById('plan').dataset)")
            return got if "pathSeq" in got else None

        for _ in range(5):
            # (between a prediction and its path the view has no path: a stale one is not drawn)
            d = wait_until("a path on the plan view", drawn_path, timeout=5, every=0.02)
            seq = int(d["pathSeq"])
            path = wait_until(f"path seq {seq} here", lambda s=seq: paths.get(s), timeout=5)
            pred = wait_until(f"prediction seq {seq} here", lambda s=seq: by_seq.get(s), timeout=5)
            assert json.loads(d["pathK"]) == path.steps and path.steps[-1] == pred.step
            assert path.indices == [0, 2] and len(path.steps) >= 2
            assert json.loads(d["pathP"]) == path.X.tolist()
            sd = np.sqrt([np.diag(path.covariance(i)) for i in range(len(path.steps))])
            np.testing.assert_allclose(json.loads(d["pathSd"]), sd, rtol=1e-12)
            assert path.X[-1].tolist() == [pred.x[0], pred.x[2]]
            time.sleep(0.2)

        # Truth and a measured (delayed) position reach the page too.
        def with_truth() -> dict | None:
            v = read(browser)
            return v if all(r["truth"] and r["meas"] for r in v["rows"]) else None

        v = wait_until("truth and a measurement on the page", with_truth)
        for r in v["rows"]:
            assert abs(float(r["x"]) - float(r["truth"])) < 3.0  # the prediction tracks the truth
            assert float(r["ageMs"]) >= 0.0
        assert v["warn"] == "" or "camera" not in v["warn"], v["warn"]

        # Pause freezes the view, resume follows again.
        browser.find_element("id", "pause").click()
        k0 = read(browser)["k"]
        time.sleep(0.8)
        assert read(browser)["k"] == k0
        browser.find_element("id", "pause").click()
        wait_until("the view to follow again", lambda: read(browser)["k"] != k0, timeout=10)

        OUT.mkdir(parents=True, exist_ok=True)
        browser.save_screenshot(str(OUT / "live.png"))

        # The robot simulator stops (no close of its session): its sensors go silent.
        sim.send_signal(signal.SIGKILL)
        sim.wait(10)
        v = wait_until("the silent-sensor warning",
                       lambda: (lambda v: v if "sensor camera silent" in v["warn"] else None)(read(browser)),
                       timeout=20)
        assert browser.find_element("id", "warn").is_displayed()
        browser.save_screenshot(str(OUT / "warning.png"))

        # pd-web stops: the page keeps its last state and says the stream is lost; the
        # warning's ages go on counting.
        last_k = read(browser)["k"]
        web.send_signal(signal.SIGTERM)
        assert web.wait(15) == 0, procs.log("web")
        wait_until("the page to notice the end of the stream",
                   lambda: "stream lost" in browser.find_element("id", "conn").text, timeout=15)
        v = read(browser)
        assert v["k"] is not None and int(v["k"]) >= int(last_k) and len(v["rows"]) == 2
        silent = wait_until("a later age", lambda: (lambda a: a if a > silent_age(v["warn"]) else None)(
            silent_age(read(browser)["warn"])), timeout=5)
        assert silent > silent_age(v["warn"])
        print(f"\npd-web live chain: compared {checked} frames (steps {min(steps)}..{max(steps)}); "
              f"warning: {v['warn']!r}; screenshots in {OUT}")
        display.close()
    finally:
        transport.close()


def test_names_like_object_properties_and_markup_are_shown_as_names(browser) -> None:
    """A session named ``constructor`` (valid per protocol.md section 2) is a session like any
    other; a name carrying markup (the wire refuses it; the page must not rely on that) is
    shown as text, never parsed as HTML."""
    from selenium.webdriver.support.ui import Select

    bus = InMemoryBus()
    transport = bus.transport()
    server = pd_web.WebServer(transport, "127.0.0.1", 0).start()
    try:
        browser.get(server.url)
        wait_until("the page to listen", lambda: server.fanout.listeners >= 1, timeout=15)
        names = ["p1", "v1", "p2", "v2"]
        sent = {}
        for s, off in (("constructor", 5.0), ("paper", 1.0)):
            transport.put(keys.truth_key(s), encode(Truth(session=s, step=12, t_ns=0, names=names,
                                                          x=np.array([off, 0.0, off + 1, 0.0]))))
            sent[s] = Prediction(session=s, seq=3, step=12, t_ns=0, x=np.array([off, 0.5, off + 1, 0.25]),
                                 P=np.diag([0.04, 0.01, 0.09, 0.01]), newest_step=2,
                                 made_ns=time.time_ns(), counters={"accepted": 3})
            transport.put(keys.prediction_key(s), encode(sent[s]))
        overview = ("return Array.from(document.getElementById('overview').rows)"
                    ".map((r) => [r.dataset.session, r.cells[1].textContent])")
        rows = wait_until("both sessions in the overview",
                          lambda: (lambda r: r if len(r) == 2 else None)(browser.execute_script(overview)))
        assert rows == [["constructor", "1"], ["paper", "1"]]
        for s in ("constructor", "paper", "constructor"):
            Select(browser.find_element("id", "session")).select_by_value(s)
            v = read(browser)
            assert v["session"] == s and int(v["k"]) == 12
            assert [float(r["x"]) for r in v["rows"]] == [sent[s].x[0], sent[s].x[2]]
            assert [float(r["truth"]) for r in v["rows"]] == [sent[s].x[0], sent[s].x[2] - 0.0]

        markup = "<img src=x onerror=window.pwned=1>"
        browser.execute_script("""onEvent({type: "pred", i: 99, s: arguments[0], ts: Date.now(),
            k: 1, seq: 1, now: 0, lead: 1, period_ms: 50, names: [arguments[0], "v"], pos: [0],
            layout: "axis", x: [1, 2], var: [1, 1], ell: null, meas: {}, truth: null, err: null,
            delay_ms: {}, lat_ms: 1, c: {accepted: 1}, cmd: null});""", markup)
        wait_until("the picker to list it", lambda: browser.execute_script(
            "return Array.from(document.getElementById('session').options)"
            ".some((o) => o.value === arguments[0])",
            markup))
        Select(browser.find_element("id", "session")).select_by_value(markup)
        shown = browser.execute_script("""return {imgs: document.querySelectorAll('img').length,
            pwned: window.pwned === undefined ? null : window.pwned,
            cell: document.getElementById('values').rows[0].cells[0].textContent,
            row: Array.from(document.getElementById('overview').rows).map((r) => r.cells[0].textContent)};""")
        assert shown == {"imgs": 0, "pwned": None, "cell": markup,
                         "row": sorted(["constructor", "paper", markup])}
    finally:
        server.close()


PAGES, IDLE = 10, 200
SESSIONS, RATE_HZ, SECONDS = 10, 20.0, 6.0


def test_pages_keep_up_with_10_sessions_at_20_hz_and_200_idle_connections(browser) -> None:
    """10 pages (tabs; half on 127.0.0.1, half on localhost: a browser opens at most 6
    connections per host) and 200 idle Server-Sent Events connections (they never read) while
    10 sessions publish at 20 Hz. Every event reaches every page, in order; the lag (page
    receipt - server send) of each page is printed, not asserted."""
    bus = InMemoryBus()
    transport = bus.transport()
    server = pd_web.WebServer(transport, "127.0.0.1", 0).start()
    port = server.httpd.server_address[1]
    idle: list[socket.socket] = []
    tabs = [browser.current_window_handle]
    try:
        browser.get(server.url)
        for j in range(1, PAGES):
            browser.switch_to.new_window("tab")
            browser.get(f"http://{'localhost' if j % 2 else '127.0.0.1'}:{port}/")
            tabs.append(browser.current_window_handle)
        browser.switch_to.window(tabs[0])
        wait_until("the pages to listen", lambda: server.fanout.listeners >= PAGES, timeout=30)
        for _ in range(IDLE):
            sock = socket.socket()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # reads nothing: small
            sock.connect(("127.0.0.1", port))
            sock.sendall(b"GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n")
            idle.append(sock)
        wait_until("the idle connections", lambda: server.fanout.listeners >= PAGES + IDLE, timeout=30)
        names = [f"s{i:02d}" for i in range(SESSIONS)]
        P = np.diag([0.04, 0.01, 0.09, 0.01])
        ticks = int(SECONDS * RATE_HZ)
        t0 = time.monotonic()
        for k in range(ticks):
            now = time.time_ns()
            for j, s in enumerate(names):
                x = np.array([0.1 * k, 1.0, 0.1 * k + j, 0.5])
                transport.put(keys.prediction_key(s), encode(Prediction(
                    session=s, seq=k, step=k + 10, t_ns=now, x=x, P=P, newest_step=k,
                    made_ns=now, counters={"accepted": k})))
            delay = t0 + (k + 1) / RATE_HZ - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        sent_s = time.monotonic() - t0
        sent = SESSIONS * ticks
        assert server.feed.events == sent
        page_stats = """const l = stats.lags.slice().sort((a, b) => a - b);
            const q = (p) => (l.length ? l[Math.min(l.length - 1, Math.floor(p * l.length))] : 0);
            return {received: stats.received, gaps: stats.gaps, p50: q(0.5), p95: q(0.95),
                    max: stats.maxLag};"""
        per_page = []
        for h in tabs:
            browser.switch_to.window(h)
            st = wait_until("the page to receive every event", lambda: (
                lambda s: s if s["received"] >= sent else None)(browser.execute_script(page_stats)),
                timeout=30)
            assert st["received"] == sent and st["gaps"] == 0  # none lost, none reordered
            per_page.append(st)
        browser.switch_to.window(tabs[0])
        state = json.loads(urllib.request.urlopen(server.url + "state.json", timeout=5).read())
        assert state["cut"] == 0 and state["listeners"] == PAGES + IDLE
        weight = pd_web.page_weight()
        p95 = sorted(p["p95"] for p in per_page)
        print(f"\npd-web page weight: {weight} bytes (HTML+JS+CSS); {SESSIONS} sessions x "
              f"{RATE_HZ:g} Hz for {sent_s:.1f} s: sent {sent} ({sent / sent_s:.0f}/s) to {PAGES} "
              f"pages + {IDLE} idle connections in {state['batches']} batches; every page received "
              f"all, gaps 0; live page lag p50 {per_page[0]['p50']:.0f} ms, p95 "
              f"{per_page[0]['p95']:.0f} ms, max {per_page[0]['max']:.0f} ms; p95 over the "
              f"{PAGES} pages {p95[0]:.0f}..{p95[-1]:.0f} ms (shared machine)")
        OUT.mkdir(parents=True, exist_ok=True)
        browser.save_screenshot(str(OUT / "load.png"))
    finally:
        for sock in idle:
            sock.close()
        for h in tabs[1:]:
            browser.switch_to.window(h)
            browser.close()
        browser.switch_to.window(tabs[0])
        server.close()


def test_a_page_over_the_cap_says_why(browser) -> None:
    """At the page cap the stream is refused (503): the page says so, with pd-web's reason."""
    bus = InMemoryBus()
    server = pd_web.WebServer(bus.transport(), "127.0.0.1", 0, max_clients=1).start()
    holder = socket.create_connection(("127.0.0.1", server.httpd.server_address[1]), timeout=5)
    try:
        holder.sendall(b"GET /events HTTP/1.1\r\nHost: localhost\r\n\r\n")
        wait_until("the first connection", lambda: server.fanout.listeners == 1, timeout=10)
        browser.get(server.url)
        text = wait_until("the refusal on the page", lambda: (
            lambda t: t if "pages are connected" in t else None)(
            browser.find_element("id", "conn").text), timeout=15)
        assert text.startswith("stream refused: pd-web: 1 pages are connected, its cap")
        assert server.fanout.refused >= 1
    finally:
        holder.close()
        server.close()


@pytest.mark.parametrize("view", ["top", "chase"])
def test_the_ghost_and_the_path_on_the_delayed_frame(browser, tmp_path, view) -> None:
    """The daemon core (in-process, in-memory bus) serves an omni session whose spec asks for
    the path; camera frames captured 12 steps ago (rendered by pd-robot-sim's camera, top-down
    or the perspective chase camera) reach pd-web. On the page's video canvas the ghost is the
    outline at the daemon's newest prediction (the step where the command sent now lands)
    projected with the frame's own capture-time view, and the path is the daemon's path of the
    same seq, pixel for pixel. Screenshots: ``out/web/ghost.png``, ``out/web/ghost-chase.png``."""
    from pd_client.tools.camera_view import outline, render_view
    from pd_service.wire.path import PredictedPath
    from tests.service.helpers import Clock
    from tests.service.test_core import make_core

    from .omni_drive import drive, omni_spec, pose

    bus = InMemoryBus()
    t = bus.transport()
    spec = omni_spec()
    preds: dict[int, Prediction] = {}
    paths: dict[int, PredictedPath] = {}
    t.subscribe(keys.prediction_key("omni"), lambda s: (lambda p: preds.__setitem__(p.seq, p))(
        decode(bytes(s.payload), Prediction)))
    t.subscribe(keys.path_key("omni"), lambda s: (lambda p: paths.__setitem__(p.seq, p))(
        decode(bytes(s.payload), PredictedPath)))
    clock = Clock(-1)
    core = make_core(bus, clock, tmp_path)
    server = pd_web.WebServer(t, "127.0.0.1", 0).start()
    try:
        browser.get(server.url)
        wait_until("the page to listen", lambda: server.fanout.listeners >= 1, timeout=15)
        t.put(keys.config_key("omni"), encode(spec))
        core.run_once()

        def run(k: int) -> None:
            clock.t = spec.time_of(k) + spec.period_ns // 2
            core.run_once()

        drive(t, spec, run, 40, 4, view=view)
        wait_until("the newest frame on the page", lambda: browser.execute_script(
            "return document.getElementById('video').dataset.frameSeq") == "36", timeout=15)
        d = browser.execute_script("return Object.assign({}, document.getElementById('video').dataset)")
        frame = render_view(view, "omni", 36, spec.time_of(24), *pose(24))
        assert int(d["frameTns"]) == frame.t_ns and float(d["frameK"]) == 24.0
        p = preds[int(d["ghostSeq"])]
        # the newest prediction when the frame arrived (at step 36): of step 36 + lead
        assert int(d["ghostK"]) == p.step == 36 + spec.lead
        assert json.loads(d["ghostPose"]) == [p.x[0], p.x[1], p.x[2]]
        want = frame.project(outline(p.x[0], p.x[1], p.x[2]))
        np.testing.assert_allclose(json.loads(d["ghostPx"]), want, rtol=0, atol=1e-9)
        if view == "chase":  # the 2-sigma ellipse: a projected polygon
            from pd_client.tools.camera_view import ellipse_points

            ell = frame.project(np.array(ellipse_points((p.x[0], p.x[1]), p.P[:2, :2])))
            np.testing.assert_allclose(json.loads(d["ghostEll"]), ell, rtol=0, atol=1e-9)
        path = paths[p.seq]
        assert path.steps[-1] == p.step
        np.testing.assert_allclose(json.loads(d["pathPx"]),
                                   frame.project(path.X[:, :2]), rtol=0, atol=1e-9)
        assert browser.find_element("id", "video").is_displayed()
        OUT.mkdir(parents=True, exist_ok=True)
        browser.execute_script("document.getElementById('video-box').scrollIntoView()")
        shot = OUT / ("ghost.png" if view == "top" else f"ghost-{view}.png")
        browser.save_screenshot(str(shot))
        print(f"\nghost ({view}): frame captured at step 24 shown with the prediction of step "
              f"{p.step} (seq {p.seq}); path of {len(path.steps)} points; screenshot {shot}")
    finally:
        server.close()
        core.close()
