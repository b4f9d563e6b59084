"""rmw_zenoh attachment layouts, byte for byte: docs/design.md "Publishers" (33 bytes:
int64 LE sequence number, int64 LE source timestamp, 1 length byte 16, 16 GID bytes;
attachment_helpers.cpp after ros2/rmw_zenoh#601, Jazzy >= 0.2.4) and the keyed layout of
Jazzy 0.2.0..0.2.3 (attachment_helpers.cpp before #601)."""

from __future__ import annotations

import struct

import pytest

from pd_service.ros2.attachment import (
    Attachment,
    attachment_layout,
    decode_attachment,
    encode_attachment,
)
from pd_service.ros2.errors import Ros2DecodeError

GID = bytes(range(1, 17))
ATT = Attachment(sequence_number=7, source_timestamp_ns=1_700_000_000_123_456_789, gid=GID)


def test_positional_layout_bytes() -> None:
    raw = encode_attachment(ATT)
    assert len(raw) == 33
    assert raw[:8] == struct.pack("<q", 7)
    assert raw[8:16] == struct.pack("<q", 1_700_000_000_123_456_789)
    assert raw[16] == 16
    assert raw[17:] == GID
    assert attachment_layout(raw) == "positional"
    assert decode_attachment(raw) == ATT


def test_keyed_layout_bytes() -> None:
    raw = encode_attachment(ATT, "keyed")
    expected = (
        b"\x0fsequence_number"
        + struct.pack("<q", 7)
        + b"\x10source_timestamp"
        + struct.pack("<q", 1_700_000_000_123_456_789)
        + b"\x0asource_gid"
        + b"\x10"
        + GID
    )
    assert raw == expected and len(raw) == 77
    assert attachment_layout(raw) == "keyed"
    assert decode_attachment(raw) == ATT


def test_negative_and_extreme_values_round_trip() -> None:
    for seq, ts in ((-1, 0), (2**63 - 1, -(2**63)), (1, 1)):
        att = Attachment(seq, ts, b"\xff" * 16)
        assert decode_attachment(encode_attachment(att)) == att
        assert decode_attachment(encode_attachment(att, "keyed")) == att


@pytest.mark.parametrize(
    "raw",
    [
        b"",
        b"\x00" * 32,
        b"\x00" * 16 + b"\x0f" + b"\x00" * 16,  # 33 bytes, GID length 15
        encode_attachment(ATT, "keyed")[:-1],
        encode_attachment(ATT, "keyed") + b"\x00",
        encode_attachment(ATT, "keyed").replace(b"source_gid", b"source_xid"),
    ],
)
def test_bad_attachments_refused(raw: bytes) -> None:
    with pytest.raises(Ros2DecodeError):
        decode_attachment(raw)


def test_gid_size_checked() -> None:
    with pytest.raises(ValueError):
        Attachment(1, 1, b"\x00" * 15)
