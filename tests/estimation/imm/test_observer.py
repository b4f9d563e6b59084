"""ImmObserverPredictor: exact replay under delayed, shuffled, lost packets; factory."""

from __future__ import annotations

import numpy as np
import pytest

from pd_service.estimation.imm.factory import make_imm
from pd_service.estimation.imm.filter import ImmFilter

from .common import SIGMA_BEARING

MODES = [
    {"model": "imm_cv", "params": {"period_s": 0.1, "sigma_accel": 0.003}},
    {"model": "imm_ct", "params": {"period_s": 0.1, "sigma_accel": 0.0016,
                                   "sigma_turn_step": 0.0035}},
]
TRANSITION = [[0.95, 0.05], [0.05, 0.95]]
SENSORS = [
    {"name": f"st{i + 1}", "kind": "range_bearing", "station": list(p), "sigma_range": 0.3,
     "sigma_bearing": SIGMA_BEARING}
    for i, p in enumerate([(9.5, -8.5), (25.1, 18.5), (-6.1, 18.5)])
]
X0 = np.array([0.0, 0.3, 0.0, 0.0, 0.0])
P0 = np.diag([0.25, 0.0025, 0.25, 0.0025, 3e-4])


def _truth(steps):
    """Straight, then a left turn at 6 deg/s (exact arcs)."""
    from pd_service.estimation.imm.models import ct_transition

    x = X0.copy()
    out = [x]
    for k in range(steps):
        x = ct_transition(x, 0.1)
        x[4] = np.radians(6.0) if k + 1 >= steps // 3 else 0.0
        out.append(x)
    return np.array(out)


def _traffic(steps, max_delay, seed, filt):
    """Packets (sensor, stamp, z, arrival): 80% sampled, delays 0..max_delay, shuffled."""
    rng = np.random.default_rng(seed)
    truth = _truth(steps)
    pk = []
    for s in range(steps + 1):
        for sen in filt.sensors:
            if rng.random() < 0.8:
                z = sen.h(truth[s]) + rng.standard_normal(2) * np.sqrt(np.diag(sen.R))
                pk.append((sen.name, s, z, s + int(rng.integers(0, max_delay + 1))))
    order = rng.permutation(len(pk))
    return [pk[i] for i in order]


def _from_scratch(filt: ImmFilter, packets, target):
    """Plain IMM run from step 0 over the packets (stamp order), then predicted to target."""
    names = [s.name for s in filt.sensors]
    by: dict[int, list] = {}
    for name, s, z, _ in packets:
        by.setdefault(s, []).append((names.index(name), z, None))
    st = filt.initial_state(X0, P0)
    for k in range(target + 1):
        if by.get(k):
            st = filt.update(st, sorted(by[k], key=lambda o: o[0]))
        if k == target:
            break
        st = filt.predict(st, k)
    return filt.output(st), st


@pytest.mark.parametrize("variant", ["single", "centralised", "imm1", "imm2"])
def test_exact_replay_under_shuffled_delayed_packets(variant):
    steps, max_delay, lead = 60, 8, 3
    op = make_imm(MODES, TRANSITION, SENSORS, variant, X0, P0, lead=lead, max_delay=max_delay,
                  node=1)
    traffic = _traffic(steps, max_delay, seed=11, filt=op.filter)
    accepted = []
    for now in range(steps + 1):
        for pkt in [p for p in traffic if p[3] == now]:  # shuffled within the arrival step
            assert op.add_measurement(pkt[0], pkt[1], pkt[2], now=now)
            accepted.append(pkt)
        pred = op.predict(now)
        if now % 12 == 5 or now == steps:
            (x, P), st = _from_scratch(op.filter, accepted, now + lead)
            assert pred.step == now + lead
            np.testing.assert_allclose(pred.x, x, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(pred.P, P, rtol=1e-10, atol=1e-15)
            modes = op.predict_modes(now)
            k = 1 if variant == "imm1" else 0
            np.testing.assert_allclose(modes.mu, st.mu[k], rtol=1e-10, atol=1e-15)
            np.testing.assert_allclose(modes.x, st.x[k], rtol=1e-12, atol=1e-12)
    assert op.counters["accepted"] == len(accepted)
    # Same packets, in stamp order, without delay: the same answer.
    op2 = make_imm(MODES, TRANSITION, SENSORS, variant, X0, P0, lead=lead, max_delay=max_delay,
                   node=1)
    for name, s, z, _ in sorted(accepted, key=lambda p: (p[1], p[0])):
        op2.add_measurement(name, s, z, now=s)
    for now in range(max(p[1] for p in accepted), steps + 1):
        op2.predict(now)
    np.testing.assert_allclose(op2.predict(steps).x, op.predict(steps).x, rtol=1e-12, atol=1e-12)


def test_counters_and_window():
    op = make_imm(MODES, TRANSITION, SENSORS, "imm2", X0, P0, lead=2, max_delay=5)
    z = [10.0, 0.5]
    assert op.add_measurement("st1", 3, z, now=3)
    assert not op.add_measurement("st1", 3, z, now=4)  # duplicate
    assert not op.add_measurement("st2", 9, z, now=6)  # future
    assert not op.add_measurement("st2", 0, z, now=6)  # late (window starts at 1)
    assert op.add_measurement("st2", 1, z, now=6)
    c = op.counters
    assert (c["accepted"], c["duplicate"], c["future"], c["late"]) == (2, 1, 1, 1)
    pred = op.predict_modes(7)
    assert pred.step == 9 and pred.mu.shape == (2,) and pred.x.shape == (2, 5)
    assert pred.mu.sum() == pytest.approx(1.0)
    np.testing.assert_array_equal(pred.x_combined, op.predict(7).x)


def test_bad_input_is_refused_clearly():
    op = make_imm(MODES, TRANSITION, SENSORS, "centralised", X0, P0, lead=1, max_delay=3)
    with pytest.raises(ValueError, match="sensor"):
        op.add_measurement("radar", 0, [1.0, 0.0], now=0)
    with pytest.raises(ValueError, match="z"):
        op.add_measurement("st1", 0, [1.0], now=0)
    with pytest.raises(ValueError, match="R"):
        op.add_measurement("st1", 0, [1.0, 0.0], now=0, R=[[1.0, 0.0], [0.0, 0.0]])
    assert op.add_measurement("st1", 0, [1.0, 0.0], now=0, R=[[0.5, 0.0], [0.0, 0.01]])
    assert op.counters["accepted"] == 1


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"variant": "best"}, "variant"),
        ({"modes": [{"model": "imm_nope"}]}, "unknown model"),
        ({"modes": [{"model": "imm_cv", "params": {"sigma_accel": -1}}]}, "sigma_accel"),
        ({"modes": [{"model": "imm_cv", "extra": 1}]}, "unknown keys"),
        ({"modes": "imm_cv"}, "list"),
        ({"transition": [[0.5, 0.4], [0.5, 0.5]]}, "transition"),
        ({"sensors": [{"name": "a", "kind": "sonar"}]}, "kind"),
        ({"P0": np.zeros((5, 5))}, "P0"),
        ({"x0": [0.0, 0.3]}, "x0"),
        ({"lead": -1}, "lead"),
        ({"node": 7}, "node"),
    ],
)
def test_factory_rejects_bad_specs(kwargs, msg):
    args = {"modes": MODES, "transition": TRANSITION, "sensors": SENSORS, "variant": "imm2",
            "x0": X0, "P0": P0, "lead": 1, "max_delay": 4}
    args.update(kwargs)
    with pytest.raises(ValueError, match=msg):
        make_imm(**args)


def test_factory_accepts_names_and_objects():
    from pd_service.estimation.imm import range_bearing
    from pd_service.estimation.nonlinear.registry import make_model

    op = make_imm(["imm_cv", make_model("imm_ct")], TRANSITION,
                  [range_bearing("a", [0, 0], 0.3, 0.05)], "single", X0, P0, lead=0, max_delay=0)
    assert op.sensor_names == ["a"] and op.variant == "single" and op.n == 5
