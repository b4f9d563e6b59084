"""decode() raises WireError, and nothing else, for any byte string.

For every message kind: 2,000 random byte strings, 5,000 byte-level mutations of valid
encodings and 3,000 structural mutations (a field replaced by a hostile value, removed,
added, or nested to death), plus a fixed list of hand-made hostile inputs. A seeded
random loop keeps it reproducible and fast; a failure prints the offending bytes.
"""

from __future__ import annotations

import copy
import math
import random

import msgpack
import numpy as np
import pytest

from pd_service.wire import (
    MAX_MESSAGE_BYTES,
    MESSAGE_TYPES,
    SessionSpec,
    WireError,
    decode,
    encode,
)
from pd_service.wire.errors import MAX_REASON_CHARS
from tests.wire.factories import (
    EXAMPLES,
    imm_spec,
    measurement,
    omni_spec,
    paper_spec,
    prediction,
)

N_RANDOM = 2_000
N_BYTE_MUTATIONS = 5_000
N_STRUCT_MUTATIONS = 3_000

INTERESTING_BYTES = [0x00, 0x7F, 0x80, 0x8F, 0x90, 0x9F, 0xA0, 0xBF, 0xC0, 0xC1, 0xC2, 0xC3,
                     0xC4, 0xC7, 0xCA, 0xCB, 0xCC, 0xCF, 0xD0, 0xD3, 0xD4, 0xD9, 0xDC, 0xDD,
                     0xDE, 0xDF, 0xE0, 0xFF]
DEEP = "__DEEP__"
HOSTILE = [
    None, True, False, 0, -1, 1, 2**63, 2**64 - 1, -(2**63), 1.5, math.nan, math.inf,
    -math.inf, -0.0, 1e308, "", "A", "x" * 70, "@service", "s1", "camera", [], {}, [1.0],
    [[1.0, 2.0], [3.0, 4.0]], {"shape": [2], "data": [1, 2]}, {"shape": [0], "data": []},
    {"shape": [2, 2], "data": [1, 2, 3]}, {"shape": [65], "data": [0.0] * 65},
    {"shape": [1e9], "data": []}, {"shape": [-1], "data": []}, {"shape": [True], "data": [1.0]},
    {"shape": [1], "data": [math.nan]}, {"shape": [2, 2], "data": [1, 0, 0, -1]},
    {"shape": [1], "data": ["1"]}, {"shape": [1], "data": [None]}, {"kind": "other"},
    {"kind": 5}, b"bytes", msgpack.ExtType(1, b"x"), DEEP, list(range(100)),
    {"v": 1}, {str(i): i for i in range(50)},
]


def _valid_encodings() -> list[bytes]:
    out = [encode(make()) for make in EXAMPLES.values()]
    out += [encode(measurement(step=None, t_ns=-5, R=np.eye(2))),
            encode(prediction(n=1, newest_step=None)),
            encode(paper_spec(session="x-1")),
            encode(omni_spec(sigma=True)),
            encode(imm_spec(position=True))]
    return out


VALID = _valid_encodings()


def _byte_mutation(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(9)
        pos = rng.randrange(len(b) + 1) if b else 0
        if op == 0 and b:  # flip bits
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:  # an interesting byte
            b[rng.randrange(len(b))] = rng.choice(INTERESTING_BYTES)
        elif op == 2:  # truncate
            del b[pos:]
        elif op == 3:  # insert random bytes
            b[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif op == 4 and b:  # delete a slice
            del b[pos:pos + rng.randint(1, 16)]
        elif op == 5 and b:  # duplicate a slice
            b[pos:pos] = b[pos:pos + rng.randint(1, 32)]
        elif op == 6:  # splice with another valid message
            other = rng.choice(VALID)
            b = b[:pos] + other[rng.randrange(len(other)):]
        elif op == 7:  # trailing garbage
            b += rng.randbytes(rng.randint(1, 4))
        elif op == 8 and b:  # forge a container length
            heads = [i for i, x in enumerate(b) if 0x80 <= x <= 0xBF]
            if heads:
                i = rng.choice(heads)
                b[i] = (b[i] & 0xF0) | rng.randrange(16)
    return bytes(b)


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _struct_mutation(rng: random.Random, data: bytes) -> bytes:
    obj = msgpack.unpackb(data)
    for _ in range(rng.randint(1, 2)):
        paths = [p for p in _paths(obj) if p]
        path = rng.choice(paths)
        parent = obj
        for p in path[:-1]:
            parent = parent[p]
        last = path[-1]
        op = rng.randrange(4)
        if op == 0 and isinstance(parent, dict):
            del parent[last]
        elif op == 1 and isinstance(parent, dict):
            parent[rng.choice(["extra", "V", "z ", "", "shape"])] = copy.deepcopy(rng.choice(HOSTILE[:20]))
        else:
            value = rng.choice(HOSTILE)
            parent[last] = copy.deepcopy(value)
    packed = msgpack.packb(obj, use_bin_type=True)
    marker = msgpack.packb(DEEP)
    if marker in packed:
        depth = rng.choice([10, 100, 1000, 1024, 1025, 5000])
        packed = packed.replace(marker, b"\x91" * depth + b"\xc0")
    return packed


def _hand_made() -> list[bytes]:
    m = encode(measurement())
    return [
        b"", b"\xc0", b"\xc1", b"\x80", b"\x90", b"\xa0", b"\x01", b"\xcb" + b"\x7f\xf8" + b"\0" * 6,
        b"\x91" * 1023 + b"\xc0", b"\x91" * 1025 + b"\xc0", b"\x91" * 60000,
        b"\x81\xa1v" * 20000, b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff",
        b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xc9\xff\xff\xff\xff\x01",
        b"\xd6\xff\x00\x00\x00\x01",  # msgpack timestamp
        b"\x81\x01\x02", b"\x81\xc0\x02", b"\x81\x90\x02", b"\x81\xc4\x01v\x01",
        m + b"\x00", m[:-1], m * 2, b"\x00" * (MAX_MESSAGE_BYTES + 1),
        encode(paper_spec()) + b"\x90" * (MAX_MESSAGE_BYTES),
        msgpack.packb([msgpack.unpackb(m)]), msgpack.packb("Measurement"),
        msgpack.packb({**msgpack.unpackb(m), "z": {"shape": [2], "data": [1.0, 2.0]} | {"x": 1}}),
        msgpack.packb({**msgpack.unpackb(m), "z": {"shape": [2], "data": [1.0, 2.0]}},
                      use_single_float=True),
    ]


def _check(data: bytes, msg_type) -> bool:
    """Decode; True if accepted. Fails the test on anything but a clean WireError."""
    try:
        msg = decode(data, msg_type)
    except WireError as exc:
        reason = exc.reason
        assert isinstance(reason, str) and reason, data
        assert len(reason) <= MAX_REASON_CHARS and "\n" not in reason, reason
        assert reason.startswith(msg_type.__name__), reason
        return False
    except Exception as exc:  # pragma: no cover - this is the failure being tested for
        pytest.fail(f"decode({data[:200]!r}..., {msg_type.__name__}) raised "
                    f"{type(exc).__name__}: {exc}")
    assert type(msg) is msg_type
    try:
        again = encode(msg)
    except WireError as exc:  # re-encoding can only fail on size
        assert "limit" in exc.reason
        return True
    assert decode(again, msg_type) == msg
    return True


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_decode_raises_only_wire_error(msg_type):
    rng = random.Random(f"fuzz-{msg_type.__name__}")
    own = encode(EXAMPLES[msg_type]())
    accepted = refused = 0
    inputs: list[bytes] = list(_hand_made())
    for _ in range(N_RANDOM):
        n = rng.choice([rng.randint(0, 8), rng.randint(0, 64), rng.randint(0, 400)])
        head = bytes([rng.choice([0x80 | rng.randrange(16), 0xDE, 0xDF])]) if rng.random() < 0.5 else b""
        inputs.append(head + rng.randbytes(n))
    for _ in range(N_BYTE_MUTATIONS):
        base = own if rng.random() < 0.7 else rng.choice(VALID)
        inputs.append(_byte_mutation(rng, base))
    for _ in range(N_STRUCT_MUTATIONS):
        inputs.append(_struct_mutation(rng, own))
    for data in inputs:
        if _check(data, msg_type):
            accepted += 1
        else:
            refused += 1
    assert accepted + refused >= 10_000
    # The mutations are hostile: nearly everything must be refused, but the valid
    # message itself and harmless mutations (e.g. a changed seq) still pass.
    assert refused > 0.8 * (accepted + refused)
    assert _check(own, msg_type)


def test_decode_accepts_bytes_like_only():
    data = encode(measurement())
    msg_type = type(measurement())
    assert decode(bytearray(data), msg_type) == decode(memoryview(data), msg_type)
    for bad in (None, "text", 5, [1, 2]):
        with pytest.raises(WireError, match="expected bytes"):
            decode(bad, msg_type)  # type: ignore[arg-type]


def test_decode_needs_a_message_class():
    with pytest.raises(TypeError):
        decode(encode(measurement()), dict)  # type: ignore[arg-type]


@pytest.mark.parametrize("make", [omni_spec, imm_spec], ids=["unscented", "imm"])
def test_nonlinear_specs_raise_only_wire_error(make):
    """Structural and byte mutations of the nonlinear model kinds' specs."""
    rng = random.Random(f"fuzz-{make.__name__}")
    own = encode(make())
    inputs = [_struct_mutation(rng, own) for _ in range(1_500)]
    inputs += [_byte_mutation(rng, own) for _ in range(1_500)]
    refused = sum(not _check(data, SessionSpec) for data in inputs)
    assert refused > 0.8 * len(inputs)
    assert _check(own, SessionSpec)
