"""Every message survives encode -> decode unchanged (hypothesis)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pd_service.wire import MESSAGE_TYPES, Measurement, SessionSpec, WireError, decode, encode
from pd_service.wire.ros2 import (
    CommandBinding,
    OutputBinding,
    Ros2Binding,
    StateLayout,
    TopicBinding,
)
from tests.wire.factories import EXAMPLES, STRATEGIES, measurement, paper_spec

SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def test_every_message_type_has_an_example_and_a_strategy():
    assert set(EXAMPLES) == set(MESSAGE_TYPES) == set(STRATEGIES)


def _check_round_trip(msg) -> None:
    data = encode(msg)
    back = decode(data, type(msg))
    assert back == msg
    assert hash(back) == hash(msg)
    assert encode(back) == data  # canonical: same message, same bytes
    for name in type(msg).model_fields:  # arrays come back read-only float64
        value = getattr(back, name)
        if isinstance(value, np.ndarray):
            assert value.dtype == np.float64 and not value.flags.writeable
            np.testing.assert_array_equal(value, getattr(msg, name))


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_example_round_trip(msg_type):
    _check_round_trip(EXAMPLES[msg_type]())


@pytest.mark.parametrize("msg_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
def test_property_round_trip(msg_type):
    @SETTINGS
    @given(STRATEGIES[msg_type])
    def run(msg):
        _check_round_trip(msg)

    run()


@SETTINGS
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=64))
def test_float_values_are_bit_exact(values):
    m = measurement(z=np.array(values))
    back = decode(encode(m), type(m))
    assert [math.copysign(1.0, v) for v in back.z] == [math.copysign(1.0, v) for v in values]
    assert back.z.tolist() == values


def test_ints_in_data_are_floats():
    raw = msgpack.unpackb(encode(measurement()))
    raw["z"] = {"shape": [3], "data": [1, -2, 2**62]}
    m = decode(msgpack.packb(raw), Measurement)
    assert m.z.dtype == np.float64 and m.z.tolist() == [1.0, -2.0, float(2**62)]


def test_field_order_and_all_fields_on_the_wire():
    for msg_type, make in EXAMPLES.items():
        raw = msgpack.unpackb(encode(make()))
        # SessionSpec.ros2, .expire_s and .path are left off the wire when None (unset), and
        # stamp_rounding / robot_clock / command_timing / clock_asymmetry_ns at their defaults
        # (older specs' bytes)
        optional = ({"ros2", "expire_s", "stamp_rounding", "path", "robot_clock",
                     "command_timing", "clock_asymmetry_ns"} if msg_type is SessionSpec
                    else set())
        assert list(raw) == [f for f in msg_type.model_fields if f not in optional]
        assert raw["v"] == 1


def test_spec_with_ros2_topics_round_trips():
    spec = paper_spec()
    binding = Ros2Binding(
        sensors={"camera": TopicBinding(topic="/cam/point", msg_type="geometry_msgs/msg/PointStamped",
                                        fields=["x", "y"])},
        commands=CommandBinding(msg_type="geometry_msgs/msg/TwistStamped"),
        outputs=OutputBinding(layout=StateLayout(x=0, y=2, vx=1, vy=3, velocity_frame="world")))
    with_ros2 = SessionSpec.model_validate({**spec.model_dump(), "ros2": binding.model_dump()})
    raw = msgpack.unpackb(encode(with_ros2))
    assert raw["ros2"]["sensors"]["camera"]["fields"] == ["x", "y"]
    assert "path_topic" not in raw["ros2"]["outputs"]  # the default: the bytes stay as before
    back = decode(encode(with_ros2), SessionSpec)
    assert back == with_ros2 and back.ros2 == binding


def test_spec_with_an_estimated_robot_clock_and_echoed_commands_round_trips():
    spec = paper_spec().model_copy(update={"robot_clock": "estimated",
                                           "command_timing": "echoed",
                                           "clock_asymmetry_ns": -100_000_000})
    raw = msgpack.unpackb(encode(spec))
    assert (raw["robot_clock"], raw["command_timing"], raw["clock_asymmetry_ns"]) == \
        ("estimated", "echoed", -100_000_000)
    assert decode(encode(spec), SessionSpec) == spec
    assert not {"robot_clock", "clock_asymmetry_ns"} & set(msgpack.unpackb(encode(paper_spec())))
    with pytest.raises(WireError):
        decode(msgpack.packb({**spec.model_dump(), "clock_asymmetry_ns": 61 * 10**9},
                             use_bin_type=True), SessionSpec)


def test_encode_refuses_non_messages():
    with pytest.raises(WireError, match="expected a wire message"):
        encode({"v": 1})  # type: ignore[arg-type]


@pytest.mark.filterwarnings("ignore:Pydantic serializer warnings")
def test_encode_refuses_unencodable_values():
    bad = Measurement.model_construct(v=1, session="s1", sensor="c", seq=np.int64(1), step=0,
                                      t_ns=None, z=np.zeros(1), R=None)
    with pytest.raises(WireError, match="Measurement: cannot encode"):
        encode(bad)
