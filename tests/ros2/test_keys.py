"""rmw_zenoh key expressions and liveliness tokens against the examples of ros2/rmw_zenoh
docs/design.md (the version with type hashes and the compact QoS chunk, as in the Jazzy 0.2.x
releases; stored copy at commit 99a6a2bd10b949052f4f12c5854825dc005e95a5), copied verbatim."""

from __future__ import annotations

import pytest

from pd_service.ros2.errors import Ros2DecodeError
from pd_service.ros2.keys import (
    NodeIdentity,
    QoS,
    TopicEndpoint,
    bridge_keyexpr,
    dds_type_name,
    entity_gid,
    fully_qualified_name,
    mangle,
    parse_qos,
    parse_token,
    topic_keyexpr,
)
from pd_service.ros2.messages import type_hash

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

# design.md, "Topic and Service name mapping to Zenoh key expressions" (verbatim).
DOC_CHATTER_KEY = "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # noqa: E501
DOC_CHATTER_NS_KEY = "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # noqa: E501
# design.md, "Graph Cache" examples (verbatim). The document writes domain 2 in these token
# examples while saying "with ROS_DOMAIN_ID=0 by default"; the strings are reproduced as given.
DOC_LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DOC_LISTENER_SUB = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,"  # noqa: E501
DOC_TALKER_PUB = "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"  # noqa: E501


def test_rihs01_of_string_from_typestore_matches_design_doc() -> None:
    # The same hash the design document prints for std_msgs/msg/String, computed by rosbags.
    from pd_service.ros2.messages import typestore

    assert typestore().hash_rihs01("std_msgs/msg/String") == STRING_HASH


def test_topic_keys_match_design_doc() -> None:
    assert topic_keyexpr(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == DOC_CHATTER_KEY
    fq = fully_qualified_name("/robot1", "chatter")
    assert fq == "/robot1/chatter"
    assert topic_keyexpr(0, fq, "std_msgs/msg/String", STRING_HASH) == DOC_CHATTER_NS_KEY


def test_node_token_matches_design_doc() -> None:
    node = NodeIdentity(
        domain_id=2, session_id="aac3178e146ba6f1fc6e6a4085e77f21", node_id=0, name="listener"
    )
    assert node.token() == DOC_LISTENER_NODE


def test_endpoint_tokens_match_design_doc() -> None:
    listener = NodeIdentity(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener")
    sub = TopicEndpoint(listener, 10, "MS", "/chatter", "std_msgs/msg/String", STRING_HASH, QoS(depth=10))
    assert sub.token() == DOC_LISTENER_SUB
    talker = NodeIdentity(2, "8b20917502ee955ac4476e0266340d5c", 0, "talker")
    pub = TopicEndpoint(talker, 10, "MP", "/chatter", "std_msgs/msg/String", STRING_HASH, QoS(depth=7))
    assert pub.token() == DOC_TALKER_PUB
    assert pub.keyexpr() == "2/chatter/std_msgs::msg::dds_::String_/" + STRING_HASH


@pytest.mark.parametrize("token", [DOC_LISTENER_NODE, DOC_LISTENER_SUB, DOC_TALKER_PUB])
def test_parse_token_round_trips(token: str) -> None:
    p = parse_token(token)
    node = NodeIdentity(p.domain_id, p.session_id, p.node_id, p.node_name, p.namespace, p.enclave)
    if p.kind == "NN":
        assert node.token() == token
    else:
        assert p.kind in ("MP", "MS") and p.topic and p.ros_type and p.type_hash and p.qos
        ep = TopicEndpoint(node, p.entity_id, p.kind, p.topic, p.ros_type, p.type_hash, p.qos)  # type: ignore[arg-type]
        assert ep.token() == token


def test_namespace_and_enclave_are_mangled() -> None:
    node = NodeIdentity(0, "ab", 3, "pd_service", namespace="/robot1/sim", enclave="/secure")
    assert node.token() == "@ros2_lv/0/ab/3/3/NN/%secure/%robot1%sim/pd_service"
    ep = TopicEndpoint(
        node,
        4,
        "MP",
        node.resolve("odom_predicted"),
        "nav_msgs/msg/Odometry",
        type_hash("nav_msgs/msg/Odometry"),
    )
    assert (
        "/MP/%secure/%robot1%sim/pd_service/%robot1%sim%odom_predicted/nav_msgs::msg::dds_::Odometry_/"
        in ep.token()
    )
    assert ep.keyexpr().startswith("0/robot1/sim/odom_predicted/nav_msgs::msg::dds_::Odometry_/RIHS01_")


def test_qos_chunk() -> None:
    assert QoS().keyexpr() == "::,:,:,:,,"
    assert QoS(reliability="best_effort", depth=5).keyexpr() == "2::,5:,:,:,,"
    assert QoS(durability="transient_local", history="keep_all", depth=1).keyexpr() == ":1:2,1:,:,:,,"
    for q in (QoS(), QoS(reliability="best_effort", depth=5), QoS(durability="transient_local", depth=1)):
        assert parse_qos(q.keyexpr()) == q
    with pytest.raises(Ros2DecodeError):
        parse_qos("9::,5:,:,:,,")
    with pytest.raises(Ros2DecodeError):
        parse_qos("::,x:,:,:,,")


def test_names() -> None:
    assert mangle("/") == "%" and mangle("/robot1/chatter") == "%robot1%chatter"
    assert dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    assert fully_qualified_name("/", "cmd_vel") == "/cmd_vel"
    assert fully_qualified_name("/bot", "/tf") == "/tf"
    for bad in ("", "/", "a//b", "a/", "1abc", "~/x", "a b"):
        with pytest.raises(ValueError):
            fully_qualified_name("/", bad)
    with pytest.raises(ValueError):
        topic_keyexpr(0, "/chatter", "std_msgs/msg/String", "RIHS01_xyz")


def test_bridge_keys_follow_ros2dds() -> None:
    # zenoh-plugin-ros2dds ros2_utils.rs ros2_name_to_key_expr: drop the leading '/', prefix the
    # bridge namespace (without its '/').
    assert bridge_keyexpr("/cmd_vel") == "cmd_vel"
    assert bridge_keyexpr("/cmd_vel", "/bot1") == "bot1/cmd_vel"
    assert bridge_keyexpr("/robot/odom", "/") == "robot/odom"
    with pytest.raises(ValueError):
        bridge_keyexpr("cmd_vel")


def test_gid_is_xxh3_128_of_token_low_then_high() -> None:
    import xxhash

    gid = entity_gid(DOC_TALKER_PUB)
    assert len(gid) == 16
    v = xxhash.xxh3_128_intdigest(DOC_TALKER_PUB.encode())
    assert int.from_bytes(gid[:8], "little") == v & (2**64 - 1)
    assert int.from_bytes(gid[8:], "little") == v >> 64


def test_bad_tokens_refused() -> None:
    for bad in (
        "@ros2_lv/0/ab/0/0/XX/%/%/n",
        "@other/0/ab/0/0/NN/%/%/n",
        "@ros2_lv/0/ab/0/0/NN/%/%",
        DOC_TALKER_PUB.rsplit("/", 1)[0],
    ):
        with pytest.raises(Ros2DecodeError):
            parse_token(bad)
