# ruff: noqa: E501  (the rule table reads best one rule per line)
"""The nonlinear model kinds on the wire: "unscented" and "imm".

Round trips, one test per validation rule (through the wire, checking the reason a person
reads), linear specs unchanged byte for byte, and the conversion to the backends' plain
factories (same estimator as the factory called directly, refusals with the reason).
"""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from pydantic import ValidationError

from pd_service.backends import build, command_dim, imm_sensor
from pd_service.wire import SensorSpec, SessionSpec, WireError, decode, encode
from pd_service.wire.convert import (
    check_command,
    check_measurement,
)
from pd_service.wire.messages import AdaptSpec, ImmModelSpec, ModeSpec, UnscentedModelSpec
from tests.wire.factories import (
    DELETE,
    OMNI_Q0,
    SIGMA_BEARING,
    STATIONS,
    command,
    imm_spec,
    measurement,
    omni_spec,
    paper_spec,
    set_field,
)

#: A small linear SessionSpec as encoded by the protocol before the nonlinear kinds existed
#: (session "old": A = [[1, 0.1], [0, 1]], B = [[0], [0.1]], Q = 0.01 I, sensor "pos"
#: H = [1, 0], R = 0.25, delay 1, interval 2, lead 3, max_delay 4).
OLD_LINEAR_SPEC = bytes.fromhex(
    "8ca17601a773657373696f6ea36f6c64a9706572696f645f6e730aa865706f63685f6e7300a56d6f64656c84"
    "a46b696e64a66c696e656172a14182a57368617065920202a46461746194cb3ff0000000000000cb3fb99999"
    "9999999acb0000000000000000cb3ff0000000000000a14282a57368617065920201a46461746192cb000000"
    "0000000000cb3fb999999999999aa15182a57368617065920202a46461746194cb3f847ae147ae147bcb0000"
    "000000000000cb0000000000000000cb3f847ae147ae147ba2783082a573686170659102a46461746192cb00"
    "00000000000000cb0000000000000000a2503082a57368617065920202a46461746194cb3ff0000000000000"
    "cb0000000000000000cb0000000000000000cb3ff0000000000000a773656e736f72739185a46e616d65a370"
    "6f73a14882a57368617065920102a46461746192cb3ff0000000000000cb0000000000000000a15282a57368"
    "617065920101a46461746191cb3fd0000000000000a564656c617901a8696e74657276616c02a46c65616403"
    "a96d61785f64656c617904ad7075626c6973685f657665727901ac636f6d6d616e645f686f6c64a4686f6c64")


# ---------------------------------------------------------------- compatibility ----------

def test_old_linear_spec_decodes_and_encodes_to_the_same_bytes():
    spec = decode(OLD_LINEAR_SPEC, SessionSpec)
    assert spec.model.kind == "linear" and spec.sensors[0].kind == "linear"
    assert spec.sensors[0].station is None and spec.n == 2 and spec.r == 1
    assert encode(spec) == OLD_LINEAR_SPEC


def test_linear_sensors_are_written_as_before():
    raw = msgpack.unpackb(encode(paper_spec()))
    assert [list(s) for s in raw["sensors"]] == [["name", "H", "R", "delay", "interval"]] * 2
    # an explicit kind "linear" is accepted and not written back
    raw["sensors"][0]["kind"] = "linear"
    raw["sensors"][1]["station"] = None
    spec = decode(msgpack.packb(raw), SessionSpec)
    assert spec == paper_spec() and encode(spec) == encode(paper_spec())


def test_nonlinear_sensors_are_written_without_h():
    raw = msgpack.unpackb(encode(omni_spec()))
    assert list(raw["sensors"][0]) == ["name", "R", "delay", "interval", "kind"]
    raw = msgpack.unpackb(encode(imm_spec(position=True)))
    assert list(raw["sensors"][0]) == ["name", "R", "delay", "interval", "kind", "station"]
    assert list(raw["sensors"][3]) == ["name", "R", "delay", "interval", "kind"]


@pytest.mark.parametrize("make", [omni_spec, lambda: omni_spec(adapt=False, sigma=True),
                                  imm_spec, lambda: imm_spec(position=True, variant="single")])
def test_round_trip(make):
    spec = make()
    data = encode(spec)
    back = decode(data, SessionSpec)
    assert back == spec and hash(back) == hash(spec) and encode(back) == data


def test_dimensions():
    u, i = omni_spec(), imm_spec(position=True)
    assert (u.n, u.r, [s.m for s in u.sensors]) == (6, None, [3])
    assert (i.n, i.r, [s.m for s in i.sensors]) == (5, None, [2, 2, 2, 2])


def test_params_keep_ints_and_floats():
    spec = decode(encode(omni_spec()), SessionSpec)
    params = spec.model.params
    assert type(params["mass"]) is int and type(params["period_s"]) is float
    assert params["Q"] == OMNI_Q0
    # Python callers may pass numpy scalars and 1-D arrays: stored as plain numbers / lists
    m = UnscentedModelSpec(model="omni3", params={"mass": np.float64(9.5), "n": np.int64(3),
                                                  "Q": np.array(OMNI_Q0)})
    assert m.params == {"mass": 9.5, "n": 3, "Q": OMNI_Q0}
    assert type(m.params["mass"]) is float and type(m.params["n"]) is int


# ---------------------------------------------------------------- validation -------------

def arr(*shape_then_data):
    *shape, data = shape_then_data
    return {"shape": list(shape), "data": [float(v) for v in data]}


def reason(obj: dict) -> str:
    with pytest.raises(WireError) as info:
        decode(msgpack.packb(obj, use_bin_type=True), SessionSpec)
    return info.value.reason


U = "unscented"
I = "imm"  # noqa: E741
IP = "imm+position"
L = "linear"
RAW = {
    U: lambda: msgpack.unpackb(encode(omni_spec())),
    I: lambda: msgpack.unpackb(encode(imm_spec())),
    IP: lambda: msgpack.unpackb(encode(imm_spec(position=True))),
    L: lambda: msgpack.unpackb(encode(paper_spec())),
}
KINDS = "model must be a map whose 'kind' is one of: linear, unscented, imm"

CASES = [
    # -- model kind
    (U, "model.kind", "ukf", f"SessionSpec.model: {KINDS}"),
    (U, "model.kind", None, f"SessionSpec.model: {KINDS}"),
    (U, "model.extra", 1, "SessionSpec.model.unscented.extra: Extra inputs are not permitted"),
    (U, "model.model", DELETE, "SessionSpec.model.unscented.model: Field required"),
    (U, "model.model", "Omni3", "SessionSpec.model.unscented.model: String should match pattern"),
    # -- params
    (U, "model.params", [1.0], "SessionSpec.model.unscented.params: must be a map: parameter name -> number or list of numbers"),
    (U, "model.params.mass", True, "SessionSpec.model.unscented.params.mass: expected a number or a list of numbers, got bool"),
    (U, "model.params.mass", None, "params.mass: expected a number or a list of numbers, got nil"),
    (U, "model.params.mass", "10", "params.mass: expected a number or a list of numbers, got str"),
    (U, "model.params.mass", {"a": 1}, "params.mass: expected a number or a list of numbers, got dict"),
    (U, "model.params.mass", math.nan, "params.mass: must be a finite number (no NaN or infinity)"),
    (U, "model.params.mass", [1.0, math.inf], "params.mass: must be a finite number"),
    (U, "model.params.mass", [], "params.mass: a list holds 1..256 numbers, got 0"),
    (U, "model.params.mass", [0.5] * 257, "params.mass: a list holds 1..256 numbers, got 257"),
    (U, "model.params.mass", [[1.0]], "params.mass: expected a number or a list of numbers, got list"),
    (U, "model.params.bad-name", 1, "params: 'bad-name' is not a parameter name"),
    (U, "model.params", {f"p{i}": 1 for i in range(33)}, "params: at most 32 entries, got 33"),
    # -- adapt
    (U, "model.adapt.method", "kalman", "SessionSpec.model.unscented.adapt.method: Input should be 'mit' or 'sage_husa'"),
    (U, "model.adapt.indices", DELETE, "SessionSpec.model.unscented.adapt.indices: Field required"),
    (U, "model.adapt.indices", [], "adapt.indices: List should have at least 1 item"),
    (U, "model.adapt.indices", [3, 3], "SessionSpec.model.unscented.adapt.indices: must be distinct, got [3, 3]"),
    (U, "model.adapt.indices", [64], "adapt.indices.0: Input should be less than 64"),
    (U, "model.adapt.indices", [3.0], "adapt.indices.0: Input should be a valid integer"),
    (U, "model.adapt.indices", [2, 6], "SessionSpec.model.unscented.adapt.indices: [2, 6] must be < n=6 (x0 has 6 values)"),
    (U, "model.adapt.window", 0, "adapt.window: Input should be greater than or equal to 1"),
    (U, "model.adapt.window", 10_001, "adapt.window: Input should be less than or equal to 10000"),
    (U, "model.adapt.window", 20.0, "adapt.window: Input should be a valid integer"),
    (U, "model.adapt.eta", 0.0, "adapt.eta: Input should be greater than 0"),
    (U, "model.adapt.eta", math.inf, "adapt.eta: Input should be a finite number"),
    (U, "model.adapt.rule", "fast", "adapt.rule: Input should be 'normalised' or 'plain'"),
    (U, "model.adapt.max_gap", 101, "adapt.max_gap: Input should be less than or equal to 100"),
    (U, "model.adapt.forgetting", 0.9, "SessionSpec.model.unscented.adapt.forgetting: forgetting does not apply to method 'mit'"),
    (U, "model.adapt.method", "sage_husa", "SessionSpec.model.unscented.adapt.window: window, eta do not apply to method 'sage_husa'"),
    (U, "model.adapt.q_min", [1e-9], "adapt.q_min: must have one value per index (3), got 1"),
    (U, "model.adapt.q_max", [0.0, 1.0, 1.0], "adapt.q_max.0: Input should be greater than 0"),
    (U, "model.adapt.extra", 1, "adapt.extra: Extra inputs are not permitted"),
    # -- sigma
    (U, "model.sigma", {"alpha": 0.0}, "SessionSpec.model.unscented.sigma.alpha: Input should be greater than 0"),
    (U, "model.sigma", {"alpha": 1.0, "gamma": 1.0}, "sigma.gamma: Extra inputs are not permitted"),
    (U, "model.sigma", {"kappa": -6.0}, "SessionSpec.model.unscented.sigma.kappa: n + kappa must be > 0 (n=6, kappa=-6.0)"),
    # -- timing
    (U, "lead", 1001, "SessionSpec.lead: 1001 exceeds 1000 for a 'unscented' model (every step of lead is propagated at each prediction)"),
    (I, "lead", 1001, "SessionSpec.lead: 1001 exceeds 1000 for a 'imm' model"),
    # -- prior
    (U, "x0", arr(5, [0.0] * 5), "SessionSpec.P0: must be 5x5 (x0 has 5 values), got shape [6, 6]"),
    (U, "P0", arr(6, 6, (-np.eye(6)).ravel()), "SessionSpec.P0: must be positive semi-definite"),
    # -- sensors of an unscented model
    (U, "sensors.0.kind", "linear", "SessionSpec.sensors.0.H: is required for a sensor of kind 'linear' (z = H x + v)"),
    (U, "sensors.0.kind", "lidar", "SessionSpec.sensors.0.kind: Input should be 'linear', 'model', 'range_bearing' or 'position'"),
    (U, "sensors.0.H", arr(3, 6, [0.0] * 18), "SessionSpec.sensors.0.H: is only for kind 'linear'; a 'model' sensor's h(x) is the model's"),
    (U, "sensors.0.station", arr(2, [0.0, 0.0]), "SessionSpec.sensors.0.station: is only for kind 'range_bearing', not 'model'"),
    (U, "sensors.0.R", arr(3, 2, [0.0] * 6), "SessionSpec.sensors.0.R: must be square, got shape [3, 2]"),
    (U, "sensors.0.R", arr(1, 1, [-1.0]), "SessionSpec.sensors.0.R: must be positive semi-definite"),
    (U, "sensors.0.kind", "position", "SessionSpec.sensors.0.R: must be 2x2 for kind 'position' (z has 2 values), got shape [3, 3]"),
    # -- imm model
    (I, "model.modes", [{"model": "imm_cv", "params": {}}], "SessionSpec.model.imm.modes: List should have at least 2 items after validation, not 1"),
    (I, "model.modes", [{"model": "imm_cv", "params": {}}] * 9, "SessionSpec.model.imm.modes: List should have at most 8 items after validation, not 9"),
    (I, "model.modes.1.model", DELETE, "SessionSpec.model.imm.modes.1.model: Field required"),
    (I, "model.modes.1.extra", 1, "SessionSpec.model.imm.modes.1.extra: Extra inputs are not permitted"),
    (I, "model.modes.1.params.sigma_accel", -math.inf, "SessionSpec.model.imm.modes.1.params.sigma_accel: must be a finite number"),
    (I, "model.transition", arr(3, 3, np.eye(3).ravel()), "SessionSpec.model.imm.transition: must be 2x2 (2 modes), got shape [3, 3]"),
    (I, "model.transition", arr(2, 2, [1.1, -0.1, 0.005, 0.995]), "SessionSpec.model.imm.transition: entries must be >= 0"),
    (I, "model.transition", arr(2, 2, [0.9, 0.2, 0.005, 0.995]), "SessionSpec.model.imm.transition: every row must sum to 1 (off by 0.1)"),
    (I, "model.transition", arr(2, 2, [0.995, 0.005 + 2e-9, 0.005, 0.995]), "imm.transition: every row must sum to 1 (off by 2e-09)"),
    (I, "model.transition", DELETE, "SessionSpec.model.imm.transition: Field required"),
    (I, "model.variant", "federated", "SessionSpec.model.imm.variant: Input should be 'single', 'centralised', 'imm1' or 'imm2'"),
    (I, "model.variant", DELETE, "SessionSpec.model.imm.variant: Field required"),
    (I, "model.mu0", arr(3, [0.5, 0.25, 0.25]), "SessionSpec.model.imm.mu0: must have 2 values (2 modes), got 3"),
    (I, "model.mu0", arr(2, [0.7, 0.7]), "SessionSpec.model.imm.mu0: must be >= 0 and sum to 1"),
    (I, "model.mu0", arr(2, [1.5, -0.5]), "SessionSpec.model.imm.mu0: must be >= 0 and sum to 1"),
    (I, "model.node", 3, "SessionSpec.model.imm.node: 3 must index one of the 3 sensors"),
    (I, "model.node", 16, "SessionSpec.model.imm.node: Input should be less than 16"),
    (I, "model.node", -1, "SessionSpec.model.imm.node: Input should be greater than or equal to 0"),
    (I, "model.kappa", -5.0, "SessionSpec.model.imm.kappa: n + kappa must be > 0 (n=5, kappa=-5.0)"),
    (I, "model.kappa", math.nan, "SessionSpec.model.imm.kappa: Input should be a finite number"),
    # -- sensors of an imm model
    (I, "sensors.0.station", DELETE, "SessionSpec.sensors.0.station: is required for kind 'range_bearing'"),
    (I, "sensors.0.station", arr(3, [0.0] * 3), "SessionSpec.sensors.0.station: must have 2 values (xi, eta), got 3"),
    (I, "sensors.0.station", [9.5, -8.5], "SessionSpec.sensors.0.station: expected an array"),
    (I, "sensors.0.R", arr(2, 2, [0.09, 0.01, 0.01, 0.004]), "SessionSpec.sensors.0.R: must be diagonal with positive entries for kind 'range_bearing': diag(sigma_range^2, sigma_bearing^2)"),
    (I, "sensors.0.R", arr(2, 2, [0.09, 0.0, 0.0, 0.0]), "SessionSpec.sensors.0.R: must be diagonal with positive entries"),
    (I, "sensors.0.R", arr(1, 1, [0.09]), "SessionSpec.sensors.0.R: must be 2x2 for kind 'range_bearing' (z has 2 values), got shape [1, 1]"),
    (I, "sensors.0.H", arr(2, 5, [0.0] * 10), "SessionSpec.sensors.0.H: is only for kind 'linear'"),
    (IP, "sensors.3.R", arr(2, 2, [1.0, 1.0, 1.0, 1.0]), "SessionSpec.sensors.3.R: must be positive definite for kind 'position' (the IMM filter uses R^-1)"),
    (IP, "sensors.3.station", arr(2, [0.0, 0.0]), "SessionSpec.sensors.3.station: is only for kind 'range_bearing', not 'position'"),
    (I, "x0", arr(6, [0.0] * 6), "SessionSpec.P0: must be 6x6 (x0 has 6 values), got shape [5, 5]"),
    # -- a linear model keeps its rules and names the model kind in the error
    (L, "model.kind", "other", f"SessionSpec.model: {KINDS}"),
    (L, "sensors.0.H", DELETE, "SessionSpec.sensors.0.H: is required for a sensor of kind 'linear' (z = H x + v)"),
]


@pytest.mark.parametrize("base, path, value, expected", CASES,
                         ids=[f"{c[0]}.{c[1]}={str(c[2])[:20]}" for c in CASES])
def test_rule(base, path, value, expected):
    got = reason(set_field(RAW[base](), path, value))
    assert expected in got, got


def _kind_swap(base: str, index: int, **fields) -> dict:
    obj = RAW[base]()
    sensor = obj["sensors"][index]
    for k in ("H", "station", "kind"):
        sensor.pop(k, None)
    sensor.update(fields)
    return obj


@pytest.mark.parametrize("base, fields, expected", [
    (L, {"kind": "model"}, "SessionSpec.sensors.0.kind: 'model' ('camera') does not fit a 'linear' model (use: linear)"),
    (U, {"kind": "range_bearing", "station": arr(2, [0.0, 0.0]), "R": arr(2, 2, [1.0, 0.0, 0.0, 1.0])},
     "SessionSpec.sensors.0.kind: 'range_bearing' ('pose') does not fit a 'unscented' model (use: model)"),
    (U, {"kind": "linear", "H": arr(3, 6, np.eye(3, 6).ravel())},
     "SessionSpec.sensors.0.kind: 'linear' ('pose') does not fit a 'unscented' model (use: model)"),
    (I, {"kind": "model"}, "SessionSpec.sensors.0.kind: 'model' ('st1') does not fit a 'imm' model (use: range_bearing, position)"),
])
def test_sensor_kind_must_fit_the_model(base, fields, expected):
    got = reason(_kind_swap(base, 0, **fields))
    assert expected in got, got


def test_transition_tolerance():
    ok = set_field(RAW[I](), "model.transition", arr(2, 2, [0.995, 0.005 + 5e-10, 0.005, 0.995]))
    assert decode(msgpack.packb(ok), SessionSpec).model.transition[0, 1] == 0.005 + 5e-10


def test_python_construction():
    with pytest.raises(ValidationError, match="indices: must be distinct"):
        AdaptSpec(indices=[1, 1])
    with pytest.raises(ValidationError, match="transition: every row must sum to 1"):
        ImmModelSpec(modes=[ModeSpec(model="a"), ModeSpec(model="b")],
                     transition=np.ones((2, 2)), variant="imm2")
    with pytest.raises(ValidationError, match="x: expected a number"):
        UnscentedModelSpec(model="omni3", params={"x": np.array([[1.0]])})
    with pytest.raises(ValidationError, match="station: is required"):
        SensorSpec(name="st", kind="range_bearing", R=np.eye(2), delay=0, interval=1)
    assert UnscentedModelSpec(model="omni3").params == {}


# ---------------------------------------------------------------- conversion -------------

def _drive(estimators, steps, measure, command=None):
    """Feed every estimator the same calls; return their predictions per step."""
    out = [[] for _ in estimators]
    for k in range(steps):
        u = None if command is None else command(k)
        samples = measure(k)
        for est in estimators:
            if u is not None:
                assert est.add_command(k + 5, u, now=k)
            for sensor, s, z in samples:
                est.add_measurement(sensor, s, z, now=k)
        for i, est in enumerate(estimators):
            out[i].append(est.predict(k))
    return out


def _pose(k: int) -> np.ndarray:
    t = 0.01 * k
    return np.array([0.3 * np.sin(t), 0.2 * (1 - np.cos(t)), 0.5 * t])


def test_unscented_spec_builds_the_factorys_estimator():
    from pd_service.estimation.nonlinear.factory import make_unscented

    spec = omni_spec()
    op = build(spec).est
    direct = make_unscented(
        "omni3", {"period_s": 0.01, "mass": 10, "Q": OMNI_Q0}, x0=np.zeros(6),
        P0=np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3]), lead=5, max_delay=10,
        command_hold="hold", adapt={"method": "mit", "indices": [3, 4, 5], "window": 20,
                                    "eta": 0.1},
        sigma=None, sensors=["pose"], sensor_R={"pose": 1e-8 * np.eye(3)})
    rng = np.random.default_rng(3)
    late = {}

    def measure(k):
        late.setdefault(k + int(rng.integers(0, 4)), []).append((k, _pose(k)))
        return [("pose", s, z) for s, z in late.pop(k, [])]

    a, b = _drive([op, direct], 80, measure, lambda k: np.array([0.1, -0.05, 0.02]) if k % 10 == 0 else None)
    for p, q in zip(a, b, strict=True):
        assert p.step == q.step and p.newest_step == q.newest_step
        np.testing.assert_array_equal(p.x, q.x)
        np.testing.assert_array_equal(p.P, q.P)
    assert op.counters == direct.counters and op.counters["accepted"] >= 75


def _range_bearing(k: int, station) -> np.ndarray:
    xi, eta = 0.03 * k, 0.01 * k
    dx, dy = xi - station[0], eta - station[1]
    return np.array([math.hypot(dx, dy), math.atan2(dy, dx)])


@pytest.mark.parametrize("variant", ["single", "centralised", "imm1", "imm2"])
def test_imm_spec_builds_the_factorys_estimator(variant):
    from pd_service.estimation.imm.factory import make_imm

    spec = imm_spec(variant=variant, node=1, position=True)
    op = build(spec).est
    direct = make_imm(
        modes=[{"model": "imm_cv", "params": {"period_s": 0.1, "sigma_accel": 0.003}},
               {"model": "imm_ct", "params": {"period_s": 0.1, "sigma_accel": 0.0016,
                                              "sigma_turn_step": 0.00349}}],
        transition=[[0.995, 0.005], [0.005, 0.995]],
        sensors=[{"name": f"st{i + 1}", "kind": "range_bearing", "station": list(st),
                  "sigma_range": 0.3, "sigma_bearing": SIGMA_BEARING}
                 for i, st in enumerate(STATIONS)]
        + [{"name": "cam", "kind": "position", "R": [[0.04, 0.01], [0.01, 0.04]]}],
        variant=variant, x0=[0.0, 0.3, 0.0, 0.0, 0.0],
        P0=np.diag([0.25, 0.0025, 0.25, 0.0025, np.deg2rad(1.0) ** 2]), lead=5, max_delay=10,
        node=1)
    assert op.variant == variant

    def measure(k):
        got = [(f"st{i + 1}", k - 1, _range_bearing(k - 1, st)) for i, st in enumerate(STATIONS)
               if k >= 1 and (k + i) % 3]
        if k % 2 == 0:
            got.append(("cam", k, np.array([0.03 * k, 0.01 * k])))
        return got

    a, b = _drive([op, direct], 40, measure)
    for p, q in zip(a, b, strict=True):
        assert p.step == q.step and p.newest_step == q.newest_step
        # the spec's R against the literal sigmas squared
        np.testing.assert_allclose(p.x, q.x, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(p.P, q.P, rtol=1e-9, atol=1e-15)
    assert op.counters == direct.counters and op.counters["accepted"] > 50


def test_imm_sensor_maps():
    spec = imm_spec(position=True)
    rb = imm_sensor(spec.sensors[0])
    R = rb.pop("R")
    assert rb == {"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5]}
    np.testing.assert_array_equal(R, np.diag([0.3**2, SIGMA_BEARING**2]))
    pos = imm_sensor(spec.sensors[3])
    np.testing.assert_array_equal(pos["R"], [[0.04, 0.01], [0.01, 0.04]])


def _unscented(**model) -> SessionSpec:
    base = omni_spec(adapt=False)
    return base.model_copy(update={"model": UnscentedModelSpec(**model)})


@pytest.mark.parametrize("make, expected", [
    (lambda: _unscented(model="no-such-model"), "SessionSpec.model: refused by the estimator: model: unknown model 'no-such-model' (registered: "),
    (lambda: _unscented(model="omni3", params={"wheels": 4}), "SessionSpec.model: refused by the estimator: model 'omni3': bad parameters"),
    (lambda: _unscented(model="omni3", params={"mass": -1.0}), "SessionSpec.model: refused by the estimator: mass: must be a positive number"),
    (lambda: _unscented(model="omni3", params={"mass": [1.0, 2.0]}), "SessionSpec.model: refused by the estimator: model 'omni3': bad parameters"),
    (lambda: omni_spec(adapt=False).model_copy(update={"x0": np.zeros(5), "P0": np.eye(5)}), "SessionSpec.x0: refused by the estimator: x0: expected length 6, got 5"),
    (lambda: omni_spec().model_copy(update={"sensors": [SensorSpec(name="gps", kind="model", R=np.eye(3), delay=0, interval=1)]}), "SessionSpec.sensors: refused by the estimator: sensors: unknown ['gps']"),
    (lambda: omni_spec().model_copy(update={"sensors": [SensorSpec(name="pose", kind="model", R=np.eye(2), delay=0, interval=1)]}), "SessionSpec.sensors: refused by the estimator: sensor_R['pose']: expected shape (3, 3), got (2, 2)"),
    (lambda: _unscented(model="omni3", params={"Q": [0.0] * 6}, adapt=AdaptSpec(indices=[3])), "SessionSpec.model.unscented.adapt.indices: refused by the estimator: indices: adapted entries of Q must start > 0"),
    (lambda: imm_spec().model_copy(update={"x0": np.zeros(4), "P0": np.eye(4)}), "SessionSpec.P0: refused by the estimator: P0: expected shape (5, 5), got (4, 4)"),
    (lambda: imm_spec().model_copy(update={"model": imm_spec().model.model_copy(update={"modes": [ModeSpec(model="imm_cv"), ModeSpec(model="omni3")]})}), "SessionSpec.model.imm.modes: refused by the estimator: modes: all modes need the same n and nu"),
    (lambda: imm_spec().model_copy(update={"model": imm_spec().model.model_copy(update={"modes": [ModeSpec(model="imm_cv"), ModeSpec(model="nope")]})}), "SessionSpec.model: refused by the estimator: model: unknown model 'nope'"),
])
def test_refused_by_the_estimator(make, expected):
    with pytest.raises(WireError) as info:
        build(make())
    assert info.value.reason.startswith(expected), info.value.reason


def test_command_dim_and_check_command():
    u, i = omni_spec(), imm_spec()
    nu_u, nu_i = command_dim(u), command_dim(i)
    assert command_dim(paper_spec()) == 1 and nu_u == 3 and nu_i == 0
    check_command(command(session="u1", u=np.array([0.1, 0.2, 0.3])), u, nu_u)
    check_command(command(session="u1", u=np.array([0.1, 0.2, 0.3])), u, r=3)
    with pytest.raises(WireError, match=r"^Command.u: expected 3 values \(model 'omni3' has 3 inputs\), got 1$"):
        check_command(command(session="u1"), u, nu_u)
    with pytest.raises(WireError, match=r"^Command.u: session 'i1' takes no commands \(its model has no inputs\)$"):
        check_command(command(session="i1"), i, nu_i)
    with pytest.raises(WireError, match="refused by the estimator: model: unknown model"):
        command_dim(_unscented(model="nope"))


def test_check_measurement_uses_the_sensor_R_dimension():
    u, i = omni_spec(), imm_spec()
    check_measurement(measurement(session="u1", sensor="pose", z=np.zeros(3)), u)
    check_measurement(measurement(session="i1", sensor="st2", z=np.array([10.0, 0.5])), i)
    with pytest.raises(WireError, match=r"^Measurement.z: expected 3 values for sensor 'pose', got 2$"):
        check_measurement(measurement(session="u1", sensor="pose"), u)
    with pytest.raises(WireError, match="unknown sensor 'camera' \\(session 'i1' has: st1, st2, st3\\)"):
        check_measurement(measurement(session="i1", sensor="camera"), i)


@pytest.mark.parametrize("base, path, value, expected", CASES,
                         ids=[f"{c[0]}.{c[1]}={str(c[2])[:20]}" for c in CASES])
def test_every_rule_has_a_field_path(base, path, value, expected):
    head = reason(set_field(RAW[base](), path, value)).split(": ", 1)[0]
    assert head.startswith("SessionSpec.") and len(head) > len("SessionSpec."), head
