"""``pd-operator --ros2``'s node on the in-memory bus: Twist / TwistStamped CDR on the bound
command topic's rmw_zenoh key, attachments counting up, node and publisher tokens."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rosbags")

from pd_client.tools.ros2_operator import Ros2OperatorNode  # noqa: E402
from pd_client.tools.ros2_robot import Ros2Options  # noqa: E402
from pd_service.ros2.attachment import decode_attachment  # noqa: E402
from pd_service.ros2.extract import extract_command  # noqa: E402
from pd_service.ros2.keys import parse_token, topic_keyexpr  # noqa: E402
from pd_service.ros2.messages import decode, type_hash  # noqa: E402
from pd_service.wire.ros2 import CommandBinding  # noqa: E402

from ..conftest import Collector  # noqa: E402


@pytest.mark.parametrize("msg_type", ["geometry_msgs/msg/Twist",
                                      "geometry_msgs/msg/TwistStamped"])
def test_operator_node_publishes_twists_on_the_rmw_zenoh_key(bus, msg_type):
    sink = Collector(bus, "**")
    t = bus.transport()
    node = Ros2OperatorNode(t, CommandBinding(topic="cmd_vel", msg_type=msg_type),
                            options=Ros2Options(domain_id=3, namespace="/bot1"),
                            clock=lambda: 1_700_000_000_123_000_000)
    key = topic_keyexpr(3, "/bot1/cmd_vel", msg_type, type_hash(msg_type))
    assert node.key == key
    node.send([0.5, -0.25])
    node.send(np.array([0.0, 0.1]))
    got = [s for s in sink.samples if s.key == key]
    assert len(got) == 2
    cmds = [extract_command(decode(s.payload, msg_type)) for s in got]
    np.testing.assert_array_equal(cmds[0].u, [0.5, -0.25])
    np.testing.assert_array_equal(cmds[1].u, [0.0, 0.1])
    if msg_type.endswith("TwistStamped"):
        assert cmds[0].stamp_ns == 1_700_000_000_123_000_000
    atts = [decode_attachment(s.attachment) for s in got]
    assert [a.sequence_number for a in atts] == [1, 2]
    assert all(a.gid == node.endpoint.gid() for a in atts)
    tokens = [parse_token(k) for k in sink.t.get_liveliness("@ros2_lv/**")]
    assert sorted(tk.kind for tk in tokens) == ["MP", "NN"]
    mp = next(tk for tk in tokens if tk.kind == "MP")
    assert (mp.domain_id, mp.node_name, mp.namespace, mp.topic, mp.ros_type) == (
        3, "operator", "/bot1", "/bot1/cmd_vel", msg_type)
    node.close()
    assert sink.t.get_liveliness("@ros2_lv/**") == []
