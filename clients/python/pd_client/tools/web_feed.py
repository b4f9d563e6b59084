"""What pd-web's page shows, computed on the server: one compact JSON event per prediction.

:class:`LiveFeed` subscribes (wildcards, every session) to the daemon's predictions
(``pd/*/*/prediction``), the measurements it receives (``pd/*/*/sensor/*``, after the downlink),
the operator's commands (``pd/*/*/cmd``) and a simulator's truth (``robot/*/*/truth``), and turns
each prediction into one event for the page (:meth:`FeedSession.event`)::

    {"type": "pred", "i": 17, "s": "paper", "ts": 1.7e12,     # server event id, send time (ms)
     "k": 130, "now": 120, "lead": 10, "period_ms": 50.0,     # target step, session's step now
     "names": ["p1", "v1", "p2", "v2"], "pos": [0, 2],        # state names, position indices
     "layout": "axis" | "plane",                              # p1, p2 on one axis | x, y plane
     "x": [...], "var": [...],                                # mean and diag(P), n values
     "ell": [cx, cy, a, b, angle] | null,                     # plane: 2-sigma ellipse (m, rad)
     "meas": {"camera": {"k": 110, "age_ms": 512.0, "p": {"p1": 3.1, "p2": 9.0}}},
     "truth": {"k": 120, "p": [..positions..]} | null,        # newest truth
     "err": {"k": 120, "e": [..n..]} | null,                  # newest prediction - truth pair
     "delay_ms": {"camera": 503.2},                           # newest measured downlink delay
     "lat_ms": 1.2,                                           # receipt - made_ns
     "c": {"accepted": .., "late": .., "future": .., "refused": ..},
     "cmd": {"k": 131, "u": [0.5]} | null,
     "term": 1830...,                                     # publisher's ownership term
     "st": 0}                                             # older-term predictions dropped

for a session whose spec asks for the predicted path (``pd/*/*/path``, a PredictedPath), one
``path`` event after its prediction, the page's position components only::

    {"type": "path", "i": 18, "s": "paper", "ts": 1.7e12, "seq": 41,   # seq of its prediction
     "k": [120, 121, ..., 130],                               # steps, the target last
     "p": [[..positions..], ...],                             # means, one row per step
     "sd": [[..sigma..], ...],                                # axis: 1-sigma per position
     "ell": [[cx, cy, a, b, angle], ...] | null}              # plane: 2-sigma ellipse per step

(a path that lacks one of the page's position components is counted, ``paths_unshown``, not
drawn); for a robot with a camera (``pd/*/*/camera``, a CameraFrame after the link's delay) a
``frame`` event per frame, with the "ghost": the robot's outline at the newest prediction's
pose (the target step, where the command sent now acts), projected into that frame's own view
(its capture-time centre and scale, or its pinhole camera at the robot's capture-time pose),
and the newest path in it::

    {"type": "frame", "s": "omni", "seq": 12, "t_ns": ..., "k": 101.0,   # capture step
     "age_ms": 612.0, "w": 320, "h": 240, "fmt": "jpeg", "img": "<base64 image>",
     "ghost": {"seq": 41, "k": 121, "pose": [x, y, yaw], "px": [[u, v], ...],   # outline
               "ell": [u, v, a, b, angle] | null,             # 2-sigma, top-down view
               "ell_px": [[u, v], ...] | null} | null,        # 2-sigma, perspective view
     "path_px": [[u, v], ...] | null}

(frames are sent live only, not kept for a late page: they are large); and, twice a second,
a ``tick`` event with the sessions the daemons report and the warnings
(predictions stopped, sensors silent: ``[what, seconds since]`` pairs). A prediction of an
older ownership term than the newest seen for its session (a second owner during a partition
between instances, docs/service.md) makes no event: it is counted (``st``) and dropped
(:class:`pd_service.wire.fence.TermFence`), so the page never shows two owners interleaved.
The 2-sigma ellipse
of the planar position (x, y) with covariance C (2 x 2): semi-axes 2 sqrt(lambda_i) along C's
eigenvectors.
"""

from __future__ import annotations

import json
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from pd_service.transport import Handle, Sample, Transport
from pd_service.wire import Command, Measurement, Prediction, SessionSpec, keys
from pd_service.wire.camera import CameraFrame
from pd_service.wire.fence import TermFence
from pd_service.wire.path import PredictedPath

from .._base import try_decode
from ..admin import Admin
from ..errors import PdClientError
from ..pairing import TruthPairs, prediction_error
from ..truth import Truth

#: Events of one session kept for a page that connects late (or reloads after the run): as
#: many as the page keeps (app.js KEEP).
HISTORY = 200
#: Counters the page shows (from the prediction's counters).
COUNTERS = ("accepted", "late", "future", "refused")
_AXIS_NAME = re.compile(r"^p\d+$")
_PLANES = (("x", "y"), ("px", "py"), ("xi", "eta"))

Json = dict[str, Any]


def position_layout(names: list[str] | None, n: int) -> tuple[str, list[int]]:
    """("axis", indices) for 1-D positions named p1, p2, ... (all on one axis), ("plane",
    [ix, iy]) for a planar robot (x, y / px, py / xi, eta), else ("axis", [0])."""
    if names and len(names) == n:
        for a, b in _PLANES:
            if a in names and b in names:
                return "plane", [names.index(a), names.index(b)]
        axis = [i for i, nm in enumerate(names) if _AXIS_NAME.match(nm)]
        if axis:
            return "axis", axis
    return "axis", [0] if n else []


def ellipse_2sigma(C: np.ndarray) -> tuple[float, float, float]:
    """(a, b, angle): semi-axes (2 sigma, a >= b) and the major axis' angle (rad, from +x) of
    a 2 x 2 covariance. C = V diag(l) V^T, a = 2 sqrt(l_max), b = 2 sqrt(l_min)."""
    S = 0.5 * (C + C.T)
    lam, vec = np.linalg.eigh(S)
    lam = np.maximum(lam, 0.0)
    return (2.0 * math.sqrt(float(lam[1])), 2.0 * math.sqrt(float(lam[0])),
            math.atan2(float(vec[1, 1]), float(vec[0, 1])))


def _num(v: float) -> float | None:
    """A JSON-safe float (NaN / inf -> null)."""
    f = float(v)
    return f if math.isfinite(f) else None


def _vec(a: np.ndarray) -> list[float | None]:
    return [_num(v) for v in np.asarray(a, dtype=float).ravel()]


class FeedSession:
    """Everything known about one session, and its page event per prediction."""

    def __init__(self, name: str, keep: int = 512) -> None:
        self.name = name
        self.spec: SessionSpec | None = None
        self.spec_asked: float | None = None  # monotonic s of the last query for it
        self.names: list[str] | None = None
        self.pairs = TruthPairs(keep)
        self.latest_truth: tuple[int, np.ndarray] | None = None
        self.pair: tuple[int, np.ndarray] | None = None  # (step, prediction - truth)
        self.meas: dict[str, Json] = {}
        self.delay_ms: dict[str, float] = {}
        self.sensor_seen: dict[str, float] = {}  # monotonic s of the newest sample
        self.cmd: Json | None = None
        self.last_pred: float | None = None  # monotonic s
        #: The daemon's robot clock warning (SessionStatus.clock; robot_clock "estimated"
        #: sessions only, polled with the status): "" none.
        self.clock_warning = ""
        self.clock_warning_since = 0.0  # monotonic s at which it was first reported
        self.predictions = 0
        self.stale_term = 0  # predictions of an older ownership term, dropped
        self.history: deque[tuple[int, bytes]] = deque(maxlen=HISTORY)  # (event id, JSON)
        #: The newest prediction's (layout, position indices): what a path event draws.
        self.layout: tuple[str, list[int]] | None = None
        self.paths_unshown = 0
        self.ghosts_unshown = 0
        self.last_prediction: Prediction | None = None
        self.last_path: PredictedPath | None = None

    # --- clock of the session ----------------------------------------------------------

    def step_at(self, t_ns: int) -> float | None:
        """The session's (fractional) step at wall time ``t_ns``, from its spec."""
        if self.spec is None:
            return None
        return (t_ns - self.spec.epoch_ns) / self.spec.period_ns

    def sample_ns(self, m: Measurement) -> int | None:
        if m.t_ns is not None:
            return int(m.t_ns)
        if m.step is not None and self.spec is not None:
            return self.spec.epoch_ns + m.step * self.spec.period_ns
        return None

    # --- inputs -------------------------------------------------------------------------

    def add_truth(self, t: Truth) -> None:
        if t.names and len(t.names) == t.x.shape[0]:
            self.names = list(t.names)
        if self.latest_truth is None or t.step >= self.latest_truth[0]:
            self.latest_truth = (t.step, t.x)
        p = self.pairs.add_truth(t)
        if p is not None:
            self._pair(p, t)

    def _pair(self, p: Prediction, t: Truth) -> None:
        err = prediction_error(p, t)
        if err is not None and (self.pair is None or p.step >= self.pair[0]):
            self.pair = (p.step, err)

    def add_measurement(self, m: Measurement, recv_ns: int, mono: float) -> None:
        self.sensor_seen[m.sensor] = mono
        t_sample = self.sample_ns(m)
        if t_sample is not None:
            self.delay_ms[m.sensor] = (recv_ns - t_sample) / 1e6
        pos = self._measured_positions(m)
        if pos:
            step = m.step
            if step is None and t_sample is not None and self.spec is not None:
                step = round((t_sample - self.spec.epoch_ns) / self.spec.period_ns)
            self.meas[m.sensor] = {"k": step, "t_ns": t_sample, "p": pos}

    def _measured_positions(self, m: Measurement) -> dict[str, float]:
        """Position states a sample measures directly: rows of a linear sensor's H that are
        a unit vector e_i (i a position index), or a 'position' sensor's (xi, eta)."""
        if self.spec is None:
            return {}
        sensor = next((s for s in self.spec.sensors if s.name == m.sensor), None)
        n = self.spec.x0.shape[0]
        names = self.state_names(n)
        layout, pos = position_layout(names, n)
        if sensor is None or m.z.shape[0] != sensor.m:
            return {}
        out: dict[str, float] = {}
        if sensor.kind == "linear" and sensor.H is not None:
            for r, row in enumerate(sensor.H):
                nz = np.flatnonzero(row)
                if len(nz) == 1 and row[nz[0]] == 1.0 and int(nz[0]) in pos:
                    out[names[int(nz[0])]] = float(m.z[r])
        elif sensor.kind == "position" and layout == "plane":
            out[names[pos[0]]], out[names[pos[1]]] = float(m.z[0]), float(m.z[1])
        return {k: v for k, v in out.items() if math.isfinite(v)}

    def add_command(self, c: Command) -> None:
        self.cmd = {"k": c.step, "u": _vec(c.u)}

    def state_names(self, n: int) -> list[str]:
        if self.names is not None and len(self.names) == n:
            return self.names
        return [f"x{i}" for i in range(n)]

    # --- the page's event ---------------------------------------------------------------

    def event(self, p: Prediction, recv_ns: int, now_ns: int, mono: float) -> Json:
        """The page's event for prediction ``p`` (see the module's docstring)."""
        self.last_pred = mono
        self.predictions += 1
        self.last_prediction = p
        t = self.pairs.add_prediction(p)
        if t is not None:
            self._pair(p, t)
        n = p.x.shape[0]
        names = self.state_names(n)
        layout, pos = position_layout(names, n)
        self.layout = (layout, pos)
        ell = None
        if layout == "plane":
            a, b, ang = ellipse_2sigma(p.P[np.ix_(pos, pos)])
            ell = [_num(p.x[pos[0]]), _num(p.x[pos[1]]), _num(a), _num(b), _num(ang)]
        now = self.step_at(now_ns)
        meas = {s: {"k": v["k"], "p": v["p"],
                    "age_ms": None if v["t_ns"] is None else (now_ns - v["t_ns"]) / 1e6}
                for s, v in self.meas.items()}
        lt = self.latest_truth
        return {
            "type": "pred", "s": self.name, "k": p.step, "seq": p.seq,
            "now": None if now is None else math.floor(now),
            "lead": None if self.spec is None else self.spec.lead,
            "period_ms": None if self.spec is None else self.spec.period_ns / 1e6,
            "names": names, "pos": pos, "layout": layout,
            "x": _vec(p.x), "var": _vec(np.diag(p.P)), "ell": ell,
            "meas": meas,
            "truth": None if lt is None or lt[1].shape[0] != n else
            {"k": lt[0], "p": _vec(lt[1][pos])},
            "err": None if self.pair is None else {"k": self.pair[0], "e": _vec(self.pair[1])},
            "delay_ms": dict(self.delay_ms),
            "lat_ms": (recv_ns - p.made_ns) / 1e6,
            "c": {k: int(p.counters.get(k, 0)) for k in COUNTERS},
            "cmd": self.cmd,
            "term": p.term, "st": self.stale_term,
        }

    def path_event(self, path: PredictedPath) -> Json | None:
        """The page's event for ``path`` (module docstring), or None (counted) if it lacks
        one of the page's position components or no prediction set the layout yet."""
        self.last_path = path
        if self.layout is None:
            self.paths_unshown += 1
            return None
        layout, pos = self.layout
        cols = [path.indices.index(i) if i in path.indices else -1 for i in pos]
        if -1 in cols:
            self.paths_unshown += 1
            return None
        k = len(path.steps)
        covs = [path.covariance(i)[np.ix_(cols, cols)] for i in range(k)]
        ell = None
        if layout == "plane":
            ell = []
            for i in range(k):
                a, b, ang = ellipse_2sigma(covs[i])
                ell.append([_num(path.X[i, cols[0]]), _num(path.X[i, cols[1]]), _num(a), _num(b),
                            _num(ang)])
        return {"type": "path", "s": self.name, "seq": path.seq, "k": list(path.steps),
                "p": [_vec(path.X[i, cols]) for i in range(k)],
                "sd": [_vec(np.sqrt(np.maximum(np.diag(c), 0.0))) for c in covs], "ell": ell}

    def frame_event(self, f: CameraFrame, recv_ns: int) -> Json:
        """The page's event for camera frame ``f`` (module docstring): the ghost at the newest
        prediction's pose projected through the frame's own view (``CameraFrame.project``);
        the 2-sigma ellipse as (u, v, a, b, angle) in a top-down view (u = w/2 + scale (x -
        cx), v = h/2 - scale (y - cy): an ellipse stays one, v down negates the angle), as a
        projected polygon ``ell_px`` in a perspective one. No ghost (counted
        ``ghosts_unshown``) when the pose is behind a perspective camera."""
        from .camera_view import ellipse_points, outline_px

        k = self.step_at(f.t_ns)
        ev: Json = {"type": "frame", "s": self.name, "seq": f.seq, "t_ns": f.t_ns, "k": k,
                    "age_ms": (recv_ns - f.t_ns) / 1e6, "w": f.width, "h": f.height,
                    "fmt": f.format, "img": f.data, "ghost": None, "path_px": None}
        p = self.last_prediction
        if p is None or self.layout is None or self.layout[0] != "plane":
            return ev
        ix, iy = self.layout[1]
        names = self.state_names(p.x.shape[0])
        ih = next((names.index(h) for h in ("theta", "yaw") if h in names), None)
        x, y = float(p.x[ix]), float(p.x[iy])
        yaw = float(p.x[ih]) if ih is not None else 0.0
        C = p.P[np.ix_([ix, iy], [ix, iy])]
        px = outline_px(f, x, y, yaw)
        ell_px = f.project(np.array(ellipse_points((x, y), C))) if f.pinhole else None
        if px is None or (f.pinhole is not None and ell_px is None):
            self.ghosts_unshown += 1
            return ev
        ell, centre = None, f.project(np.array([[x, y]]))
        if f.scale is not None and centre is not None:
            a, b, ang = ellipse_2sigma(C)
            ell = [*centre[0], a * f.scale, b * f.scale, -ang]
        ev["ghost"] = {"seq": p.seq, "k": p.step, "pose": [x, y, yaw], "px": px, "ell": ell,
                       "ell_px": ell_px}
        path = self.last_path
        if path is not None and ix in path.indices and iy in path.indices:
            cx, cy = path.indices.index(ix), path.indices.index(iy)
            ev["path_px"] = f.project(path.X[:, [cx, cy]])
        return ev

    def warnings(self, mono: float, stale_s: float
                 ) -> tuple[float | None, dict[str, float], list[tuple[str, float]]]:
        """(seconds since the newest prediction, seconds since each sensor's newest sample,
        warnings as (what, seconds since)). Predictions are stopped after max(stale_s, 3
        publish periods); a sensor is silent after max(stale_s, 3 sample intervals). The page
        writes "<what> for <seconds> s", adding the time since the tick: the ages go on
        counting when the stream is lost."""
        warn: list[tuple[str, float]] = []
        period = 0.0 if self.spec is None else self.spec.period_ns / 1e9
        pred_age = None if self.last_pred is None else mono - self.last_pred
        every = 1 if self.spec is None else self.spec.publish_every
        if pred_age is not None and pred_age > max(stale_s, 3 * every * period):
            warn.append(("no prediction", pred_age))
        sensors = {s.name: s.interval for s in self.spec.sensors} if self.spec else {}
        for s in self.sensor_seen:
            sensors.setdefault(s, 1)
        ages: dict[str, float] = {}
        for s, interval in sensors.items():
            seen = self.sensor_seen.get(s)
            if seen is None:
                continue  # never heard: not "silent", just not (yet) publishing
            ages[s] = mono - seen
            if ages[s] > max(stale_s, 3 * interval * period):
                warn.append((f"sensor {s} silent", ages[s]))
        if self.clock_warning:
            warn.append((self.clock_warning, mono - self.clock_warning_since))
        return pred_age, ages, warn


Sink = Callable[[bytes], None]


class LiveFeed:
    """Zenoh samples of every session -> page events (JSON text) passed to ``sink``.

    Transport callbacks only decode and update the session's view under one lock, then pass
    the event's JSON (bytes) to ``sink`` (which must not block: :class:`.web_fanout.Fanout`
    queues it).
    ``sessions()`` / ``snapshot()`` give a late page what it missed. ``poll_status()`` (call
    it every second or so, not on a transport thread) asks the daemons which sessions they
    run and fetches the specs not yet known.
    """

    def __init__(self, transport: Transport, sink: Sink, *, stale_s: float = 1.0,
                 now_ns: Callable[[], int] = time.time_ns,
                 mono: Callable[[], float] = time.monotonic) -> None:
        self.transport = transport
        self.sink = sink
        self.stale_s = stale_s
        self._now_ns = now_ns
        self._mono = mono
        self.lock = threading.Lock()
        self.views: dict[str, FeedSession] = {}
        self.reported: list[str] = []  # sessions the daemons report
        self.events = 0
        self.invalid = 0
        self.fence = TermFence()
        self.admin = Admin(transport)
        subs: list[tuple[str, Callable[[Sample], None]]] = [
            (keys.ALL_PREDICTIONS, self._on_prediction),
            (keys.ALL_CONFIGS, self._on_config),
            (keys.ALL_SENSORS, self._on_measurement),
            (keys.ALL_COMMANDS, self._on_command),
            (keys.ALL_TRUTHS, self._on_truth),
            (keys.ALL_PATHS, self._on_path),
            (keys.ALL_CAMERAS, self._on_frame),
        ]
        self._handles: list[Handle] = [transport.subscribe(k, cb) for k, cb in subs]

    def _view(self, session: str) -> FeedSession:
        v = self.views.get(session)
        if v is None:
            v = self.views[session] = FeedSession(session)
        return v

    def _session_of(self, sample: Sample) -> str | None:
        if sample.kind != "put":
            return None
        try:
            return keys.parse_key(sample.key).session
        except keys.KeyError_:
            return None

    def _on_prediction(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        p = try_decode(sample, Prediction)
        with self.lock:
            if p is None or p.session != session:
                self.invalid += 1
                return
            if not self.fence.admit(session, p.term):  # an older owner's: counted, not shown
                self._view(session).stale_term += 1
                return
            self._emit(session, self._view(session).event(p, sample.recv_ns, self._now_ns(),
                                                          self._mono()))

    def _emit(self, session: str, ev: Json, keep: bool = True) -> None:
        """Stamp and send one page event (``lock`` held); ``keep``: number it and keep it for
        a late page (the page counts gaps in the numbers: a live-only event has none)."""
        ev["ts"] = self._now_ns() / 1e6
        if keep:
            self.events += 1
            ev["i"] = self.events
        data = json.dumps(ev, separators=(",", ":")).encode()
        if keep:
            self.views[session].history.append((self.events, data))
        self.sink(data)

    def _on_frame(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        f = try_decode(sample, CameraFrame)
        with self.lock:
            if f is None or f.session != session:
                self.invalid += 1
                return
            self._emit(session, self._view(session).frame_event(f, sample.recv_ns), keep=False)

    def _on_path(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        path = try_decode(sample, PredictedPath)
        with self.lock:
            if path is None or path.session != session:
                self.invalid += 1
                return
            ev = self._view(session).path_event(path)
            if ev is not None:
                self._emit(session, ev)

    def _on_config(self, sample: Sample) -> None:
        session = self._session_of(sample)  # a delete (session removed) keeps the last spec
        if session is None:
            return
        spec = try_decode(sample, SessionSpec)
        with self.lock:
            if spec is None or spec.session != session:
                self.invalid += 1
                return
            self._view(session).spec = spec

    def _on_measurement(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        m = try_decode(sample, Measurement)
        with self.lock:
            if m is None or m.session != session:
                self.invalid += 1
                return
            self._view(session).add_measurement(m, sample.recv_ns, self._mono())

    def _on_command(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        c = try_decode(sample, Command)
        with self.lock:
            if c is None or c.session != session:
                self.invalid += 1
                return
            self._view(session).add_command(c)

    def _on_truth(self, sample: Sample) -> None:
        session = self._session_of(sample)
        if session is None:
            return
        t = try_decode(sample, Truth)
        with self.lock:
            if t is None or t.session != session:
                self.invalid += 1
                return
            self._view(session).add_truth(t)

    # --- status, warnings, snapshots ----------------------------------------------------

    def poll_status(self, timeout: float = 0.5) -> None:
        """Sessions the daemons report (ServiceStatus), and the specs of the sessions seen
        that were not put while this feed listened (queried on ``pd/p<k>/<s>/config``: the daemon
        answers them; at most every 10 s per session); for sessions whose robot clock is
        estimated, their SessionStatus: its clock warning (unknown, one-sided, stale, jumped)
        joins the session's warnings."""
        try:
            reported = sorted({s for st in self.admin.service_status(timeout=timeout)
                               for s in st.sessions})
        except PdClientError:
            reported = []
        mono = self._mono()
        with self.lock:
            self.reported = reported
            missing = []
            for s in sorted(set(reported) | set(self.views)):
                v = self._view(s)
                if v.spec is None and (v.spec_asked is None or mono - v.spec_asked >= 10.0):
                    v.spec_asked = mono
                    missing.append(s)
        for s in missing:
            try:
                spec = self.admin.get_spec(s, timeout=timeout)
            except PdClientError:
                spec = None
            if spec is not None:
                with self.lock:
                    self._view(s).spec = spec
        with self.lock:
            clocked = [n for n, v in self.views.items()
                       if v.spec is not None and v.spec.robot_clock == "estimated"]
        for s in clocked:  # the daemon's view of the robot's clock: a warning when unsure
            try:
                st = self.admin.status(s, timeout=timeout)
            except PdClientError:
                continue
            text = ""
            if st.clock is not None and st.clock.warning:
                text = f"clock: {st.clock.warning}"
            with self.lock:
                v = self._view(s)
                if text and not v.clock_warning:
                    v.clock_warning_since = self._mono()
                v.clock_warning = text

    def tick(self) -> bytes:
        """The ``tick`` event's JSON: sessions (reported and seen) and their warnings."""
        mono = self._mono()
        with self.lock:
            out: Json = {}
            for name, v in sorted(self.views.items()):
                pa, ages, warn = v.warnings(mono, self.stale_s)
                out[name] = {"pa": pa, "sa": ages, "warn": warn, "n": v.predictions,
                             "st": v.stale_term, "paths_unshown": v.paths_unshown,
                             "ghosts_unshown": v.ghosts_unshown}
            names = sorted(set(self.reported) | set(self.views))
            ev = {"type": "tick", "ts": self._now_ns() / 1e6, "list": names,
                  "reported": self.reported, "sessions": out, "events": self.events}
            return json.dumps(ev, separators=(",", ":")).encode()

    def snapshot(self) -> list[bytes]:
        """Every session's kept events, oldest first (call with ``lock`` held to pair it
        with registering a listener)."""
        return [t for _, t in sorted(e for v in self.views.values() for e in v.history)]

    def close(self) -> None:
        for h in self._handles:
            h.close()
        self._handles.clear()
        self.admin.close()
