"""``pd-viz``: a Foxglove WebSocket server showing pd-service sessions live.

    pd-viz --session paper                  # ws://127.0.0.1:8765, open it in Foxglove
    pd-viz                                  # every session the daemons serve
    pd-viz --session paper --xy 0,2 --port 8766

Built on the official ``foxglove-sdk`` (``pip install 'pd-client[viz]'``); Foxglove desktop
or web (and PlotJuggler's Foxglove WebSocket client) connect to it. Channels per session
``<s>`` (frame ``world``; docs/visualize.md and deploy/foxglove/pd-service-layout.json):

=========================  ====================  ============================================
topic                      schema                content
=========================  ====================  ============================================
/<s>/pose                  foxglove.PoseInFrame  predicted position (x, y) at the target step
/<s>/ellipse               foxglove.SceneUpdate  its 2-sigma ellipse, from P's (x, y) block
/<s>/truth_pose            foxglove.PoseInFrame  the simulator's truth (when published)
/<s>/path_band             foxglove.SceneUpdate  predicted path (spec's ``path``): its (x, y)
                                                 means as a line, a 2-sigma ellipse per point
/<s>/path                  JSON                  the same path: steps, t_ns, x, y, sd_x, sd_y
/<s>/camera                foxglove.CompressedImage  the robot's camera (a CameraFrame, after the
                                                 link's delay), stamped with its capture time
/<s>/camera_info           foxglove.CameraCalibration  its view as a pinhole camera looking down
/<s>/ghost                 foxglove.ImageAnnotations  on that frame: the robot's outline at the
                                                 newest prediction's pose, its 2-sigma ellipse,
                                                 the newest path (pixels of the frame's view)
/<s>/prediction            JSON                  step, x / var / sd per state name, latency
/<s>/error                 JSON                  prediction - truth per state, and / sigma
/<s>/measurement           JSON                  each sensor packet as it arrives, its age
/<s>/command               JSON                  each command as it arrives
/<s>/truth                 JSON                  truth per state name
/<s>/status                JSON                  counters, latency, late / future refusals
/<s>/log                   foxglove.Log          the service's ErrorReports
/<s>/ros2/prediction       ros2msg (cdr)         step, newest_step, latency_ms, x_<i>, sd_<i>
                                                 (state index i): for PlotJuggler
/<s>/ros2/error            ros2msg (cdr)         step, err_<i>, z_<i> (error / sigma)
/<s>/ros2/status           ros2msg (cdr)         accepted, late, future, refused, published,
                                                 latency_ms
=========================  ====================  ============================================

The JSON channels carry a JSON Schema named ``pd_viz.<Channel>`` (typed fields, in the form
Lichtblick's and Foxglove's parsers read; the per-state maps ``x``, ``var``, ``sd``, ``err``,
``z`` are objects of numbers keyed by state name). The ``ros2/*`` channels
(:mod:`.viz_series`) are the numeric series as flat ROS 2 messages, one type per session
(``pd_viz_msgs/msg/<Session>Prediction``, ...) whose per-state fields are numbered by state
index (``x_0``, ``sd_0``, ...: the spec says how many states there are, not their names).
Every channel is made before the server starts (the series from the session's spec), so a
viewer finds them all in the advertisement it gets on connecting; a channel made while a
viewer is connected can be refused to it ("Unknown channel ID": foxglove-sdk 0.30 sends the
advertisement before it registers the channel for that client's subscribe). Only a session
whose spec pd-viz could not read at start gets its series later (when the status poll reads
the spec, else at its first prediction). A channel is never replaced: viewers hold its id.
``newest_step`` is -1 before any measurement.

The position states are ``--xy I,J`` or, from the truth's state names, ``x,y`` /
``p1,p2`` / ``px,py``, else 0 and 1; a heading named ``theta``/``yaw``/``psi``/``heading``
orients the pose. Angles in the JSON channels are radians; times ns; ages ms.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np

from pd_service.transport import Handle, Sample, Transport
from pd_service.wire import (
    Command,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    SessionStatus,
    WireError,
    decode,
    keys,
)
from pd_service.wire.camera import CameraFrame
from pd_service.wire.convert import command_step, measurement_step
from pd_service.wire.path import PredictedPath

from ..admin import Admin
from ..display import Display
from ..errors import PdClientError
from ..pairing import prediction_error
from ..truth import Truth
from . import common
from .camera_view import ellipse_points
from .viz_series import SeriesType, type_name

#: A wire message type a channel decodes.
W = TypeVar("W", Measurement, Command, PredictedPath, CameraFrame)

TOOL = "pd-viz"
FRAME = "world"
#: The camera's frame id, and the height (m) of the pinhole its calibration describes.
CAMERA_FRAME = "camera"
CAMERA_HEIGHT_M = 10.0
DEFAULT_PORT = 8765
_HEADINGS = ("theta", "yaw", "psi", "heading")
_XY_NAMES = (("x", "y"), ("p1", "p2"), ("px", "py"))

log = logging.getLogger("pd_client.viz")

_NUMBERS: dict[str, Any] = {"type": "object", "additionalProperties": {"type": "number"},
                            "description": "one value per state, keyed by state name"}
_INT: dict[str, Any] = {"type": "integer"}
_NUM: dict[str, Any] = {"type": "number"}


def _object(title: str, **props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


#: The JSON channels' schemas (the viewers' form: pd_client.tools.flat_schema).
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "prediction": _object("pd_viz.Prediction", step=_INT, seq=_INT, newest_step=_INT, t_ns=_INT,
                          x=_NUMBERS, var=_NUMBERS, sd=_NUMBERS, latency_ms=_NUM),
    "error": _object("pd_viz.Error", step=_INT, err=_NUMBERS, sd=_NUMBERS, z=_NUMBERS),
    "measurement": _object("pd_viz.Measurement", sensor={"type": "string"}, seq=_INT,
                           z={"type": "array", "items": _NUM}, step=_INT, age_steps=_INT,
                           age_ms=_NUM),
    "command": _object("pd_viz.Command", seq=_INT, u={"type": "array", "items": _NUM}, step=_INT),
    "truth": _object("pd_viz.Truth", step=_INT, x=_NUMBERS),
    "path": _object("pd_viz.Path", seq=_INT, steps={"type": "array", "items": _INT},
                    t_ns={"type": "array", "items": _INT},
                    **{k: {"type": "array", "items": _NUM} for k in ("x", "y", "sd_x", "sd_y")}),
    "status": _object(
        "pd_viz.Status", session={"type": "string"}, state={"type": "string"}, now_step=_INT,
        counters={"type": "object", "additionalProperties": _INT}, late=_INT, future=_INT,
        accepted=_INT, refused=_INT, published=_INT, latency_ms_last=_NUM, latency_ms_p50=_NUM,
        latency_ms_max=_NUM, missed=_INT, term=_INT, stale_term=_INT,
        viewer={"type": "object", "additionalProperties": _INT},
        daemon_latency_us_p50=_NUM, daemon_latency_us_p99=_NUM),
}


def position_indices(n: int, names: Sequence[str] | None,
                     override: tuple[int, int] | None = None) -> tuple[int, int | None]:
    """Indices of the (x, y) position in a state of ``n`` components (y None if n == 1)."""
    if override is not None:
        return override
    if names:
        for a, b in _XY_NAMES:
            if a in names and b in names:
                return names.index(a), names.index(b)
    return 0, (1 if n > 1 else None)


def heading_index(names: Sequence[str] | None) -> int | None:
    for h in _HEADINGS:
        if names and h in names:
            return list(names).index(h)
    return None


def _ts(t_ns: int) -> Any:
    """foxglove Timestamp of a time in ns (exact; None before 1970)."""
    from foxglove.messages import Timestamp

    return Timestamp(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000) if t_ns >= 0 else None


def _named(values: Sequence[float] | np.ndarray, names: Sequence[str]) -> dict[str, float]:
    return {n: float(v) for n, v in zip(names, values, strict=False)}


class SessionView:
    """The Foxglove channels of one session, fed from the transport. Callbacks may run on
    any transport thread; the foxglove channels are thread-safe, the small state is locked."""

    def __init__(self, transport: Transport, session: str, context: Any,
                 xy: tuple[int, int] | None = None, spec: SessionSpec | None = None) -> None:
        import foxglove
        from foxglove.channels import (
            CameraCalibrationChannel,
            CompressedImageChannel,
            ImageAnnotationsChannel,
            LogChannel,
            PoseInFrameChannel,
            SceneUpdateChannel,
        )

        self.session = session
        self.spec = spec
        self.xy = xy
        self.names: list[str] | None = None
        self._lock = threading.Lock()
        self.counts = {"predictions": 0, "measurements": 0, "commands": 0, "truth": 0,
                       "errors": 0, "invalid": 0, "paths": 0, "paths_unshown": 0, "frames": 0,
                       "ghosts_unshown": 0, "series_unshown": 0}
        p = f"/{session}/"
        ctx = {"context": context}
        self.pose = PoseInFrameChannel(p + "pose", **ctx)
        self.ellipse = SceneUpdateChannel(p + "ellipse", **ctx)
        self.truth_pose = PoseInFrameChannel(p + "truth_pose", **ctx)
        self.path_band = SceneUpdateChannel(p + "path_band", **ctx)
        self.camera = CompressedImageChannel(p + "camera", **ctx)
        self.camera_info = CameraCalibrationChannel(p + "camera_info", **ctx)
        self.ghost = ImageAnnotationsChannel(p + "ghost", **ctx)
        self._last_pred: Prediction | None = None
        self._last_path: PredictedPath | None = None
        self.log = LogChannel(p + "log", **ctx)
        self.json = {name: foxglove.Channel(p + name, schema=foxglove.Schema(
            name=f"pd_viz.{name.capitalize()}", encoding="jsonschema",
            data=json.dumps(schema).encode()), message_encoding="json", **ctx)
                     for name, schema in JSON_SCHEMAS.items()}
        self._context = context
        self._series: dict[str, tuple[SeriesType, Any]] = {}  # kind -> (type, channel)
        self._add_series("status", (("accepted", "late", "future", "refused", "published"),
                                    ("latency_ms",)))
        if spec is not None:
            self.add_state_series(spec.n)
        self.display = Display(transport, session, truth=True, errors=False, history=256)
        self.display.on_prediction(self._on_prediction)
        self.display.on_truth(self._on_truth)
        self._handles: list[Handle] = [
            transport.subscribe(keys.sensors_of(session), self._on_sensor),
            transport.subscribe(keys.command_key(session), self._on_command),
            transport.subscribe(keys.error_key(session), self._on_error),
            transport.subscribe(keys.path_key(session), self._on_path),
            transport.subscribe(keys.camera_key(session), self._on_frame),
        ]

    # --- helpers -----------------------------------------------------------------------

    def _state_names(self, n: int) -> list[str]:
        names = self.names
        return list(names) if names and len(names) == n else [f"x{i}" for i in range(n)]

    def _pose(self, x: np.ndarray, t_ns: int) -> Any:
        from foxglove.messages import Pose, PoseInFrame, Quaternion, Vector3

        i, j = position_indices(x.shape[0], self.names, self.xy)
        h = heading_index(self.names)
        yaw = float(x[h]) if h is not None and h < x.shape[0] else 0.0
        return PoseInFrame(
            timestamp=_ts(t_ns),
            frame_id=FRAME,
            pose=Pose(position=Vector3(x=float(x[i]), y=float(x[j]) if j is not None else 0.0,
                                       z=0.0),
                      orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0),
                                             w=math.cos(yaw / 2.0))))

    def _add_series(self, kind: str, fields: tuple[tuple[str, ...], tuple[str, ...]]) -> None:
        """Make the session's ``ros2/<kind>`` channel (ints, floats) unless it exists: once
        advertised, a channel is kept (a viewer holds its id)."""
        import foxglove

        with self._lock:
            if kind in self._series:
                return
            st = SeriesType(type_name(self.session, kind.capitalize()), *fields)
            ch = foxglove.Channel(f"/{self.session}/ros2/{kind}", message_encoding="cdr",
                                  schema=foxglove.Schema(name=st.name, encoding="ros2msg",
                                                         data=st.definition().encode()),
                                  context=self._context)
            self._series[kind] = (st, ch)

    def add_state_series(self, n: int) -> None:
        """Make the ``ros2/prediction`` and ``ros2/error`` channels for a state of ``n``
        components (fields numbered by state index; a later call keeps the first ones)."""
        idx = range(n)
        self._add_series("prediction", (("step", "newest_step"), (
            "latency_ms", *(f"x_{i}" for i in idx), *(f"sd_{i}" for i in idx))))
        self._add_series("error", (("step",), (*(f"err_{i}" for i in idx),
                                               *(f"z_{i}" for i in idx))))

    def _log_series(self, kind: str, n: int, t_ns: int, ints: list[int], floats: list[float],
                    now: int) -> None:
        if kind not in self._series:  # normally made at start, from the spec (module docstring)
            self.add_state_series(n)
        st, ch = self._series[kind]
        if t_ns < 0 or len(floats) != len(st.floats):  # before 1970, or another state size
            with self._lock:
                self.counts["series_unshown"] += 1
            return
        ch.log(st.encode(t_ns, ints, floats), log_time=now)

    def _emit(self, name: str, msg: dict[str, Any], log_ns: int | None = None) -> None:
        self.json[name].log(json.dumps(msg, allow_nan=False, default=float).encode(),
                            log_time=log_ns or time.time_ns())

    def _decoded(self, sample: Sample, cls: type[W]) -> W | None:
        """The ``cls`` message a put carries, or None (a delete; bad bytes: counted
        ``invalid``)."""
        if sample.kind != "put":
            return None
        try:
            return decode(sample.payload, cls)
        except WireError:
            self.counts["invalid"] += 1
            return None

    # --- callbacks -----------------------------------------------------------------------

    def _on_prediction(self, p: Prediction) -> None:
        from foxglove.messages import (
            Color,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            SceneEntity,
            SceneUpdate,
        )

        now = time.time_ns()
        with self._lock:
            self.counts["predictions"] += 1
            self._last_pred = p
        truth = self.display.truth_at(p.step)  # kept by the display before it calls back
        n = p.x.shape[0]
        names = self._state_names(n)
        var = np.diag(p.P)
        self.pose.log(self._pose(p.x, p.t_ns), log_time=now)
        i, j = position_indices(n, self.names, self.xy)
        if j is not None:
            cov = p.P[np.ix_([i, j], [i, j])]
            pts = ellipse_points((float(p.x[i]), float(p.x[j])), cov)
            line = LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=2.0,
                                 scale_invariant=True,
                                 points=[Point3(x=a, y=b, z=0.0) for a, b in pts],
                                 color=Color(r=0.2, g=0.6, b=1.0, a=1.0))
            self.ellipse.log(SceneUpdate(entities=[SceneEntity(
                timestamp=_ts(p.t_ns),
                frame_id=FRAME, id=f"{self.session}-2sigma", lines=[line])]), log_time=now)
        self._emit("prediction", {
            "step": p.step, "seq": p.seq, "newest_step": p.newest_step, "t_ns": p.t_ns,
            "x": _named(p.x, names), "var": _named(var, names),
            "sd": _named(np.sqrt(np.maximum(var, 0.0)), names),
            "latency_ms": (now - p.made_ns) / 1e6}, now)
        self._emit("status", self._status_msg(p, now), now)
        sd = np.sqrt(np.maximum(var, 0.0))
        self._log_series("prediction", n, p.t_ns,
                         [p.step, -1 if p.newest_step is None else p.newest_step],
                         [(now - p.made_ns) / 1e6, *p.x.tolist(), *sd.tolist()], now)
        c = p.counters
        self._log_series("status", n, p.t_ns, [int(c.get(k, 0)) for k in (
            "accepted", "late", "future", "refused", "published")], [(now - p.made_ns) / 1e6], now)
        if truth is not None:
            self._emit_error(p, truth, now)

    def _status_msg(self, p: Prediction, now: int) -> dict[str, Any]:
        st = self.display.stats()
        c = p.counters
        return {"session": self.session, "counters": dict(c),
                "late": c.get("late", 0), "future": c.get("future", 0),
                "accepted": c.get("accepted", 0), "refused": c.get("refused", 0),
                "published": c.get("published", 0),
                "latency_ms_last": (st.latency_us_last or 0.0) / 1e3,
                "latency_ms_p50": (st.latency_us_p50 or 0.0) / 1e3,
                "latency_ms_max": (st.latency_us_max or 0.0) / 1e3,
                "missed": st.missed, "term": st.term, "stale_term": st.stale_term,
                "viewer": dict(self.counts)}

    def _emit_error(self, p: Prediction, t: Truth, now: int) -> None:
        err = prediction_error(p, t)
        if err is None:
            return
        n = p.x.shape[0]
        sd = np.sqrt(np.maximum(np.diag(p.P), 0.0))
        names = self._state_names(n)
        z = np.where(sd > 0, err / np.where(sd > 0, sd, 1.0), 0.0)
        self._emit("error", {"step": p.step, "err": _named(err, names), "sd": _named(sd, names),
                             "z": _named(z, names)}, now)
        self._log_series("error", n, p.t_ns, [p.step], [*err.tolist(), *z.tolist()], now)

    def _on_truth(self, t: Truth) -> None:
        now = time.time_ns()
        with self._lock:
            if self.names is None and t.names and len(t.names) == t.x.shape[0]:
                self.names = list(t.names)
            self.counts["truth"] += 1
        p = self.display.prediction_for(t.step)
        names = self._state_names(t.x.shape[0])
        self.truth_pose.log(self._pose(t.x, t.t_ns), log_time=now)
        self._emit("truth", {"step": t.step, "x": _named(t.x, names)}, now)
        if p is not None:
            self._emit_error(p, t, now)

    def _on_sensor(self, sample: Sample) -> None:
        m = self._decoded(sample, Measurement)
        if m is None:
            return
        self.counts["measurements"] += 1
        msg: dict[str, Any] = {"sensor": m.sensor, "seq": m.seq, "z": [float(v) for v in m.z]}
        spec = self.spec
        if spec is not None:
            s = measurement_step(m, spec)
            msg["step"] = s
            msg["age_steps"] = spec.step_of(sample.recv_ns) - s
            msg["age_ms"] = (sample.recv_ns - (m.t_ns if m.t_ns is not None
                                               else spec.time_of(s))) / 1e6
        self._emit("measurement", msg, sample.recv_ns)

    def _on_command(self, sample: Sample) -> None:
        c = self._decoded(sample, Command)
        if c is None:
            return
        self.counts["commands"] += 1
        msg: dict[str, Any] = {"seq": c.seq, "u": [float(v) for v in c.u]}
        if self.spec is not None:
            msg["step"] = command_step(c, self.spec)
        self._emit("command", msg, sample.recv_ns)

    def _on_path(self, sample: Sample) -> None:
        """A PredictedPath: its (x, y) means as a line and a 2-sigma ellipse per point on
        ``path_band``, and the numbers on ``path``; a path without the (x, y) components is
        counted (``paths_unshown``)."""
        from foxglove.messages import (
            Color,
            LinePrimitive,
            LinePrimitiveLineType,
            Point3,
            SceneEntity,
            SceneUpdate,
        )

        path = self._decoded(sample, PredictedPath)
        if path is None:
            return
        with self._lock:
            self._last_path = path
        names = self.names
        n = len(names) if names else max(path.indices) + 1
        i, j = position_indices(n, names, self.xy)
        if i not in path.indices or j is None or j not in path.indices:
            self.counts["paths_unshown"] += 1
            return
        self.counts["paths"] += 1
        now = time.time_ns()
        a, b = path.indices.index(i), path.indices.index(j)
        xs, ys = path.X[:, a], path.X[:, b]
        covs = [path.covariance(r)[np.ix_([a, b], [a, b])] for r in range(len(path.steps))]
        band = Color(r=0.77, g=0.61, b=1.0, a=0.5)
        lines = [LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=2.0,
                               scale_invariant=True, color=Color(r=0.77, g=0.61, b=1.0, a=1.0),
                               points=[Point3(x=float(x), y=float(y), z=0.0)
                                       for x, y in zip(xs, ys, strict=True)])]
        lines += [LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=1.0,
                                scale_invariant=True, color=band,
                                points=[Point3(x=u, y=v, z=0.0) for u, v in ellipse_points(
                                    (float(x), float(y)), c, segments=24)])
                  for x, y, c in zip(xs, ys, covs, strict=True)]
        t_end = path.t_ns(len(path.steps) - 1)
        self.path_band.log(SceneUpdate(entities=[SceneEntity(
            timestamp=_ts(t_end), frame_id=FRAME, id=f"{self.session}-path", lines=lines)]),
            log_time=now)
        self._emit("path", {
            "seq": path.seq, "steps": list(path.steps),
            "t_ns": [path.t_ns(r) for r in range(len(path.steps))],
            "x": xs.tolist(), "y": ys.tolist(),
            "sd_x": [math.sqrt(max(float(c[0, 0]), 0.0)) for c in covs],
            "sd_y": [math.sqrt(max(float(c[1, 1]), 0.0)) for c in covs]}, now)

    def _on_frame(self, sample: Sample) -> None:
        """A camera frame: the image, its calibration, and the ghost on it (module docstring):
        the outline at the newest prediction's (x, y, heading), in the frame's own view."""
        from foxglove.messages import (
            CameraCalibration,
            Color,
            CompressedImage,
            ImageAnnotations,
            Point2,
            PointsAnnotation,
            PointsAnnotationType,
        )

        from .camera_view import outline_px

        f = self._decoded(sample, CameraFrame)
        if f is None:
            return
        with self._lock:
            self.counts["frames"] += 1
            p, path = self._last_pred, self._last_path
        now, stamp = time.time_ns(), _ts(f.t_ns)
        self.camera.log(CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=f.image(),
                                        format=f.format), log_time=now)
        if f.pinhole is not None:  # the camera's own calibration (unrectified image: P = [K | 0])
            K, model, D = list(f.pinhole.K), f.pinhole.distortion_model, list(f.pinhole.D)
        else:  # a pinhole at CAMERA_HEIGHT_M looking down: f / height = the frame's px per metre
            assert f.scale is not None
            fl = f.scale * CAMERA_HEIGHT_M
            K, model, D = [fl, 0.0, f.width / 2, 0.0, fl, f.height / 2, 0.0, 0.0, 1.0], \
                "plumb_bob", [0.0] * 5
        self.camera_info.log(CameraCalibration(
            timestamp=stamp, frame_id=CAMERA_FRAME, width=f.width, height=f.height,
            distortion_model=model or "plumb_bob", D=D or [0.0] * 5, K=K,
            R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
            P=[*K[0:3], 0.0, *K[3:6], 0.0, *K[6:9], 0.0]), log_time=now)
        if p is None:
            return
        n = p.x.shape[0]
        i, j = position_indices(n, self.names, self.xy)
        if j is None:
            return
        h = heading_index(self.names)
        x, y = float(p.x[i]), float(p.x[j])
        yaw = float(p.x[h]) if h is not None and h < n else 0.0

        def line(kind: Any, pts: Sequence[Sequence[float]], rgba: tuple[float, ...],
                 width: float) -> Any:
            return PointsAnnotation(timestamp=stamp, type=kind, thickness=width,
                                    outline_color=Color(r=rgba[0], g=rgba[1], b=rgba[2],
                                                        a=rgba[3]),
                                    points=[Point2(x=float(u), y=float(v)) for u, v in pts])

        ghost = outline_px(f, x, y, yaw)
        ell = f.project(np.array(ellipse_points((x, y), p.P[np.ix_([i, j], [i, j])])))
        if ghost is None or ell is None:  # the predicted pose is behind the camera
            with self._lock:
                self.counts["ghosts_unshown"] += 1
            return
        marks = [line(PointsAnnotationType.LineLoop, ghost, (0.29, 0.64, 1.0, 1.0), 2.0),
                 line(PointsAnnotationType.LineLoop, ell, (0.29, 0.64, 1.0, 0.6), 1.0)]
        if path is not None and i in path.indices and j in path.indices:
            a, b = path.indices.index(i), path.indices.index(j)
            path_px = f.project(path.X[:, [a, b]])
            if path_px is not None:
                marks.append(line(PointsAnnotationType.LineStrip, path_px,
                                  (0.77, 0.61, 1.0, 1.0), 1.5))
        self.ghost.log(ImageAnnotations(timestamp=stamp, points=marks), log_time=now)

    def _on_error(self, sample: Sample) -> None:
        from foxglove.messages import Log, LogLevel

        try:
            e = decode(sample.payload, ErrorReport)
        except WireError:
            return
        self.counts["errors"] += 1
        self.log.log(Log(timestamp=_ts(e.t_ns), level=LogLevel.Warning,
                         message=f"{e.key}: {e.reason}", name=f"pd-service/{self.session}"),
                     log_time=sample.recv_ns)

    def on_status(self, st: SessionStatus) -> None:
        """The daemon's SessionStatus (queried periodically)."""
        c = st.counters
        self._emit("status", {"session": self.session, "state": st.state,
                              "now_step": st.now_step, "counters": dict(c),
                              "late": c.get("late", 0), "future": c.get("future", 0),
                              "accepted": c.get("accepted", 0), "published": st.published,
                              "daemon_latency_us_p50": st.latency_p50_us,
                              "daemon_latency_us_p99": st.latency_p99_us})

    def close(self) -> None:
        for h in self._handles:
            h.close()
        self._handles.clear()
        self.display.close()


class VizServer:
    """A Foxglove WebSocket server (its own foxglove Context) with one :class:`SessionView`
    per session. ``port`` 0 picks a free port (see :attr:`port`)."""

    def __init__(self, transport: Transport, sessions: Sequence[str], host: str = "127.0.0.1",
                 port: int = DEFAULT_PORT, xy: tuple[int, int] | None = None,
                 status_every: float = 1.0) -> None:
        import foxglove

        self.transport = transport
        self.host = host
        self.context = foxglove.Context()
        self.admin = Admin(transport)
        self.views: dict[str, SessionView] = {}
        for s in sessions:
            spec = self._spec(s)
            self.views[s] = SessionView(transport, s, self.context, xy, spec)
        self.server = foxglove.start_server(name="pd-service", host=host, port=port,
                                            context=self.context)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if status_every > 0:
            self._thread = threading.Thread(target=self._poll, args=(status_every,),
                                            name="pd-viz-status", daemon=True)
            self._thread.start()

    def _spec(self, session: str) -> SessionSpec | None:
        try:
            return self.admin.get_spec(session, timeout=1.0)
        except PdClientError:
            return None

    @property
    def port(self) -> int:
        return int(self.server.port)

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "::") else self.host
        return f"ws://{host}:{self.port}"

    def _poll(self, every: float) -> None:
        while not self._stop.wait(every):
            for s, view in self.views.items():
                if view.spec is None:
                    view.spec = self._spec(s)
                    if view.spec is not None:
                        view.add_state_series(view.spec.n)
                try:
                    view.on_status(self.admin.status(s, timeout=min(every, 1.0)))
                except PdClientError:
                    continue
                except Exception:  # never let a bad reply stop the status channel
                    log.debug("status of %s failed", s, exc_info=True)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for v in self.views.values():
            v.close()
        self.admin.close()
        self.server.stop()


def served_sessions(transport: Transport, timeout: float = 2.0) -> list[str]:
    """Every session the live daemon instances serve."""
    with Admin(transport) as admin:
        return sorted({s for st in admin.service_status(timeout=timeout) for s in st.sessions})


# --- command line ----------------------------------------------------------------------------

def _xy(value: str) -> tuple[int, int]:
    a, _, b = value.partition(",")
    try:
        return int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--xy: expected I,J (two state indices), got {value!r}") from None


def _add_flags(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--session", action="append", metavar="NAME",
                    help="session to show (repeatable; default: all the daemons serve)")
    ap.add_argument("--host", default="127.0.0.1",
                    help="address the WebSocket server binds (default 127.0.0.1)")
    ap.add_argument("--port", type=int, default=DEFAULT_PORT,
                    help=f"WebSocket port (default {DEFAULT_PORT}; 0: any free port)")
    ap.add_argument("--xy", type=_xy, help="state indices of the x, y position, e.g. 0,2")
    ap.add_argument("--status-every", type=float, default=1.0,
                    help="seconds between SessionStatus queries (0: none)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds")


def _main(ap: argparse.ArgumentParser, args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        import foxglove  # noqa: F401
    except ImportError:
        return common.fail(TOOL, "needs foxglove-sdk: pip install 'pd-client[viz]'", 2)
    return common.run_on_transport(TOOL, args, lambda t: _serve(t, args, stop), stop=stop)


def _serve(transport: Transport, args: argparse.Namespace, stop: threading.Event) -> int:
    sessions = args.session or served_sessions(transport)
    if not sessions:
        return common.fail(TOOL, "no session given and none served by a live daemon")
    try:
        for s in sessions:
            keys.check_name(s, "session")
        server = VizServer(transport, sessions, args.host, args.port, args.xy,
                           args.status_every)
    except (keys.KeyError_, PdClientError) as exc:
        return common.fail(TOOL, exc, 2)
    except RuntimeError as exc:  # the port is taken
        return common.fail(TOOL, f"cannot serve on {args.host}:{args.port}: {exc}")
    print(f"{TOOL}: Foxglove WebSocket server on {server.url} "
          f"(sessions: {', '.join(sessions)})", flush=True)
    try:
        stop.wait(args.duration)
    finally:
        server.close()
    return 0


CLI = common.Tool(TOOL, __doc__, _add_flags, _main)
build_parser, main = CLI.build_parser, CLI.main


if __name__ == "__main__":
    sys.exit(main())
