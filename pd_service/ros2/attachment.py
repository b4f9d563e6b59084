"""The Zenoh attachment rmw_zenoh_cpp puts on every published sample: sequence number, source
timestamp and publisher GID.

Two layouts exist (both written with the zenoh-ext serializer: integers little-endian, a
string or byte buffer as a LEB128 length then its bytes):

``positional`` -- rmw_zenoh Jazzy >= 0.2.4 (and Rolling >= 0.6.0), ``attachment_helpers.cpp``
after ros2/rmw_zenoh#601 (Jazzy backport #605); docs/design.md "Publishers"::

    offset 0   8 bytes  sequence number, int64 little-endian
    offset 8   8 bytes  source timestamp, int64 little-endian, ns since the UNIX epoch
    offset 16  1 byte   GID length, 0x10 (LEB128 of 16)
    offset 17 16 bytes  publisher GID
    (33 bytes)

``keyed`` -- rmw_zenoh Jazzy 0.2.0 .. 0.2.3, ``attachment_helpers.cpp`` before #601: each value
preceded by its name as a serialized string::

    str "sequence_number", int64, str "source_timestamp", int64, str "source_gid", buf (16 bytes)
    (77 bytes)

A subscriber of rmw_zenoh drops a sample that has no attachment or one it cannot parse, so a
publisher must send the layout of the robot's release.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

from pd_service.ros2.errors import Ros2DecodeError

#: RMW_GID_STORAGE_SIZE in rmw Jazzy (bytes).
GID_SIZE = 16

AttachmentLayout = Literal["positional", "keyed"]

_INT64 = struct.Struct("<q")
_KEYS = ("sequence_number", "source_timestamp", "source_gid")


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh attachment values. ``sequence_number`` counts from 1 per publisher;
    ``source_timestamp_ns`` is the publisher's wall clock at publication (ns since epoch)."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"GID must have {GID_SIZE} bytes, got {len(self.gid)}")
        for name in ("sequence_number", "source_timestamp_ns"):
            value = getattr(self, name)
            if not -(2**63) <= value < 2**63:
                raise ValueError(f"{name} {value} does not fit an int64")


def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def encode_attachment(att: Attachment, layout: AttachmentLayout = "positional") -> bytes:
    """The attachment bytes in ``layout`` (see the module docstring)."""
    seq, stamp = _INT64.pack(att.sequence_number), _INT64.pack(att.source_timestamp_ns)
    gid = _leb128(GID_SIZE) + att.gid
    if layout == "positional":
        return seq + stamp + gid

    def key(name: str) -> bytes:
        return _leb128(len(name)) + name.encode("ascii")

    return key(_KEYS[0]) + seq + key(_KEYS[1]) + stamp + key(_KEYS[2]) + gid


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def take(self, n: int, what: str) -> bytes:
        if self.pos + n > len(self.data):
            raise Ros2DecodeError(f"attachment: truncated in {what} ({len(self.data)} bytes)")
        chunk = self.data[self.pos : self.pos + n]
        self.pos += n
        return chunk

    def leb128(self, what: str) -> int:
        value, shift = 0, 0
        while True:
            byte = self.take(1, what)[0]
            value |= (byte & 0x7F) << shift
            if not byte & 0x80:
                return value
            shift += 7
            if shift > 63:
                raise Ros2DecodeError(f"attachment: length of {what} is not a valid LEB128")

    def int64(self, what: str) -> int:
        value: int = _INT64.unpack(self.take(8, what))[0]
        return value

    def key(self, expected: str) -> None:
        n = self.leb128(f"key {expected!r}")
        name = self.take(n, f"key {expected!r}")
        if name != expected.encode("ascii"):
            raise Ros2DecodeError(f"attachment: expected key {expected!r}, got {name[:32]!r}")

    def gid(self) -> bytes:
        n = self.leb128("GID length")
        if n != GID_SIZE:
            raise Ros2DecodeError(f"attachment: GID length {n}, expected {GID_SIZE}")
        return self.take(n, "GID")


def attachment_layout(data: bytes) -> AttachmentLayout:
    """Which layout ``data`` is in: 33 bytes is ``positional``; anything starting with the
    serialized key ``sequence_number`` is ``keyed``. Raises Ros2DecodeError otherwise."""
    if len(data) == 8 + 8 + 1 + GID_SIZE:
        return "positional"
    if data.startswith(_leb128(len(_KEYS[0])) + _KEYS[0].encode("ascii")):
        return "keyed"
    raise Ros2DecodeError(
        f"attachment: {len(data)} bytes is neither the 33-byte positional layout nor the keyed one"
    )


def decode_attachment(data: bytes | bytearray | memoryview) -> Attachment:
    """Parse an rmw_zenoh attachment of either layout. Raises Ros2DecodeError on anything else
    (wrong length, wrong keys, a GID that is not 16 bytes, trailing bytes)."""
    raw = bytes(data)
    layout = attachment_layout(raw)
    r = _Reader(raw)
    if layout == "keyed":
        r.key(_KEYS[0])
    seq = r.int64("sequence number")
    if layout == "keyed":
        r.key(_KEYS[1])
    stamp = r.int64("source timestamp")
    if layout == "keyed":
        r.key(_KEYS[2])
    gid = r.gid()
    if r.pos != len(raw):
        raise Ros2DecodeError(f"attachment: {len(raw) - r.pos} trailing bytes")
    return Attachment(sequence_number=seq, source_timestamp_ns=stamp, gid=gid)
