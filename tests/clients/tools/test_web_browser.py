"""pd-web in a real browser: headless Chromium (Debian's ``chromium`` + ``chromium-driver``,
driven by Selenium) loads the page.

1. A short chain over real Zenoh on a free loopback port (daemon, simulated robot, operator,
   and ``pd-web`` itself as a process): the page updates live, the values it shows (read
   from the DOM's data-* attributes) are the daemon's predictions for the same step (this
   test subscribes to ``pd/paper/prediction`` too), pause freezes it, and a warning appears
   when the robot simulator is stopped, and the page keeps its last state when pd-web
   stops. Screenshots: ``out/web/live.png``, ``out/web/warning.png``.
2. Load: 10 sessions at 20 Hz each (an in-process server on the in-memory bus): every event
   reaches the page, in order; the lag (page receipt - server send) is printed, not asserted.

``make test`` installs chromium and chromium-driver when they are missing and it can (root,
apt-get); otherwise this module skips and says why.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
import urllib.request

import numpy as np
import pytest

from pd_client import Admin, Display
from pd_client.tools import pd_web
from pd_service.transport import InMemoryBus
from pd_service.wire import Prediction, encode, keys

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
        procs.start("operator", "-m", "pd_client.tools", "operator", *zenoh, "--session", "paper",
                    "--steps", "1200")
        sim = procs.start("sim", "-m", "pd_client.tools", "sim", *zenoh, "--direct",
                          "--create-session", "--session", "paper", "--steps", "1200",
                          "--progress", "0")
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

        # pd-web stops: the page keeps its last state and says the stream is lost.
        last_k = read(browser)["k"]
        web.send_signal(signal.SIGTERM)
        assert web.wait(15) == 0, procs.log("web")
        wait_until("the page to notice the end of the stream",
                   lambda: "stream lost" in browser.find_element("id", "conn").text, timeout=15)
        v = read(browser)
        assert v["k"] is not None and int(v["k"]) >= int(last_k) and len(v["rows"]) == 2
        print(f"\npd-web live chain: compared {checked} frames (steps {min(steps)}..{max(steps)}); "
              f"warning: {v['warn']!r}; screenshots in {OUT}")
        display.close()
    finally:
        transport.close()


SESSIONS, RATE_HZ, SECONDS = 10, 20.0, 6.0


def test_page_keeps_up_with_10_sessions_at_20_hz(browser) -> None:
    bus = InMemoryBus()
    transport = bus.transport()
    server = pd_web.WebServer(transport, "127.0.0.1", 0).start()
    try:
        browser.get(server.url)
        wait_until("the page to listen", lambda: server.hub.listeners >= 1, timeout=15)
        names = [f"s{i:02d}" for i in range(SESSIONS)]
        P = np.diag([0.04, 0.01, 0.09, 0.01])
        ticks = int(SECONDS * RATE_HZ)
        t0 = time.monotonic()

        def publish() -> None:
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

        pub = threading.Thread(target=publish)
        pub.start()
        pub.join()
        sent_s = time.monotonic() - t0
        sent = SESSIONS * ticks
        assert server.feed.events == sent
        st = wait_until("the page to receive every event",
                        lambda: (lambda s: s if int(s["received"]) >= sent else None)(read(browser)["stats"]),
                        timeout=30)
        assert int(st["received"]) == sent and int(st["gaps"]) == 0  # none lost, none reordered
        assert server.hub.dropped == 0
        state = json.loads(urllib.request.urlopen(server.url + "state.json", timeout=5).read())
        weight = pd_web.page_weight()
        print(f"\npd-web page weight: {weight} bytes (HTML+JS+CSS); "
              f"{SESSIONS} sessions x {RATE_HZ:g} Hz for {sent_s:.1f} s: sent {sent} "
              f"({sent / sent_s:.0f}/s), page received {st['received']}, gaps {st['gaps']}, "
              f"lag p50 {st['lagP50']} ms, p95 {st['lagP95']} ms, max {st['lagMax']} ms; "
              f"listeners {state['listeners']}")
        OUT.mkdir(parents=True, exist_ok=True)
        browser.save_screenshot(str(OUT / "load.png"))
    finally:
        server.close()

