"""wire.codec's readers of a message's raw map: unpack_fields against unpack_map."""

from __future__ import annotations

import msgpack
import pytest

from pd_service.wire import MAX_MESSAGE_BYTES, WireError
from pd_service.wire.codec import unpack_fields, unpack_map

WANTED = frozenset({"session", "now_step", "term", "session_counters"})


def _state() -> dict:
    return {"v": 1, "session": "s1", "now_step": 199, "term": 3,
            "packets": [[k, [0.1 * k, 0.2], {"r": [1.0, 2.0]}] for k in range(40)],
            "x": {"shape": [4], "data": [1.0, 2.0, 3.0, 4.0]},
            "session_counters": {"a": 1}, "u_before": None}


def test_unpack_fields_reads_the_wanted_fields_as_unpack_map_does() -> None:
    data = msgpack.packb(_state())
    full = unpack_map(data, "SessionState")
    assert unpack_fields(data, "SessionState", WANTED) == {k: full[k] for k in WANTED}
    assert unpack_fields(memoryview(data), "SessionState", WANTED) == {k: full[k] for k in WANTED}
    assert unpack_fields(data, "SessionState", frozenset({"absent"})) == {}


@pytest.mark.parametrize("data, reason", [
    ("text", "expected bytes"),
    (b"", "expected a msgpack map"),
    (msgpack.packb([1, 2]), "expected a msgpack map"),
    (msgpack.packb(_state())[:-3], "not valid msgpack"),
    (msgpack.packb(_state()) + b"\x00", "trailing bytes"),
    (msgpack.packb({"session": b"raw"}), "not valid msgpack"),  # bin: refused as unpack_map
    (b"\xc1", "expected a msgpack map"),
    (b"\x82\xa1a\xc1", "not valid msgpack"),
])
def test_unpack_fields_refuses_what_is_not_a_map(data: object, reason: str) -> None:
    with pytest.raises(WireError, match=reason):
        unpack_fields(data, "SessionState", WANTED)  # type: ignore[arg-type]


def test_unpack_fields_refuses_deep_nesting_and_huge_messages() -> None:
    deep = b"\x81\xa1a" + b"\x91" * 2000 + b"\xc0"
    with pytest.raises(WireError, match="SessionState"):
        unpack_fields(deep, "SessionState", WANTED)
    with pytest.raises(WireError, match="SessionState"):
        unpack_fields(deep, "SessionState", frozenset())
    with pytest.raises(WireError, match="byte limit"):
        unpack_fields(b"\x80" + b"\x00" * MAX_MESSAGE_BYTES, "SessionState", WANTED)


def test_unpack_fields_leaves_what_it_skips_to_the_full_decode() -> None:
    data = msgpack.packb({"skipped": b"raw", "session": "s"})
    assert unpack_fields(data, "SessionState", WANTED) == {"session": "s"}
    with pytest.raises(WireError, match="max_bin_len"):
        unpack_map(data, "SessionState")
