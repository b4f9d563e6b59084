"""MCAP logs of pd-service sessions: what ``pd-record --mcap`` writes and ``pd-replay`` reads.

One MCAP channel per Zenoh key, topic ``/`` + key (``/pd/p<k>/<s>/sensor/<name>``,
``/pd/p<k>/<s>/cmd``, ``/pd/p<k>/<s>/prediction``, ``/pd/p<k>/<s>/path``, ``/pd/p<k>/<s>/error``,
``/pd/p<k>/<s>/status``, ``/pd/p<k>/<s>/config``, ``/robot/p<k>/<s>/truth``,
``/pd/p<k>/<s>/camera`` (CameraFrame, after the link); key layout 2,
protocol.md §3), message encoding ``json`` with the message type's JSON Schema
(``jsonschema`` schema encoding, named for the type: docs/schemas' schemas, from
:func:`pd_service.wire.schemas.schemas`, rewritten by :func:`.flat_schema.flat_schema` into
the form Lichtblick's and Foxglove's parsers read: no ``$ref`` / ``anyOf``, every property
typed; a type that cannot be said so would be written schemaless).

Each message is the payload's msgpack map, unpacked (the wire form: arrays are
``{"shape": [...], "data": [...]}``) and written as JSON. Python writes a float with
``repr``, which reads back as the same float64, and keeps ``1`` and ``1.0`` apart, so
``msgpack.packb(json.loads(data))`` decodes to exactly the numbers the daemon decoded: this
is what makes an exact offline replay possible without storing the msgpack bytes twice.
A camera frame is also written as ``foxglove.CompressedImage`` JSON on
``/pd/p<k>/<s>/camera/image`` (capture stamp, ``frame_id`` ``camera``), so the viewers' Image
panel shows the recorded video (the ghost is the displays' drawing: not recorded; a replay
ignores both). A payload that is not such a map (undecodable bytes, bin fields, NaN/inf, a delete) goes to
``/pd/p<k>/<s>/raw`` as ``{"key", "kind", "payload_b64"}`` so a replay still sees it.

The metadata record ``pd-keys`` holds the key layout and partition count P of the recording;
a log without it is of key layout 1 (``/pd/<s>/...``). Reading re-keys every message into
this process's layout and P, so an older log, or one recorded with another
``PD_PARTITIONS``, replays the same.

Publish time is the recorder's receipt time (wall clock, ns). Log time is the same, raised
to the previous message's log time when a sample written later was received earlier (two
transport threads, or the ROS 2 copies of a prediction written after it): log times never
decrease in the file, the order MCAP readers and players expect. The MCAP ``sequence`` of
each message is its arrival order at the recorder (over all channels).

ROS 2 profile where a ROS message type exists: for a session whose spec binds ROS 2 outputs
(``SessionSpec.ros2.outputs``), every prediction is also written as ``nav_msgs/msg/Odometry``
and ``geometry_msgs/msg/PoseWithCovarianceStamped`` on ``/pd/p<k>/<s>/ros2/odom`` and
``/pd/p<k>/<s>/ros2/pose`` (``cdr`` messages, ``ros2msg`` schemas: the message definitions from the
rosbags Jazzy typestore), the same messages the ``pd-ros2`` bridge publishes, so ROS tools
plot the predicted pose directly. They need the ``ros2`` extra (rosbags); without it they are
left out (said once on stderr). Replay ignores them (the JSON predictions are the record).
"""

from __future__ import annotations

import base64
import json
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import msgpack

from pd_service.transport import Handle, Sample, Transport
from pd_service.wire import Prediction, SessionSpec, WireError, decode, keys
from pd_service.wire.schemas import schemas

from .flat_schema import Inexpressible, flat_schema

#: Stream kind of a key -> message type name (its JSON Schema's title).
TYPE_OF_KIND = {"sensor": "Measurement", "cmd": "Command", "prediction": "Prediction",
                "path": "PredictedPath", "error": "ErrorReport", "status": "SessionStatus",
                "config": "SessionSpec", "truth": "Truth", "camera": "CameraFrame"}
#: The image copy of a camera frame: Foxglove's ``foxglove.CompressedImage`` as JSON (its
#: ``data`` base64, which the viewers' parser decodes by ``contentEncoding``).
IMAGE_TYPE = "foxglove.CompressedImage"
IMAGE_SCHEMA: dict[str, Any] = {
    "title": IMAGE_TYPE, "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"},
                                                       "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"}}}
RAW_SCHEMA: dict[str, Any] = {
    "title": "RawSample", "type": "object",
    "description": "A sample that is not a JSON-representable msgpack map (kept for replay).",
    "properties": {"key": {"type": "string"}, "kind": {"type": "string", "enum": ["put", "delete"]},
                   "payload_b64": {"type": "string"}},
    "required": ["key", "kind", "payload_b64"],
}
_UNPACK: dict[str, Any] = {"raw": False, "strict_map_key": True, "use_list": True}


def json_schemas() -> dict[str, dict[str, Any] | None]:
    """Type name -> the schema its MCAP channels get (None: written schemaless)."""
    out: dict[str, dict[str, Any] | None] = {}
    for name, s in (*((n.removesuffix(".json"), s) for n, s in schemas().items()),
                    ("RawSample", RAW_SCHEMA), (IMAGE_TYPE, IMAGE_SCHEMA)):
        try:
            out[name] = flat_schema(s)
        except Inexpressible:
            out[name] = None
    return out


def topic_of(key: str) -> str:
    return "/" + key


def key_of(topic: str) -> str:
    return topic.removeprefix("/")


#: Name of the metadata record that says which key layout (and P) a log's topics use.
KEYS_METADATA = "pd-keys"


def rekey(key: str, layout: int) -> str:
    """A recorded key (of key ``layout`` 1 or 2, any P) in this process's layout and P:
    the session's partition chunk recomputed. A key that is not a session's is returned
    unchanged (parsing refuses it later)."""
    parts = key.split("/")
    if layout >= 2:
        del parts[1:2]  # the recorded partition chunk
    if len(parts) < 3:
        return key
    try:
        parts.insert(1, keys.partition_chunk(keys.partition_of(parts[1])))
    except keys.KeyError_:
        return key
    return "/".join(parts)


def to_json(payload: bytes) -> bytes | None:
    """The payload's msgpack map as JSON bytes, or None if it is not one (or holds NaN/inf
    or bytes, which JSON cannot carry)."""
    try:
        obj = msgpack.unpackb(payload, **_UNPACK)
        if not isinstance(obj, dict):
            return None
        return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()
    except Exception:
        return None


def to_payload(data: bytes) -> bytes:
    """Inverse of :func:`to_json`: msgpack bytes that decode to the same values."""
    return msgpack.packb(json.loads(data), use_bin_type=True)


class McapLog:
    """An MCAP file being written: channels are registered on first use. Thread-safe."""

    def __init__(self, path: str | Path, library: str = "pd-client") -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: IO[bytes] = open(self.path, "wb")
        self._w = Writer(self._file, compression=CompressionType.ZSTD)
        self._w.start(profile="", library=library)
        self._w.add_metadata(KEYS_METADATA, {"key_layout": str(keys.KEY_LAYOUT),
                                             "partitions": str(keys.partitions())})
        self._schemas = json_schemas()
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self._seq = 0
        self._last_log = 0  # ns: the log time of the newest message written
        self.messages = 0
        self._closed = False
        self._specs: dict[str, SessionSpec] = {}  # session -> newest spec seen
        self._ros2_ok: bool | None = None  # None: not tried yet
        self.ros2_errors = 0  # predictions the ROS 2 profile could not convert
        self._ros2_failed: set[str] = set()

    def _ros2_channel(self, topic: str, msg_type: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            from pd_service.ros2.messages import typestore

            sid = self._schema_ids.get(msg_type)
            if sid is None:
                text, _ = typestore().generate_msgdef(msg_type, ros_version=2)
                sid = self._w.register_schema(name=msg_type, encoding="ros2msg",
                                              data=text.encode())
                self._schema_ids[msg_type] = sid
            cid = self._w.register_channel(topic=topic, message_encoding="cdr", schema_id=sid)
            self._channels[topic] = cid
        return cid

    def _write_ros2(self, session: str, payload: bytes, log_ns: int) -> None:
        """The prediction as ROS 2 messages, if the session's spec binds ROS 2 outputs."""
        spec = self._specs.get(session)
        out = spec.ros2.outputs if spec is not None and spec.ros2 is not None else None
        if out is None or self._ros2_ok is False:
            return
        try:
            from pd_service.ros2.extract import odometry_from_state, pose_from_state
            from pd_service.ros2.messages import encode as encode_ros
        except ImportError as exc:  # the ros2 extra is not installed
            self._ros2_ok = False
            print(f"pd-record: no ROS 2 channels in the MCAP ({exc}); pip install "
                  "'pd-service[ros2]'", file=sys.stderr)
            return
        self._ros2_ok = True
        try:
            pred = decode(payload, Prediction)
            odom = odometry_from_state(pred.x, pred.P, out.layout, pred.t_ns, out.frame_id,
                                       out.child_frame_id)
            pose = pose_from_state(pred.x, pred.P, out.layout, pred.t_ns, out.frame_id)
            prefix = topic_of(keys.session_prefix(session))
            msgs = ((f"{prefix}/ros2/odom", "nav_msgs/msg/Odometry", odom),
                    (f"{prefix}/ros2/pose", "geometry_msgs/msg/PoseWithCovarianceStamped",
                     pose))
            for topic, msg_type, msg in msgs:
                data = encode_ros(msg, msg_type)
                with self._lock:
                    if self._closed:
                        return
                    self._add(self._ros2_channel(topic, msg_type), data, log_ns)
        except (WireError, ValueError) as exc:  # the JSON channel keeps the prediction
            with self._lock:
                self.ros2_errors += 1
                first = session not in self._ros2_failed
                self._ros2_failed.add(session)
            if first:
                print(f"pd-record: session {session}: a prediction not written as ROS 2 "
                      f"messages ({exc}); the JSON prediction is recorded (counted in "
                      "ros2_errors, said once per session)", file=sys.stderr)

    def _channel(self, topic: str, type_name: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schema_ids.get(type_name)
            if sid is None:
                schema = self._schemas[type_name]
                sid = 0 if schema is None else self._w.register_schema(  # 0: schemaless
                    name=type_name, encoding="jsonschema", data=json.dumps(schema).encode())
                self._schema_ids[type_name] = sid
            cid = self._w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            self._channels[topic] = cid
        return cid

    def _add(self, cid: int, data: bytes, recv_ns: int) -> None:
        """One message (lock held): log time max(receipt, previous log time), module docstring."""
        self._last_log = max(self._last_log, recv_ns)
        self._w.add_message(channel_id=cid, log_time=self._last_log, data=data,
                            publish_time=recv_ns, sequence=self._seq)
        self._seq += 1
        self.messages += 1

    def write(self, topic: str, type_name: str, data: bytes, log_ns: int) -> None:
        with self._lock:
            if self._closed:
                return
            self._add(self._channel(topic, type_name), data, log_ns)

    def write_sample(self, key: str, payload: bytes, log_ns: int, kind: str = "put") -> None:
        """One received sample: on its key's channel, or the session's raw channel."""
        try:
            parsed = keys.parse_key(key)
        except keys.KeyError_:
            return
        data = to_json(payload) if kind == "put" else None
        if data is not None:
            self.write(topic_of(key), TYPE_OF_KIND[parsed.kind], data, log_ns)
            if parsed.kind == "config":
                try:
                    self._specs[parsed.session] = decode(payload, SessionSpec)
                except WireError:
                    pass
            elif parsed.kind == "prediction":
                self._write_ros2(parsed.session, payload, log_ns)
            elif parsed.kind == "camera":
                self._write_image(key, data, log_ns)
            return
        raw = {"key": key, "kind": kind, "payload_b64": base64.b64encode(payload).decode()}
        self.write(topic_of(f"{keys.session_prefix(parsed.session)}/raw"), "RawSample",
                   json.dumps(raw).encode(), log_ns)

    def _write_image(self, key: str, data: bytes, log_ns: int) -> None:
        """A camera frame's image copy on ``<topic>/image`` (module docstring), stamped with
        its capture time; a frame that is not a valid CameraFrame gets none (its JSON is kept)."""
        from pd_service.wire.camera import CameraFrame

        try:
            f = CameraFrame.model_validate(json.loads(data))
        except ValueError:
            return
        image = {"timestamp": {"sec": f.t_ns // 1_000_000_000, "nsec": f.t_ns % 1_000_000_000},
                 "frame_id": "camera", "data": f.data, "format": f.format}
        self.write(topic_of(key) + "/image", IMAGE_TYPE, json.dumps(image).encode(), log_ns)

    def metadata(self, name: str, data: dict[str, str]) -> None:
        with self._lock:
            self._w.add_metadata(name, data)

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._w.finish()
            self._file.close()


class McapRecorder:
    """Records every input and output of ``sessions`` to an MCAP file: the sensor packets on
    the daemon's side of the link (``pd/p<k>/<s>/sensor/*``), commands, predictions, error
    reports, configs (the SessionSpec, also fetched from the daemon at start), the truth,
    camera frames after the link (``pd/p<k>/<s>/camera``), and the session status (queried
    every ``status_every`` s on a background thread)."""

    def __init__(self, transport: Transport, sessions: Sequence[str], path: str | Path,
                 status_every: float = 1.0) -> None:
        self.t = transport
        self.sessions = [keys.check_name(s, "session") for s in sessions]
        self.log = McapLog(path)
        self.log.metadata("pd-record", {"sessions": ",".join(self.sessions)})
        self._handles: list[Handle] = []
        for s in self.sessions:
            for kx in (keys.sensors_of(s), keys.command_key(s), keys.prediction_key(s),
                       keys.path_key(s), keys.error_key(s), keys.status_key(s), keys.config_key(s),
                       keys.truth_key(s), keys.camera_key(s)):
                self._handles.append(transport.subscribe(kx, self._on_sample))
        self._stop = threading.Event()
        for s in self.sessions:
            self._query(keys.config_key(s))
        self._thread: threading.Thread | None = None
        if status_every > 0:
            self._thread = threading.Thread(target=self._status_loop, args=(status_every,),
                                            name="pd-record-status", daemon=True)
            self._thread.start()

    @property
    def path(self) -> Path:
        return self.log.path

    def _on_sample(self, sample: Sample) -> None:
        self.log.write_sample(sample.key, sample.payload, sample.recv_ns, sample.kind)

    def _query(self, key: str) -> None:
        try:
            replies = self.t.get(key, timeout=1.0)
        except Exception:  # no daemon answering: nothing to record
            return
        for r in replies:
            if r.ok:
                self.log.write_sample(r.key, r.payload, time.time_ns())

    def _status_loop(self, every: float) -> None:
        while not self._stop.wait(every):
            for s in self.sessions:
                self._query(keys.status_key(s))

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for h in self._handles:
            h.close()
        self._handles.clear()
        self.log.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --- reading ---------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Record:
    """One logged message: Zenoh key, stream kind, the msgpack payload, log time (ns), and
    ``kind`` put/delete (raw samples keep theirs)."""

    key: str
    stream: str
    session: str
    payload: bytes
    log_ns: int
    kind: str = "put"


def read_records(path: str | Path) -> Iterator[Record]:
    """The messages of an MCAP written by :class:`McapLog`, in arrival order."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        layout = int(meta.get(KEYS_METADATA, {}).get("key_layout", "1"))
        msgs = [(m.sequence, m.log_time, ch.topic, m.data)
                for _, ch, m in reader.iter_messages(log_time_order=False)
                if ch.message_encoding == "json"]  # the ROS 2 (cdr) copies are not the record
    msgs.sort(key=lambda t: t[0])
    for _, log_ns, topic, data in msgs:
        key = rekey(key_of(topic), layout)
        if key.endswith("/raw") and key.count("/") == 3:
            raw = json.loads(data)
            key, kind = rekey(raw["key"], layout), raw["kind"]
            payload = base64.b64decode(raw["payload_b64"])
        else:
            kind, payload = "put", to_payload(data)
        try:
            parsed = keys.parse_key(key)
        except keys.KeyError_:
            continue
        yield Record(key, parsed.kind, parsed.session, payload, log_ns, kind)
