"""The ``pd-ros2`` bridge: ROS 2 topics (rmw_zenoh or zenoh-bridge-ros2dds keys, CDR payloads)
in and out of pd-service's native keys, on any :class:`~pd_service.transport.base.Transport`
(Zenoh in the ``pd-ros2`` process, the in-memory bus in tests).

What it does, per session whose :class:`~pd_service.wire.messages.SessionSpec` has ``ros2``
bindings (learnt from ``pd/*/*/config`` puts and deletes, and from a query of ``pd/*/*/config`` at
start, which the daemon answers with every spec it knows):

- **sensors**: each bound topic's key -> CDR decode of the bound type -> (z, R, header.stamp)
  -> a native ``Measurement`` (``t_ns`` = header.stamp, ``seq`` = the rmw_zenoh attachment's
  sequence number, else the bridge's own counter per sensor) put on ``pd/p<k>/<s>/sensor/<name>``;
- **commands**: Twist -> ``Command(issued_ns = receipt on the bridge's clock)`` (read in the
  transport's callback, not when the worker gets to it: the worker's lag would move the command
  to a later apply step), TwistStamped ->
  ``Command(issued_ns = header.stamp)``, u = (linear.x, angular.z), put on ``pd/p<k>/<s>/cmd``; the
  daemon applies it at step ``floor((issued_ns - epoch_ns) / period_ns) + lead`` (for a
  continuous-time model from exactly ``issued_ns + lead * period_ns``; stamps pass at full
  resolution, docs/protocol.md "When a sample and a command apply");
- **outputs**: each ``Prediction`` on ``pd/p<k>/<s>/prediction`` -> Odometry / PoseWithCovariance-
  Stamped / TFMessage (header.stamp = ``Prediction.t_ns``), CDR, with the rmw_zenoh attachment
  (sequence number per publisher from 1, source timestamp, publisher GID); with the spec's
  ``path``, each ``PredictedPath`` on ``pd/p<k>/<s>/path`` -> nav_msgs/Path on ``path_topic``
  (one PoseStamped per point, stamped with its step's time; no covariance: a Path has none);
- **graph**: rmw_zenoh liveliness tokens (one node, a subscription per bound input, a publisher
  per output) so that ``ros2 node list`` / ``ros2 topic list`` see pd-service;
- **status**: queryable ``pd/@ros2/<instance>/status``, a JSON object of counters.

**Robot role** (``BridgeSettings.role = "robot"``, ``pd-ros2 --role robot``): run beside the
robot, on its clock, for sessions whose spec estimates the robot clock (issue 43). Per session
with a command binding it subscribes to the command topic as it reaches the robot and echoes
each Twist as applied on arrival (a ROS base controller acts on arrival): a ``CommandEcho``
(``seq`` = the rmw_zenoh attachment's sequence number, the one the operator-side bridge gave
its Command; ``applied_ns`` = receipt on this clock) on ``pd/p<k>/<s>/echo``
(``robot/p<k>/<s>/echo`` with ``echo_via_link``, for pd-link to carry down); and it answers
clock probes on ``robot/p<k>/<s>/clock``. It bridges no sensor, command or output: the
operator-side bridge does.

Bad input (not CDR of the bound type, a wrong type or type hash in the key, a bad attachment,
stamp 0, NaN, a covariance that is not PSD, a wrong frame_id) is refused: counted per session
(``refused`` and ``refused_<reason>``, reasons in :data:`REFUSAL_REASONS`) and reported as an
``ErrorReport`` on ``pd/p<k>/<s>/error`` (at most ``error_rate`` per second per session), never a
crash, never another session affected.

Threads: transport callbacks only stamp and append to a bounded inbox (oldest dropped and
counted when full); one worker thread (:meth:`Ros2Bridge.start`) decodes, converts and
publishes. :meth:`Ros2Bridge.attach` + :meth:`Ros2Bridge.drain` do the same on the caller's
thread, for deterministic tests on the in-memory bus.
"""

from __future__ import annotations

import base64
import json
import logging
import re
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Literal, TypeVar, get_args

from pydantic import ValidationError

from pd_service.errors import ConfigError
from pd_service.logs import event
from pd_service.ratelimit import TokenBucket
from pd_service.ros2.attachment import (
    Attachment,
    AttachmentLayout,
    decode_attachment,
    encode_attachment,
)
from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.extract import (
    Calibration,
    extract_calibration,
    extract_command,
    extract_image,
    extract_measurement,
    odometry_from_state,
    path_from_points,
    pose_from_state,
    tf_from_state,
)
from pd_service.ros2.keys import (
    NodeIdentity,
    QoS,
    TopicEndpoint,
    bridge_keyexpr,
    check_namespace,
    dds_type_name,
    fully_qualified_name,
    topic_keyexpr,
)
from pd_service.ros2.messages import MESSAGE_TYPES, RosMessage, decode, encode, type_hash
from pd_service.transport.base import (
    DEFAULT_SENDER_CACHE,
    Handle,
    Publisher,
    Query,
    Sample,
    Transport,
)
from pd_service.wire import (
    Command,
    CommandEcho,
    ErrorReport,
    Measurement,
    Prediction,
    SessionSpec,
    SessionStatus,
    WireError,
    keys,
)
from pd_service.wire import decode as wire_decode
from pd_service.wire import encode as wire_encode
from pd_service.wire.camera import CameraFrame
from pd_service.wire.clock_probe import answer_probe
from pd_service.wire.codec import validation_reason
from pd_service.wire.fence import TermFence
from pd_service.wire.path import PredictedPath
from pd_service.wire.pinhole import PinholeView
from pd_service.wire.ros2 import (
    CameraBinding,
    CommandBinding,
    OutputBinding,
    Ros2Binding,
    TopicBinding,
)

log = logging.getLogger("pd_service.ros2")

KeyFormat = Literal["rmw_zenoh", "bridge_ros2dds"]
#: Why an input was refused; each is a per-session counter ``refused_<reason>``.
Reason = Literal["cdr", "type", "type_hash", "attachment", "stamp", "not_finite", "covariance",
                 "frame", "image", "camera_info", "pose", "invalid"]
REFUSAL_REASONS: tuple[str, ...] = get_args(Reason)

#: QoS announced in the tokens: subscriptions best effort (they match reliable and best-effort
#: publishers alike), publishers reliable (they match every subscription); both volatile,
#: keep last 42 (rmw_zenoh's default depth).
SUBSCRIPTION_QOS = QoS(reliability="best_effort")
PUBLISHER_QOS = QoS()
#: Pose samples kept per session to place the camera at an image's stamp (at 100 Hz: 1.3 s).
POSE_HISTORY = 128
#: The TF topic (absolute: not resolved under the namespace).
TF_TOPIC = "/tf"
_INPUT_NAMES: dict[str, str] = {"commands": "cmd", "camera_frames": "camera",
                                "camera_info": "camera_info"}
_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_JSON = "application/json"


@dataclass(frozen=True)
class BridgeSettings:
    """Settings of one bridge. ``sessions`` None: every session whose spec has ``ros2``
    bindings; ``namespace`` resolves relative topic names (absolute ``/a/b``);
    ``attachment_layout`` is the rmw_zenoh attachment written on outputs (``positional`` for
    Jazzy >= 0.2.4, ``keyed`` for 0.2.0..0.2.3; both are read); ``error_rate`` / ``error_burst``
    bound the ErrorReports per session (per second / burst); ``inbox_size`` bounds the queue
    between the transport callbacks and the worker (messages); ``diagnostics_interval_s``:
    the period of /diagnostics (s; 0: none)."""

    domain_id: int = 0
    namespace: str = "/"
    key_format: KeyFormat = "rmw_zenoh"
    node_name: str = "pd_service"
    sessions: frozenset[str] | None = None
    instance: str = "default"
    attachment_layout: AttachmentLayout = "positional"
    error_rate: float = 20.0
    error_burst: int = 20
    inbox_size: int = 4096
    query_timeout_s: float = 2.0
    #: Samples each native publisher (``pd/p<k>/<s>/sensor/<name>``, ``pd/p<k>/<s>/cmd``) keeps for a
    #: restarted service to read back (``Transport.publisher(key, cache=...)``); 0: none.
    cache: int = DEFAULT_SENDER_CACHE
    #: "operator": the bridge (the default); "robot": echoes and clock probes (module docstring).
    role: Literal["operator", "robot"] = "operator"
    #: Robot role: echo on the robot-side key (``robot/p<k>/<s>/echo``) for pd-link to carry.
    echo_via_link: bool = False
    #: Seconds between two DiagnosticArrays on /diagnostics (0: none); a bound sensor topic
    #: silent for ``silent_s`` is reported (pd_service.ros2.diagnostics).
    diagnostics_interval_s: float = 1.0
    silent_s: float = 2.0

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"ROS domain id {self.domain_id} is outside 0..232")
        try:
            check_namespace(self.namespace)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if self.key_format not in get_args(KeyFormat):
            raise ConfigError(f"key format {self.key_format!r} is not one of {get_args(KeyFormat)}")
        if not _NODE_NAME.match(self.node_name):
            raise ConfigError(f"{self.node_name!r} is not a ROS 2 node name")
        if self.attachment_layout not in ("positional", "keyed"):
            raise ConfigError(f"attachment layout {self.attachment_layout!r} is not "
                              "'positional' or 'keyed'")
        try:
            keys.check_name(self.instance, "instance")
            for s in self.sessions or ():
                keys.check_name(s, "session")
        except keys.KeyError_ as exc:
            raise ConfigError(str(exc)) from None
        if self.role not in ("operator", "robot"):
            raise ConfigError(f"role {self.role!r} is not 'operator' or 'robot'")
        if not (self.diagnostics_interval_s >= 0 and self.silent_s > 0):
            raise ConfigError("diagnostics_interval_s must be >= 0, silent_s > 0")
        if not (self.error_rate > 0 and self.error_burst >= 1 and self.inbox_size >= 1):
            raise ConfigError("error_rate must be > 0, error_burst and inbox_size >= 1")


class _Refusal(Exception):
    def __init__(self, reason: Reason, text: str) -> None:
        super().__init__(text)
        self.reason, self.text = reason, text


def classify(exc: Ros2DecodeError) -> Reason:
    """The refusal reason of an error raised while taking values from a decoded message."""
    text = exc.reason
    if "header.stamp" in text:
        return "stamp"
    if "covariance" in text:
        return "covariance"
    if "not finite" in text or "quaternion" in text:
        return "not_finite"
    if "frame_id" in text:
        return "frame"
    return "invalid"


# ---------------------------------------------------------------------------------------------
# per-session routes
# ---------------------------------------------------------------------------------------------


#: What a subscribed ROS topic feeds: a sensor, the commands, the camera's images or its
#: calibration (the prefix of its ``<role>_received`` / ``_forwarded`` counters).
Role = Literal["sensor", "commands", "camera_frames", "camera_info"]


@dataclass(eq=False)
class _Input:
    """One subscribed ROS topic of ``msg_type``: a sensor (``sensor`` set), the commands, the
    camera's images or its CameraInfo (``role``)."""

    session: _Session
    sensor: str | None
    binding: TopicBinding | CommandBinding | CameraBinding
    msg_type: str
    role: Role
    topic: str  # fully qualified
    keyexpr: str  # what is subscribed (wildcards on type and hash for rmw_zenoh)
    native_key: str  # where the native message goes
    dds_type: str | None  # expected type chunk (rmw_zenoh), None: not in the key
    type_hash: str | None
    handle: Handle | None = None
    token: Handle | None = None
    endpoint: TopicEndpoint | None = None
    seq: int = 0
    publisher: Publisher | None = None  # on native_key, with the bridge's cache
    last_ns: int | None = None  # the last message's arrival (bridge's clock), for diagnostics


@dataclass(eq=False)
class _Output:
    """One ROS publisher of the predicted state."""

    what: Literal["odom", "pose", "tf", "path"]
    msg_type: str
    topic: str
    key: str
    publisher: Publisher
    gid: bytes | None
    token: Handle | None = None
    endpoint: TopicEndpoint | None = None
    seq: int = 0


@dataclass(eq=False)
class _Session:
    name: str
    spec: SessionSpec
    binding: Ros2Binding
    limiter: TokenBucket
    counters: Counter[str] = field(default_factory=Counter)
    inputs: list[_Input] = field(default_factory=list)
    outputs: list[_Output] = field(default_factory=list)
    prediction_handle: Handle | None = None
    probe_handle: Handle | None = None
    path_handle: Handle | None = None
    closed: bool = False
    #: Newest ownership term seen (predictions of an older one: a second owner, dropped).
    fence: TermFence = field(default_factory=TermFence)
    #: The camera's newest CameraInfo, and the pose sensor's newest samples (stamp, x, y, yaw).
    calibration: Calibration | None = None
    poses: deque[tuple[int, float, float, float]] = field(
        default_factory=lambda: deque(maxlen=POSE_HISTORY))
    frames: int = 0


#: A message type of the daemon's outputs (Prediction, PredictedPath).
M = TypeVar("M", Prediction, PredictedPath)

_Item = tuple[Literal["config", "input", "prediction", "path"], object, Sample]


class Ros2Bridge:
    """ROS 2 <-> pd-service bridge over ``transport`` (see the module docstring).

    ``now_ns``: the shared wall clock (ns since the epoch) for a Twist's receipt (read in the
    transport callback), the
    attachment's source timestamp and ErrorReport times. Thread model: transport callbacks
    from any thread (append only); the worker (or :meth:`drain`) processes under ``lock``;
    the status queryable takes ``lock`` to read the counters.
    """

    def __init__(self, transport: Transport, settings: BridgeSettings | None = None, *,
                 now_ns: Callable[[], int] = time.time_ns) -> None:
        self.t = transport
        self.settings = settings or BridgeSettings()
        self.now_ns = now_ns
        self.lock = threading.RLock()
        self.sessions: dict[str, _Session] = {}
        #: Bridge-wide counters (configs, inbox drops, ...).
        self.counters: Counter[str] = Counter()
        self._inbox: deque[_Item] = deque(maxlen=self.settings.inbox_size)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._diag_thread: threading.Thread | None = None
        self._diag_publisher: Publisher | None = None
        self._diag_prev: dict[str, SessionStatus] = {}
        self._handles: list[Handle] = []
        self._node_token: Handle | None = None
        self._next_entity = 1  # node id 0; entity ids never reused
        self.node: NodeIdentity | None = None
        self._closed = False
        for msg_type in MESSAGE_TYPES:  # build the typestore and the hashes now, not per message
            type_hash(msg_type)

    @property
    def rmw(self) -> bool:
        """True for rmw_zenoh keys, tokens and attachments."""
        return self.settings.key_format == "rmw_zenoh"

    # ===================================================================== lifecycle ======

    def attach(self) -> None:
        """Declare everything and load the current specs, without a worker thread (tests then
        call :meth:`drain`)."""
        s, t = self.settings, self.t
        if self.rmw:
            self.node = NodeIdentity(domain_id=s.domain_id, session_id=t.session_id(), node_id=0,
                                     name=s.node_name, namespace=s.namespace)
            self._node_token = t.declare_token(self.node.token())
        self._handles.append(t.subscribe(keys.ALL_CONFIGS, self._on_config))
        self._handles.append(t.queryable(keys.ros2_status_key(s.instance), self._on_status_query))
        replies = t.get(keys.ALL_CONFIGS, timeout=s.query_timeout_s)
        with self.lock:
            for r in replies:
                if r.ok:
                    self._apply_config_payload(r.key, r.payload)
        event(log, "ready", instance=s.instance, key_format=s.key_format, domain_id=s.domain_id,
              namespace=s.namespace, node=s.node_name, zid=t.session_id(),
              sessions=",".join(sorted(self.sessions)))

    def start(self) -> None:
        """:meth:`attach`, then start the worker thread and (``diagnostics_interval_s`` > 0)
        the diagnostics thread."""
        self.attach()
        self._thread = threading.Thread(target=self._run, name="pd-ros2-worker", daemon=True)
        self._thread.start()
        if self.settings.diagnostics_interval_s > 0:
            self._diag_thread = threading.Thread(target=self._diagnostics_loop,
                                                 name="pd-ros2-diagnostics", daemon=True)
            self._diag_thread.start()

    def close(self) -> None:
        """Stop the worker, undeclare every session, the node token and the subscriptions."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self._diag_thread is not None:
            self._diag_thread.join(timeout=5.0)
        for h in reversed(self._handles):
            h.close()
        with self.lock:
            for sess in list(self.sessions.values()):
                self._undeclare(sess)
            self.sessions.clear()
        if self._node_token is not None:
            self._node_token.close()

    def __enter__(self) -> Ros2Bridge:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ================================================================ worker / inbox ======

    def _enqueue(self, item: _Item) -> None:
        # deque(maxlen) drops the oldest item itself; count that (racy by at most a few
        # between callback threads: a counter, not an invariant)
        if len(self._inbox) == self._inbox.maxlen:
            self.counters["inbox_dropped"] += 1
        self._inbox.append(item)
        self._wake.set()

    def drain(self, max_items: int | None = None) -> int:
        """Process queued messages on the caller's thread; returns how many."""
        n = 0
        while max_items is None or n < max_items:
            try:
                kind, route, sample = self._inbox.popleft()
            except IndexError:
                break
            n += 1
            with self.lock:
                try:
                    if kind == "config":
                        self._on_config_item(sample)
                    elif kind == "input":
                        assert isinstance(route, _Input)
                        self._on_input(route, sample)
                    elif kind == "path":
                        assert isinstance(route, _Session)
                        self._on_path(route, sample)
                    else:
                        assert isinstance(route, _Session)
                        self._on_prediction(route, sample)
                except Exception:  # a bug must not stop the bridge: count and log it
                    self.counters["internal_errors"] += 1
                    log.exception("failed to process a %s sample on %s", kind, sample.key)
        return n

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            while self.drain(1024):
                if self._stop.is_set():
                    return

    # ======================================================================= configs ======

    def _on_config(self, sample: Sample) -> None:
        self._enqueue(("config", None, sample))

    def _on_input_sample(self, inp: _Input, sample: Sample) -> None:
        # recv_ns re-read on the bridge's clock, here: a Twist's issued_ns is its receipt
        self._enqueue(("input", inp, sample._replace(recv_ns=self.now_ns())))

    def _on_prediction_sample(self, sess: _Session, sample: Sample) -> None:
        self._enqueue(("prediction", sess, sample))

    def _on_path_sample(self, sess: _Session, sample: Sample) -> None:
        self._enqueue(("path", sess, sample))

    def _on_config_item(self, sample: Sample) -> None:
        if sample.kind == "delete":
            try:
                name = keys.parse_key(sample.key).session
            except keys.KeyError_:
                return
            sess = self.sessions.pop(name, None)
            if sess is not None:
                self._undeclare(sess)
                event(log, "session_unbridged", session=name, why="config deleted")
            return
        self._apply_config_payload(sample.key, sample.payload)

    def _apply_config_payload(self, key: str, payload: bytes) -> None:
        try:
            spec = wire_decode(payload, SessionSpec)
        except WireError as exc:
            self.counters["configs_invalid"] += 1
            log.debug("invalid SessionSpec on %s: %s", key, exc.reason)
            return
        self.apply_spec(spec)

    def wanted(self, spec: SessionSpec) -> bool:
        """Whether this bridge serves ``spec``: it has ros2 bindings and is selected."""
        chosen = self.settings.sessions
        return spec.ros2 is not None and (chosen is None or spec.session in chosen)

    def apply_spec(self, spec: SessionSpec) -> None:
        """(Re)declare the ROS side of ``spec`` (nothing when its bindings are unchanged);
        undeclare it when the spec no longer has bindings. Call under ``lock``."""
        name = spec.session
        old = self.sessions.get(name)
        if not self.wanted(spec):
            if old is not None:
                del self.sessions[name]
                self._undeclare(old)
                event(log, "session_unbridged", session=name, why="no ros2 bindings")
            return
        assert spec.ros2 is not None
        if old is not None and old.binding == spec.ros2 and old.spec.path == spec.path:
            old.spec = spec
            return
        if old is not None:
            del self.sessions[name]
            self._undeclare(old)
        sess = _Session(name, spec, spec.ros2,
                        TokenBucket(self.settings.error_rate, self.settings.error_burst,
                                    self.now_ns()))
        if old is not None:  # the counters survive a replacement
            sess.counters = old.counters
        try:
            self._declare(sess)
        except Exception as exc:
            self._undeclare(sess)
            self.counters["configs_refused"] += 1
            log.error("cannot bridge session", extra={"fields": {
                "event": "session_refused", "session": name, "error": str(exc)}})
            return
        self.sessions[name] = sess
        self.counters["configs_applied"] += 1
        event(log, "session_bridged", session=name, inputs=len(sess.inputs),
              outputs=",".join(o.topic for o in sess.outputs),
              replaced=old is not None)

    # ==================================================================== declaring =======

    def _entity(self) -> int:
        n, self._next_entity = self._next_entity, self._next_entity + 1
        return n

    def _fq(self, topic: str) -> str:
        return fully_qualified_name(self.settings.namespace, topic)

    def _data_key(self, fq: str, msg_type: str) -> str:
        if self.rmw:
            return topic_keyexpr(self.settings.domain_id, fq, msg_type, type_hash(msg_type))
        return bridge_keyexpr(fq)

    def _declare(self, sess: _Session) -> None:
        b = sess.binding
        if self.settings.role == "robot":
            self._declare_robot_side(sess)
            return
        for sensor, tb in b.sensors.items():
            self._declare_input(sess, sensor, tb, tb.topic, tb.msg_type, "sensor",
                                keys.sensor_key(sess.name, sensor))
        if b.commands is not None:
            self._declare_input(sess, None, b.commands, b.commands.topic, b.commands.msg_type,
                                "commands", keys.command_key(sess.name))
        if b.camera is not None:
            self._declare_input(sess, None, b.camera, b.camera.image_topic,
                                "sensor_msgs/msg/CompressedImage", "camera_frames",
                                keys.camera_key(sess.name))
            self._declare_input(sess, None, b.camera, b.camera.info_topic,
                                "sensor_msgs/msg/CameraInfo", "camera_info", None)
        if b.outputs is not None:
            self._declare_outputs(sess, b.outputs)
            sess.prediction_handle = self.t.subscribe(
                keys.prediction_key(sess.name), partial(self._on_prediction_sample, sess))
            if any(o.what == "path" for o in sess.outputs):
                sess.path_handle = self.t.subscribe(
                    keys.path_key(sess.name), partial(self._on_path_sample, sess))

    def _declare_input(self, sess: _Session, sensor: str | None,
                       binding: TopicBinding | CommandBinding | CameraBinding, topic: str,
                       msg_type: str, role: Role, native_key: str | None) -> None:
        fq = self._fq(topic)
        if self.rmw:
            # wildcards on the type and hash chunks: another type or hash on this topic is
            # refused and counted rather than silently ignored
            keyexpr = f"{self.settings.domain_id}/{fq.strip('/')}/*/*"
            dds, hsh = dds_type_name(msg_type), type_hash(msg_type)
        else:
            keyexpr, dds, hsh = bridge_keyexpr(fq), None, None
        inp = _Input(sess, sensor, binding, msg_type, role, fq, keyexpr, native_key or "", dds,
                     hsh)
        if role in ("sensor", "commands"):  # frames are for live displays: no cache
            inp.publisher = self.t.publisher(inp.native_key, cache=self.settings.cache)
        sess.inputs.append(inp)
        if self.node is not None:
            inp.endpoint = TopicEndpoint(self.node, self._entity(), "MS", fq, msg_type,
                                         type_hash(msg_type), SUBSCRIPTION_QOS)
        inp.handle = self.t.subscribe(keyexpr, partial(self._on_input_sample, inp))
        if inp.endpoint is not None:
            inp.token = self.t.declare_token(inp.endpoint.token())

    def _declare_robot_side(self, sess: _Session) -> None:
        """Robot role: the command topic, echoed; the clock probe queryable."""
        b = sess.binding
        if b.commands is not None:
            key = (keys.robot_echo_key if self.settings.echo_via_link else keys.echo_key)(
                sess.name)
            self._declare_input(sess, None, b.commands, b.commands.topic, b.commands.msg_type,
                                "commands", key)
        sess.probe_handle = self.t.queryable(keys.robot_clock_key(sess.name),
                                             partial(self._on_probe, sess))

    def _on_probe(self, sess: _Session, query: Query) -> None:
        """Robot role, transport thread: answer a ClockProbe with this clock's t2 / t3
        (bad probes refused with an error reply, counted)."""
        t2 = self.now_ns()
        try:
            reply = answer_probe(query.payload, sess.name, t2, self.now_ns())
        except WireError as exc:
            sess.counters["probes_invalid"] += 1  # racy by a few: a counter
            try:
                query.reply_err(f"not a ClockProbe of {sess.name}: {exc.reason}"[:512].encode())
            except Exception:  # the query may be gone
                pass
            return
        try:
            query.reply(keys.robot_clock_key(sess.name), wire_encode(reply))
            sess.counters["probes_answered"] += 1
        except Exception as exc:  # the query may be gone
            log.debug("probe reply failed: %s", exc)

    def _declare_outputs(self, sess: _Session, ob: OutputBinding) -> None:
        wanted: list[tuple[Literal["odom", "pose", "tf", "path"], str, str]] = []
        if ob.odom_topic is not None:
            wanted.append(("odom", "nav_msgs/msg/Odometry", self._fq(ob.odom_topic)))
        if ob.pose_topic is not None:
            wanted.append(("pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                           self._fq(ob.pose_topic)))
        if ob.tf:
            wanted.append(("tf", "tf2_msgs/msg/TFMessage", TF_TOPIC))
        if ob.path_topic is not None and sess.spec.path is not None:
            wanted.append(("path", "nav_msgs/msg/Path", self._fq(ob.path_topic)))
        for what, msg_type, fq in wanted:
            endpoint = None
            if self.node is not None:
                endpoint = TopicEndpoint(self.node, self._entity(), "MP", fq, msg_type,
                                         type_hash(msg_type), PUBLISHER_QOS)
            key = self._data_key(fq, msg_type)
            out = _Output(what, msg_type, fq, key, self.t.publisher(key),
                          endpoint.gid() if endpoint is not None else None, endpoint=endpoint)
            sess.outputs.append(out)
            if endpoint is not None:
                out.token = self.t.declare_token(endpoint.token())

    def _undeclare(self, sess: _Session) -> None:
        sess.closed = True
        handles: list[Handle | None] = [sess.prediction_handle, sess.probe_handle,
                                        sess.path_handle]
        for inp in sess.inputs:
            handles += [inp.handle, inp.token, inp.publisher]
        for out in sess.outputs:
            handles += [out.token, out.publisher]
        for h in handles:
            if h is not None:
                try:
                    h.close()
                except Exception:  # pragma: no cover - transport already closed
                    pass
        sess.inputs.clear()
        sess.outputs.clear()
        sess.prediction_handle = sess.probe_handle = sess.path_handle = None

    # ======================================================================== inputs ======

    def _check_key(self, inp: _Input, key: str) -> None:
        if inp.dds_type is None:
            return
        parts = key.rsplit("/", 2)
        got_type, got_hash = (parts[1], parts[2]) if len(parts) == 3 else ("", "")
        if got_type != inp.dds_type:
            raise _Refusal("type", f"{inp.topic}: type {got_type!r} in the key, the binding is "
                                   f"{inp.msg_type} ({inp.dds_type})")
        if got_hash != inp.type_hash:
            raise _Refusal("type_hash", f"{inp.topic}: type hash {got_hash[:80]!r} in the key is "
                                        f"not {inp.msg_type}'s {inp.type_hash} (Jazzy)")

    def _attachment_seq(self, inp: _Input, attachment: bytes | None) -> int:
        """The attachment's sequence number (>= 0), else the bridge's own count."""
        inp.seq += 1
        if attachment is None:
            return inp.seq
        try:
            att = decode_attachment(attachment)
        except Ros2DecodeError as exc:
            raise _Refusal("attachment", f"{inp.topic}: {exc.reason}") from None
        return att.sequence_number if att.sequence_number >= 0 else inp.seq

    def _decode(self, inp: _Input, payload: bytes) -> RosMessage:
        try:
            return decode(payload, inp.msg_type)
        except Ros2DecodeError as exc:
            raise _Refusal("cdr", f"{inp.topic}: {exc.reason}") from None

    def _on_input(self, inp: _Input, sample: Sample) -> None:
        sess = inp.session
        if sess.closed or sample.kind != "put":
            return
        c = sess.counters
        c["received"] += 1
        c[f"{inp.role}_received"] += 1
        inp.last_ns = self.now_ns()
        seq: int | None = None
        try:
            self._check_key(inp, sample.key)
            seq = self._attachment_seq(inp, sample.attachment)
            msg = self._decode(inp, sample.payload)
            if inp.role == "camera_info":
                sess.calibration = self._calibration(inp, msg)
                c["camera_info_applied"] += 1
                return
            if inp.role == "sensor":
                payload = self._measurement(inp, msg, seq)
            elif inp.role == "commands":
                payload = (self._echo(inp, msg, seq, sample.recv_ns)
                           if self.settings.role == "robot"
                           else self._command(inp, msg, seq, sample.recv_ns))
            else:
                payload = self._frame(inp, msg)
        except _Refusal as r:
            self._refuse(sess, sample.key, r, seq)
            return
        if inp.publisher is not None:
            inp.publisher.put(payload)
        else:
            self.t.put(inp.native_key, payload)
        c["forwarded"] += 1
        c[f"{inp.role}_forwarded"] += 1

    def _measurement(self, inp: _Input, msg: RosMessage, seq: int) -> bytes:
        b = inp.binding
        assert isinstance(b, TopicBinding) and inp.sensor is not None
        try:
            s = extract_measurement(msg, b.fields)
        except Ros2DecodeError as exc:
            raise _Refusal(classify(exc), f"{inp.topic}: {exc.reason}") from None
        if b.frame is not None and s.frame_id != b.frame:
            raise _Refusal("frame", f"{inp.topic}: frame_id {s.frame_id[:64]!r}, the binding "
                                    f"expects {b.frame!r}")
        cam = inp.session.binding.camera
        if cam is not None and cam.pose_sensor == inp.sensor:  # the camera's pose at capture
            z = s.z
            inp.session.poses.append((s.stamp_ns, float(z[b.fields.index("x")]),
                                      float(z[b.fields.index("y")]),
                                      float(z[b.fields.index("yaw")])))
        try:
            m = Measurement(session=inp.session.name, sensor=inp.sensor, seq=seq,
                            t_ns=s.stamp_ns, z=s.z, R=s.R)
        except ValidationError as exc:
            raise _Refusal("invalid", f"{inp.topic}: {validation_reason('Measurement', exc)}") \
                from None
        return wire_encode(m)

    def _command(self, inp: _Input, msg: RosMessage, seq: int, recv_ns: int) -> bytes:
        """A native Command of ``msg``: a TwistStamped's header.stamp, else ``recv_ns`` (its
        receipt on the bridge's clock) as ``issued_ns``."""
        try:
            cmd = extract_command(msg)
        except Ros2DecodeError as exc:
            raise _Refusal(classify(exc), f"{inp.topic}: {exc.reason}") from None
        issued = cmd.stamp_ns if cmd.stamp_ns is not None else recv_ns
        try:
            out = Command(session=inp.session.name, seq=seq, issued_ns=issued, u=cmd.u)
        except ValidationError as exc:
            raise _Refusal("invalid", f"{inp.topic}: {validation_reason('Command', exc)}") \
                from None
        return wire_encode(out)

    @staticmethod
    def _calibration(inp: _Input, msg: RosMessage) -> Calibration:
        try:
            return extract_calibration(msg)  # type: ignore[arg-type]
        except Ros2DecodeError as exc:
            raise _Refusal("camera_info", f"{inp.topic}: {exc.reason}") from None

    def _frame(self, inp: _Input, msg: RosMessage) -> bytes:
        """A CompressedImage -> CameraFrame with its pinhole view: the newest CameraInfo, the
        mount, the pose sample stamped nearest the image (within the tolerance)."""
        sess, cam = inp.session, inp.binding
        assert isinstance(cam, CameraBinding)
        try:
            img = extract_image(msg)  # type: ignore[arg-type]
        except Ros2DecodeError as exc:
            reason = classify(exc)
            raise _Refusal(reason if reason == "stamp" else "image",
                           f"{inp.topic}: {exc.reason}") from None
        cal = sess.calibration
        if cal is None:
            raise _Refusal("camera_info", f"{inp.topic}: no CameraInfo yet on the info topic")
        tol = round(cam.pose_tolerance_ms * 1e6)
        near = min(sess.poses, key=lambda p: abs(p[0] - img.stamp_ns), default=None)
        if near is None or abs(near[0] - img.stamp_ns) > tol:
            raise _Refusal("pose", f"{inp.topic}: no {cam.pose_sensor} sample within "
                                   f"{cam.pose_tolerance_ms:g} ms of the image's stamp")
        sess.frames += 1
        try:
            frame = CameraFrame(
                session=sess.name, seq=sess.frames, t_ns=img.stamp_ns, format=img.format,
                data=base64.b64encode(img.data).decode(), width=cal.width, height=cal.height,
                pinhole=PinholeView(K=cal.K, distortion_model=cal.distortion_model, D=cal.D,
                                    mount=cam.mount, body_x=near[1], body_y=near[2],
                                    body_yaw=near[3]))
        except ValidationError as exc:
            raise _Refusal("invalid", f"{inp.topic}: {validation_reason('CameraFrame', exc)}") \
                from None
        return wire_encode(frame)

    def _echo(self, inp: _Input, msg: RosMessage, seq: int, recv_ns: int) -> bytes:
        """Robot role: the CommandEcho of a Twist applied on arrival (``recv_ns``, this
        clock); a Twist that would not become a Command is refused as the bridge does."""
        try:
            extract_command(msg)
        except Ros2DecodeError as exc:
            raise _Refusal(classify(exc), f"{inp.topic}: {exc.reason}") from None
        inp.session.counters["echoes_sent"] += 1
        return wire_encode(CommandEcho(session=inp.session.name, seq=seq, applied_ns=recv_ns,
                                       sent_ns=self.now_ns()))

    def _refuse(self, sess: _Session, key: str, r: _Refusal, seq: int | None) -> None:
        c = sess.counters
        c["refused"] += 1
        c[f"refused_{r.reason}"] += 1
        now = self.now_ns()
        if log.isEnabledFor(logging.DEBUG):
            event(log, "refused", logging.DEBUG, session=sess.name, key=key, reason=r.reason,
                  detail=r.text)
        if not sess.limiter.allow(now):
            c["error_reports_suppressed"] += 1
            return
        report = ErrorReport(session=sess.name, key=key[:512], seq=seq,
                             reason=f"ros2 {r.reason}: {r.text}"[:1024], t_ns=now)
        self.t.put(keys.error_key(sess.name), wire_encode(report))
        c["error_reports"] += 1

    # ======================================================================= outputs ======

    def _received(self, sess: _Session, sample: Sample, cls: type[M], what: str) -> M | None:
        """The daemon's ``cls`` message of ``sess`` in ``sample``, or None (counted
        ``<what>_invalid``; every put counted ``<what>_received``)."""
        if sess.closed or sample.kind != "put":
            return None
        c = sess.counters
        c[f"{what}_received"] += 1
        try:
            msg = wire_decode(sample.payload, cls)
        except WireError as exc:
            c[f"{what}_invalid"] += 1
            log.debug("invalid %s on %s: %s", cls.__name__, sample.key, exc.reason)
            return None
        if msg.session != sess.name:
            c[f"{what}_invalid"] += 1
            return None
        return msg

    def _on_prediction(self, sess: _Session, sample: Sample) -> None:
        pred = self._received(sess, sample, Prediction, "predictions")
        if pred is None:
            return
        c = sess.counters
        if not sess.fence.admit(pred.session, pred.term):  # an older owner's (a partition)
            c["predictions_stale_term"] += 1
            return
        ob = sess.binding.outputs
        assert ob is not None
        try:
            encoded = [(out, self._output_payload(out, ob, pred)) for out in sess.outputs
                       if out.what != "path"]
        except (ValueError, TypeError) as exc:
            c["output_errors"] += 1
            self._refuse_output(sess, sample.key, pred.seq, str(exc))
            return
        self._publish(sess, encoded)
        c["predictions_republished"] += 1

    def _on_path(self, sess: _Session, sample: Sample) -> None:
        """A PredictedPath -> nav_msgs/Path on the session's path output."""
        path = self._received(sess, sample, PredictedPath, "paths")
        if path is None:
            return
        c = sess.counters
        ob = sess.binding.outputs
        assert ob is not None
        try:
            msg = path_from_points([path.t_ns(i) for i in range(len(path.steps))], path.X,
                                   path.indices, ob.layout, ob.frame_id)
            encoded = [(out, encode(msg, out.msg_type)) for out in sess.outputs
                       if out.what == "path"]
        except (ValueError, TypeError) as exc:
            c["output_errors"] += 1
            self._refuse_output(sess, sample.key, path.seq, str(exc))
            return
        self._publish(sess, encoded)
        c["paths_republished"] += 1

    def _publish(self, sess: _Session, encoded: list[tuple[_Output, bytes]]) -> None:
        """Put each output's payload with its rmw_zenoh attachment."""
        c = sess.counters
        now = self.now_ns()
        for out, payload in encoded:
            out.seq += 1
            att = None
            if out.gid is not None:
                att = encode_attachment(Attachment(out.seq, now, out.gid),
                                        self.settings.attachment_layout)
            out.publisher.put(payload, attachment=att)
            c["outputs_published"] += 1

    @staticmethod
    def _output_payload(out: _Output, ob: OutputBinding, pred: Prediction) -> bytes:
        x, P, layout, t = pred.x, pred.P, ob.layout, pred.t_ns
        msg: RosMessage
        if out.what == "odom":
            msg = odometry_from_state(x, P, layout, t, ob.frame_id, ob.child_frame_id)
        elif out.what == "pose":
            msg = pose_from_state(x, P, layout, t, ob.frame_id)
        else:
            msg = tf_from_state(x, layout, t, ob.frame_id, ob.child_frame_id)
        return encode(msg, out.msg_type)

    def _refuse_output(self, sess: _Session, key: str, seq: int, text: str) -> None:
        now = self.now_ns()
        if not sess.limiter.allow(now):
            sess.counters["error_reports_suppressed"] += 1
            return
        report = ErrorReport(session=sess.name, key=key[:512], seq=seq,
                             reason=f"ros2 output: prediction not publishable: {text}"[:1024],
                             t_ns=now)
        self.t.put(keys.error_key(sess.name), wire_encode(report))
        sess.counters["error_reports"] += 1

    # ======================================================================== status ======

    def tokens(self) -> list[str]:
        """Every liveliness token this bridge declares now (node first)."""
        with self.lock:
            out = [self.node.token()] if self.node is not None else []
            for sess in self.sessions.values():
                eps: Iterable[TopicEndpoint | None] = [i.endpoint for i in sess.inputs]
                eps = [*eps, *(o.endpoint for o in sess.outputs)]
                out += [e.token() for e in eps if e is not None]
            return out

    def status(self) -> dict[str, Any]:
        """The status document (what the queryable answers, as JSON)."""
        with self.lock:
            return {
                "instance": self.settings.instance,
                "key_format": self.settings.key_format,
                "domain_id": self.settings.domain_id,
                "namespace": self.settings.namespace,
                "node": self.settings.node_name,
                "zid": self.t.session_id(),
                "counters": {k: int(v) for k, v in sorted(self.counters.items())},
                "inbox": len(self._inbox),
                "sessions": {
                    name: {
                        "counters": {k: int(v) for k, v in sorted(sess.counters.items())},
                        "inputs": {i.sensor or _INPUT_NAMES[i.role]: {
                            "topic": i.topic, "key": i.keyexpr, "type": i.msg_type}
                                   for i in sess.inputs},
                        "outputs": [{"topic": o.topic, "key": o.key, "type": o.msg_type}
                                    for o in sess.outputs],
                    }
                    for name, sess in sorted(self.sessions.items())
                },
            }

    # =================================================================== diagnostics ======

    def _diagnostics_loop(self) -> None:
        period = self.settings.diagnostics_interval_s
        while not self._stop.wait(period):
            try:
                self.publish_diagnostics()
            except Exception:  # diagnostics must never take the bridge down
                log.exception("diagnostics failed")

    def publish_diagnostics(self) -> bytes:
        """Query the bridged sessions' statuses, publish one DiagnosticArray on
        ``/diagnostics`` (pd_service.ros2.diagnostics) and return its CDR bytes."""
        from pd_service.ros2.diagnostics import (
            DIAGNOSTICS_TOPIC,
            DIAGNOSTICS_TYPE,
            diagnostic_array,
            session_checks,
        )

        with self.lock:
            bridged = [(name, sess.spec, {i.sensor: i.last_ns for i in sess.inputs
                                          if i.sensor is not None})
                       for name, sess in sorted(self.sessions.items())]
        timeout = min(0.5, self.settings.diagnostics_interval_s)
        now = self.now_ns()
        rows = []
        for name, spec, arrivals in bridged:
            cur = None
            for r in self.t.get(keys.status_key(name), timeout=timeout):
                if r.ok:
                    try:
                        cur = wire_decode(r.payload, SessionStatus)
                    except WireError:
                        continue
                    break
            rows.append((name, session_checks(spec, self._diag_prev.get(name), cur, arrivals,
                                              now, self.settings.silent_s)))
            if cur is not None:
                self._diag_prev[name] = cur
        payload = diagnostic_array(now, self.settings.node_name, rows)
        if self._diag_publisher is None:
            fq = DIAGNOSTICS_TOPIC
            key = self._data_key(fq, DIAGNOSTICS_TYPE)
            self._diag_publisher = self.t.publisher(key)
            self._handles.append(self._diag_publisher)
            if self.node is not None:
                endpoint = TopicEndpoint(self.node, self._entity(), "MP", fq, DIAGNOSTICS_TYPE,
                                         type_hash(DIAGNOSTICS_TYPE), PUBLISHER_QOS)
                self._handles.append(self.t.declare_token(endpoint.token()))
        self._diag_publisher.put(payload)
        return payload

    def _on_status_query(self, q: Query) -> None:
        try:
            q.reply(keys.ros2_status_key(self.settings.instance),
                    json.dumps(self.status()).encode(), encoding=_JSON)
        except Exception as exc:  # e.g. the query was dropped meanwhile
            log.debug("status reply failed: %s", exc)



def bridge_metrics(bridge: Ros2Bridge) -> list[Any]:
    """pd-ros2's metric families (``pd-ros2 --metrics``): the bridge's counters, its sessions'
    counters summed over the sessions (per-session detail: the status queryable), the sessions
    bridged and the inbox level."""
    from pd_service.metrics import counters, gauge

    with bridge.lock:
        own = dict(bridge.counters)
        summed: Counter[str] = Counter()
        for sess in bridge.sessions.values():
            summed.update(sess.counters)
        n, inbox = len(bridge.sessions), len(bridge._inbox)
    return [*counters("pd_ros2", own, "Bridge"),
            *counters("pd_ros2_sessions", dict(summed), "Summed over the sessions, session"),
            gauge("pd_ros2_sessions", "Sessions bridged.", n),
            gauge("pd_ros2_inbox", "Items received, not yet handled.", inbox)]
