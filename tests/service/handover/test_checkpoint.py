"""pd_service.service.handover.checkpoint: the fast state encoding equals the validated one, byte for byte."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.backends import build
from pd_service.estimation import EstimatorState, StateError
from pd_service.scenarios import SCENARIOS, ScenarioSim, get_scenario
from pd_service.service.handover.checkpoint import encode_state, from_message, to_message
from pd_service.wire import SessionState, WireError, decode, encode


def _fed(name: str, steps: int = 40) -> EstimatorState:
    """An estimator of scenario ``name`` fed its simulated samples (delayed by 2 steps)
    and commands, exported."""
    scn = get_scenario(name)
    spec = scn.spec(name, 0)
    est = build(spec).est
    sim = ScenarioSim(scn, seed=3, loss=0.2)
    names = {s.name for s in spec.sensors}
    held: list = []
    for k in range(steps):
        u = scn.command(k)
        est.add_command(k, u, now=k)
        held += [d for d in sim.sample() if d.sensor in names and not d.lost]
        for d in [d for d in held if d.step <= k - 2]:
            est.add_measurement(d.sensor, d.step, d.z, now=k)
        held = [d for d in held if d.step > k - 2]
        est.predict(k)
        sim.advance(u)
    return est.export_state()


KW = dict(session="s1", instance="inst-a", fingerprint="ab" * 32, made_ns=123,
          session_counters={"accepted": 7, "flood": 0}, published=9, seq=9, term=5 << 16 | 7)


@pytest.mark.parametrize("name", SCENARIOS)
def test_fast_encoding_equals_the_validated_one(name):
    st = _fed(name)
    data = encode_state(st, **KW)  # type: ignore[arg-type]
    assert data == encode(to_message(st, **KW))  # type: ignore[arg-type]
    msg = decode(data, SessionState)
    assert msg.packets or msg.commands


def test_a_state_of_the_former_stacked_engine_still_restores():
    """Daemons before 2026-11 ran linear sessions on StackedObserverPredictor, a batched
    twin with the same state: their checkpoints and replicas restore into ObserverPredictor;
    any other kind is still refused."""
    st = _fed("paper")
    assert st.kind == "ObserverPredictor"
    spec = get_scenario("paper").spec("paper", 0)
    old = decode(encode(to_message(st, **KW)), SessionState).model_copy(  # type: ignore[arg-type]
        update={"kind": "StackedObserverPredictor"})
    est = build(spec).est
    est.restore_state(from_message(old, 4))  # type: ignore[attr-defined]
    want = build(spec).est
    want.restore_state(st)  # type: ignore[attr-defined]
    got, ref = est.predict(st.now + 1), want.predict(st.now + 1)
    assert np.array_equal(got.x, ref.x) and np.array_equal(got.P, ref.P)
    with pytest.raises(StateError, match="kind"):
        build(spec).est.restore_state(  # type: ignore[attr-defined]
            from_message(old.model_copy(update={"kind": "AugmentedStateKF"}), 4))


def test_a_non_finite_state_takes_the_validated_path_and_is_refused():
    st = _fed("paper")
    st.base["P"] = st.base["P"].copy()
    st.base["P"][0, 0] = np.inf
    with pytest.raises(WireError):
        encode_state(st, **KW)  # type: ignore[arg-type]


@pytest.mark.parametrize("where", ["command", "packet", "x"])
def test_every_array_is_checked_for_finite_values(where):
    """The fast path checks each array as it converts it (one stack for the commands):
    NaN anywhere takes the validated path, which refuses it."""
    st = _fed("paper")
    if where == "command":
        j, u = st.commands[-1]
        st.commands[-1] = (j, np.full_like(u, np.nan))
    elif where == "packet":
        s, name, z, R, off = st.packets[-1]
        st.packets[-1] = (s, name, np.full_like(z, np.nan), R, off)
    else:
        st.base["x"] = np.full_like(st.base["x"], np.nan)
    with pytest.raises(WireError):
        encode_state(st, **KW)  # type: ignore[arg-type]


def test_finite_values_whose_sum_overflows_are_encoded():
    st = _fed("paper")
    j, u = st.commands[0]
    st.commands[0] = (j, np.full_like(u, 1.7e308))
    st.commands[1] = (st.commands[1][0], np.full_like(u, 1.7e308))
    s, name, z, R, off = st.packets[-1]
    st.packets[-1] = (s, name, np.full(z.shape, 1.7e308), R, off)
    assert encode_state(st, **KW) == encode(to_message(st, **KW))  # type: ignore[arg-type]


def test_tensors_of_mixed_shapes_are_converted_one_by_one():
    from pd_service.wire.session_state import Tensors

    t = Tensors()
    rows = t.rows([np.zeros(2), np.ones(3)])
    assert rows == [{"shape": [2], "data": [0.0, 0.0]}, {"shape": [3], "data": [1.0] * 3}]
    assert t.finite


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_c_form_writes_what_the_python_form_writes(monkeypatch, name):
    """Where the C kernel is built (_encode.pack), the checkpoint is its bytes, which the
    Python form (dicts and lists of floats, msgpack) must equal for every backend's state,
    with counters and ints of every size class."""
    from pd_service.service.handover import checkpoint

    if checkpoint._PACK is None:
        pytest.skip("the C kernel is not in use here: the Python form runs everywhere")
    st = _fed(name)
    kw = dict(KW, session_counters={"a": 2**64 - 1, "é" * 40: -(2**63), "k" * 300: 0},
              made_ns=2**63 + 5, published=2**32, seq=65_536, term=2**63 - 1)
    fields = checkpoint._fields(st, checkpoint._as_array, checkpoint._as_arrays,
                                **kw)  # type: ignore[arg-type]
    c_form = checkpoint._PACK(fields)
    assert c_form is not None  # the C form wrote it: no silent fallback for ordinary states
    with monkeypatch.context() as m:
        m.setattr(checkpoint, "_PACK", None)
        assert encode_state(st, **kw) == c_form  # type: ignore[arg-type]
    assert encode_state(st, **kw) == c_form  # type: ignore[arg-type]


def test_samples_and_commands_inside_steps_survive_a_checkpoint_bit_for_bit():
    """A continuous-time session with samples at their own times and commands taking effect
    inside steps: export, encode (both encoders agree), decode, restore; the restored
    estimator continues with the very bits of the original."""
    from tests.wire.factories import paper_continuous_spec

    spec = paper_continuous_spec()
    rng = np.random.default_rng(3)
    a, b = build(spec).est, build(spec).est
    T = spec.period_ns / 1e9

    def feed(est, k, r):  # type: ignore[no-untyped-def]
        for name, m in (("camera", 2), ("ranger", 1)):
            s = k - int(r.integers(0, 4))
            est.add_measurement(name, s, r.standard_normal(m), k, None, float(r.uniform(0, T)))
        est.add_command(k + spec.lead, r.standard_normal(1), k, float(r.uniform(0, T)))

    for k in range(30):
        feed(a, k, rng)
    st = a.export_state()
    assert st.command_offsets and any(p[4] > 0.0 for p in st.packets)
    data = encode_state(st, **KW)  # type: ignore[arg-type]
    assert data == encode(to_message(st, **KW))  # type: ignore[arg-type]
    b.restore_state(from_message(decode(data, SessionState), b.n))
    for k in range(30, 45):
        seed = int(rng.integers(0, 2**31))
        feed(a, k, np.random.default_rng(seed))
        feed(b, k, np.random.default_rng(seed))
        pa, pb = a.predict(k), b.predict(k)
        assert np.array_equal(pa.x, pb.x) and np.array_equal(pa.P, pb.P), k
