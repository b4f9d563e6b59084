"""The C form of PredictionEncoder.encode_packed (pd_service/wire/_encode.c) against its
Python form: the same bytes for every size class of every int and string, and None (the
Python form runs) for what it does not take."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from pd_service.wire import convert
from pd_service.wire.convert import _ENCODE, PredictionEncoder
from tests.service.helpers import paper_spec

pytestmark = pytest.mark.skipif(
    _ENCODE is None, reason="the C kernel is not in use here (PD_SERVICE_PURE=1, or no C "
                            "compiler at install time): the Python form runs everywhere")

EDGES = [0, 1, 31, 32, 127, 128, 255, 256, 65_535, 65_536, 2**32 - 1, 2**32, 2**63 - 1,
         2**63, 2**64 - 1, -1, -32, -33, -128, -129, -32_768, -32_769, -(2**31),
         -(2**31) - 1, -(2**63)]


def python_form(monkeypatch, enc, pred, xd, pd, seq, made, counters, term=0) -> bytes:
    with monkeypatch.context() as m:
        m.setattr(convert, "_ENCODE", None)
        return enc.encode_packed(pred, xd, pd, seq, made, counters, term)


def fake(step, newest):
    return type("P", (), {"step": step, "newest_step": newest, "x": None, "P": None})()


@pytest.mark.parametrize("session", ["s1", "x" * 40])
def test_same_bytes_for_every_size_class(monkeypatch, session):
    spec = paper_spec(session, epoch_ns=0)
    enc = PredictionEncoder(spec, session)
    rng = np.random.default_rng(5)
    xd = msgpack.packb(rng.normal(size=4).tolist())
    pd = msgpack.packb(rng.normal(size=16).tolist())
    # the probe must actually take the C form, else this test would compare Python with itself
    assert _ENCODE.prediction(enc._parts, 1, 2, 3, xd, pd, None, 4, {}, 5) is not None
    for i, v in enumerate(EDGES):
        w = EDGES[(i * 7 + 3) % len(EDGES)]
        step = abs(v) % 2**30  # t_ns = step * period_ns stays below 2^63
        counters = {"accepted": v, "k" * (i * 13 % 300): w, "é" * (i % 30): 1, "published": abs(w)}
        for seq, made, newest, term in ((abs(v), v, None, abs(w)), (abs(w), w, step, 0),
                                        (0, 0, v, abs(v))):
            args = (fake(step, newest), xd, pd, seq, made, counters, term)
            got = enc.encode_packed(*args)
            assert got == python_form(monkeypatch, enc, *args), (v, w)
            # and the C form itself wrote it (no silent fallback for these values)
            assert _ENCODE.prediction(enc._parts, seq, step, step * spec.period_ns, xd, pd,
                                      newest, made, counters, term) == got


def test_what_it_does_not_take_goes_to_the_python_form(monkeypatch):
    spec = paper_spec("s1", epoch_ns=0)
    enc = PredictionEncoder(spec, "s1")
    xd, pd = msgpack.packb([0.0] * 4), msgpack.packb([0.0] * 16)
    P = enc._parts
    for counters in ({"a": True}, {"a": 2**64}, {"a": -(2**63) - 1}, {1: 2},
                     {"\ud800": 1}, {f"c{j}": j for j in range(300)}, {"a": np.int64(3)}):
        assert _ENCODE.prediction(P, 0, 0, 0, xd, pd, None, 0, counters, 0) is None
        try:
            want = python_form(monkeypatch, enc, fake(0, None), xd, pd, 0, 0, counters)
        except Exception as exc:  # the Python form refuses it: so does the whole call
            with pytest.raises(type(exc)):
                enc.encode_packed(fake(0, None), xd, pd, 0, 0, counters)
        else:
            assert enc.encode_packed(fake(0, None), xd, pd, 0, 0, counters) == want
    for seq in (True, 2**64, np.int64(4), 1.0):
        assert _ENCODE.prediction(P, seq, 0, 0, xd, pd, None, 0, {}, 0) is None
        assert _ENCODE.prediction(P, 0, 0, 0, xd, pd, None, 0, {}, seq) is None  # as a term
    assert _ENCODE.prediction(P, 0, 0, 0, xd, pd, np.int64(3), 0, {}, 0) is None
    with pytest.raises(TypeError):
        _ENCODE.prediction(P[:8], 0, 0, 0, xd, pd, None, 0, {}, 0)
    with pytest.raises(TypeError):
        _ENCODE.prediction(P, 0, 0, 0, bytearray(xd), pd, None, 0, {}, 0)
    with pytest.raises(TypeError):
        _ENCODE.prediction(P, 0, 0, 0, xd, pd, None, 0, {})


# --- pack: the checkpoints' msgpack (pd_service.service.handover.checkpoint.encode_state) -------------------

def wire_form(o):
    """What msgpack is given where the C form takes arrays: their wire form (Tensors)."""
    if isinstance(o, np.ndarray):
        return {"shape": list(o.shape), "data": o.ravel().tolist()}
    if isinstance(o, dict):
        return {wire_form(k): wire_form(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [wire_form(v) for v in o]
    return o


def random_tree(rng, depth=0):
    kind = rng.integers(0, 9 if depth < 4 else 5)
    if kind == 0:
        return [None, True, False][rng.integers(0, 3)]
    if kind == 1:
        v = EDGES[int(rng.integers(0, len(EDGES)))] + int(rng.integers(-1, 2))
        return v if -(2**63) <= v <= 2**64 - 1 else 0
    if kind == 2:
        return float(rng.normal() * 10.0 ** rng.integers(-300, 300))
    if kind == 3:
        return "é" * int(rng.integers(0, 3)) + "k" * int(
            [0, 5, 31, 32, 255, 256, 65_535, 65_536][rng.integers(0, 8)])
    if kind == 4:
        return float(["nan", "inf", "-inf"][rng.integers(0, 3)])  # packed as they are
    if kind == 5:
        shape = tuple(int(d) for d in rng.integers(0, 5, size=rng.integers(0, 4)))
        a = rng.normal(size=shape)
        return a.T if rng.integers(0, 2) else a  # strided too
    n = int([0, 1, 15, 16, 17][rng.integers(0, 5)])
    if kind == 6:
        return {f"k{i}": random_tree(rng, depth + 1) for i in range(n)}
    if kind == 7:
        return [random_tree(rng, depth + 1) for _ in range(n)]
    return tuple(random_tree(rng, depth + 1) for _ in range(n))


def test_pack_writes_what_msgpack_writes_of_the_wire_form():
    rng = np.random.default_rng(11)
    big = {"l": list(range(70_000)), "a": np.arange(70_000.0), "s": "x" * 70_000,
           "m": {str(i): i for i in range(70_000)}}
    for obj in [big] + [random_tree(rng) for _ in range(3000)]:
        got = _ENCODE.pack(obj)
        want = msgpack.packb(wire_form(obj), use_bin_type=True)
        assert got == want, obj


@pytest.mark.parametrize("obj", [
    2**64, -(2**63) - 1, True + 0.5j, b"bytes", bytearray(b"x"), np.float64(1.0), np.int64(1),
    np.array([1, 2]), np.array([1.0], dtype=">f8"), np.array([1.0], dtype=np.float32),
    np.array([0.0, np.nan]), np.array([[np.inf]]), {"k": np.array([1.0, -np.inf])},
    [1, 2, object()], {1.5: object()}, "\ud800", type("L", (list,), {})([1]),
    type("D", (dict,), {})(a=1), type("S", (str,), {})("s"), type("I", (int,), {})(1),
], ids=repr)
def test_pack_declines_what_it_does_not_write(obj):
    """Another type, a subclass, another dtype or byte order, a non-finite array value, an
    int beyond msgpack's range, a str that is not UTF-8: None (the Python form runs)."""
    assert _ENCODE.pack(obj) is None
    assert _ENCODE.pack({"deep": [{"x": obj}]}) is None


def test_pack_declines_deep_nesting():
    deep: list = []
    x = deep
    for _ in range(40):
        x.append([])
        x = x[0]
    assert _ENCODE.pack(deep) is None
    assert _ENCODE.pack([[[[1]]]]) == msgpack.packb([[[[1]]]])
