"""rmw_zenoh's wire format as ucr writes it, checked against what others published: the examples
of rmw_zenoh's design document, rosbags' per-distribution type stores (REP-2011 hashes computed
from their own copies of the ROS 2 definitions), and the command conversion's refusals."""

from __future__ import annotations

import math
import sys
from types import SimpleNamespace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from interop import ros2
from interop.topics import TOPICS
from interop.zenoh import rmw
from interop.zenoh.commands import TRAJECTORY_TYPE, CommandError, to_waypoints

pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")

from interop.ros2.type_hash import type_hash  # noqa: E402

# rmw_zenoh docs/design.md: demo_nodes_cpp's talker, domain 2, std_msgs/String, depth 7
DESIGN_STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_TALKER_PUB = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
    f"std_msgs::msg::dds_::String_/{DESIGN_STRING_HASH}/::,7:,:,:,,"
)
ALL_TYPES = sorted(set(TOPICS.values()) | {TRAJECTORY_TYPE})


def test_type_hash_of_string_is_the_one_in_rmw_zenohs_design_document():
    assert type_hash("std_msgs/msg/String") == DESIGN_STRING_HASH


@pytest.mark.parametrize("distro", ["ROS2_JAZZY", "ROS2_KILTED", "ROS2_LYRICAL"])
def test_type_hashes_equal_rosbags_distribution_stores(distro):
    """Every type we publish or take hashes as the named distribution's own definitions do, so
    the key expressions match a real node of that distribution (the --distro choices)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(getattr(Stores, distro))
    for t in ALL_TYPES:
        assert type_hash(t) == store.hash_rihs01(t), t


def test_type_hash_changes_with_the_definition(monkeypatch):
    """Computed from the definition, not looked up: one field renamed, another hash."""
    from interop.ros2 import type_hash as th

    before = type_hash("std_msgs/msg/String")
    real = ros2.message_text.__wrapped__

    def patched(name):
        return "string text\n" if ros2.full_name(name) == "std_msgs/msg/String" else real(name)

    th._store.cache_clear()
    th.type_hash.cache_clear()
    monkeypatch.setattr(ros2, "message_text", patched)
    try:
        assert th.type_hash("std_msgs/msg/String") != before
    finally:
        monkeypatch.undo()
        th._store.cache_clear()
        th.type_hash.cache_clear()
    assert type_hash("std_msgs/msg/String") == before


def test_key_expressions_follow_the_design_document():
    fqn = rmw.fully_qualified("/robot1", "chatter")
    key = rmw.topic_key(0, fqn, "std_msgs/msg/String", DESIGN_STRING_HASH)
    assert key == f"0/robot1/chatter/std_msgs::msg::dds_::String_/{DESIGN_STRING_HASH}"
    node = rmw.NodeId(2, "8b20917502ee955ac4476e0266340d5c", 0, "/", "talker")
    assert rmw.node_token(node) == "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
    tok = rmw.endpoint_token(
        node,
        10,
        rmw.PUBLISHER,
        "/chatter",
        "std_msgs/msg/String",
        DESIGN_STRING_HASH,
        rmw.Qos(depth=7),
    )
    assert tok == DESIGN_TALKER_PUB
    parsed = rmw.parse_endpoint_token(tok)
    assert (parsed.topic, parsed.typename, parsed.kind, parsed.qos.depth) == (
        "/chatter",
        "std_msgs/msg/String",
        "MP",
        7,
    )


def test_namespaced_tokens_mangle_every_slash():
    node = rmw.NodeId(0, "abc", 0, "/softrobot3", "ucr_bridge")
    assert rmw.node_token(node).endswith("/NN/%/%softrobot3/ucr_bridge")
    tok = rmw.endpoint_token(
        node,
        3,
        rmw.PUBLISHER,
        "/softrobot3/ucr/arcs",
        "visualization_msgs/msg/MarkerArray",
        "RIHS01_x",
        rmw.DEFAULT_QOS,
    )
    assert "/%softrobot3%ucr%arcs/visualization_msgs::msg::dds_::MarkerArray_/" in tok
    assert rmw.parse_endpoint_token(tok).namespace == "/softrobot3"


def test_qos_strings():
    assert rmw.DEFAULT_QOS.encode() == "::,10:,:,:,,"
    assert rmw.LATCHED_QOS.encode() == ":1:,1:,:,:,,"
    assert rmw.Qos(reliability=rmw.BEST_EFFORT, depth=42).encode() == "2::,:,:,:,,"
    for q in (rmw.DEFAULT_QOS, rmw.LATCHED_QOS, rmw.Qos(history=rmw.KEEP_ALL, depth=5)):
        assert rmw.decode_qos(q.encode()) == q


@given(st.integers(0, 2**63 - 1), st.integers(0, 2**63 - 1), st.binary(max_size=255))
def test_attachment_round_trip(seq, ts, gid):
    att = rmw.Attachment(seq, ts, gid)
    data = att.encode()
    assert len(data) == 17 + len(gid)
    assert rmw.Attachment.decode(data) == att


def test_attachment_layout_is_little_endian_seq_time_len_gid():
    data = rmw.Attachment(1, 2, bytes(range(16))).encode()
    assert data == (1).to_bytes(8, "little") + (2).to_bytes(8, "little") + b"\x10" + bytes(
        range(16)
    )


@pytest.mark.parametrize("data", [b"", b"\x00" * 16, b"\x00" * 16 + b"\x10" + b"\x01" * 3])
def test_attachment_decode_refuses_short_or_lying_input(data):
    with pytest.raises(ValueError):
        rmw.Attachment.decode(data)


def test_names():
    assert rmw.namespace_for("softrobot3") == "/softrobot3"
    assert rmw.namespace_for("soft-robot 3") == "/soft_robot_3"
    assert rmw.namespace_for("3arm") == "/_3arm"
    assert rmw.check_namespace("lab/robot_a") == "/lab/robot_a"
    for bad in ("/a-b", "/a//b", "/1a"):
        with pytest.raises(rmw.RosNameError):
            rmw.check_namespace(bad)
    with pytest.raises(rmw.RosNameError):
        rmw.check_node_name("ucr-bridge")
    assert rmw.fully_qualified("/r", "ucr/arcs") == "/r/ucr/arcs"
    assert rmw.fully_qualified("/r", "/rosout") == "/rosout"


def _traj(names, points):
    pts = [
        SimpleNamespace(
            positions=p,
            time_from_start=SimpleNamespace(sec=int(t), nanosec=int(round((t % 1) * 1e9))),
        )
        for t, p in points
    ]
    return SimpleNamespace(joint_names=names, points=pts)


BENDABLES = ["segment_1", "segment_2", "segment_3"]


def test_joint_trajectory_to_waypoints():
    msg = _traj(["segment_2/phi", "segment_2/kappa"], [(0.5, [0.3, 1.0]), (1.25, [0.3, 2.0])])
    assert to_waypoints(msg, BENDABLES) == [
        {"time_from_start": 0.5, "segments": {"segment_2": {"kappa": 1.0, "phi": 0.3}}},
        {"time_from_start": 1.25, "segments": {"segment_2": {"kappa": 2.0, "phi": 0.3}}},
    ]


@pytest.mark.parametrize(
    ("names", "points", "why"),
    [
        (["segment_9/kappa", "segment_9/phi"], [(1, [1, 0])], "unknown joint"),
        (["segment_1/kappa"], [(1, [1])], "both"),
        (["segment_1/kappa", "segment_1/phi"], [(1, [1])], "1 positions for 2"),
        (["segment_1/kappa", "segment_1/phi"], [(1, [math.nan, 0])], "finite"),
        (["segment_1/kappa", "segment_1/kappa"], [(1, [1, 1])], "repeats"),
        (["segment_1/x", "segment_1/phi"], [(1, [1, 1])], "unknown joint"),
    ],
)
def test_malformed_joint_trajectories_are_refused_with_a_reason(names, points, why):
    with pytest.raises(CommandError, match=why):
        to_waypoints(_traj(names, points), BENDABLES)


def test_zenoh_config_defaults_are_rmw_zenohs_session_defaults():
    pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")
    import json

    from interop.zenoh import config

    conf = config.build(config.SessionOptions(), environ={})
    get = lambda k: json.loads(conf.get_json(k))  # noqa: E731
    assert get("mode") == "peer"
    assert get("connect/endpoints") == ["tcp/localhost:7447"]
    assert get("listen/endpoints") == ["tcp/localhost:0"]
    assert get("scouting/multicast/enabled") is False
    conf = config.build(
        config.SessionOptions(mode="client", connect=["tcp/127.0.0.1:1"]),
        environ={config.ENV_OVERRIDE: "scouting/gossip/enabled=false"},
    )
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == []
    with pytest.raises(config.ZenohConfigError, match="bad Zenoh endpoint"):
        config.build(config.SessionOptions(connect=["127.0.0.1:7447"]), environ={})
    with pytest.raises(config.ZenohConfigError, match="no such file"):
        config.build(config.SessionOptions(config_file="/nonexistent.json5"), environ={})


def test_a_zenoh_config_file_leaves_multicast_scouting_off_unless_it_turns_it_on(tmp_path):
    """Defect: with `--zenoh-config FILE` (or $ZENOH_SESSION_CONFIG_URI) multicast scouting was
    left unset, so Zenoh's default (on) applied, though docs/ros2.md says it is off as in
    rmw_zenoh. Now off unless the file sets scouting/multicast/enabled or the flag is given."""
    pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")
    import json

    from interop.zenoh import config

    def multicast(text: str, name: str = "c.json5", flag: bool = False, env: bool = False):
        path = tmp_path / name
        path.write_text(text)
        opts = config.SessionOptions(config_file=None if env else str(path), multicast=flag)
        conf = config.build(opts, environ={config.ENV_CONFIG: str(path)} if env else {})
        return json.loads(conf.get_json("scouting/multicast/enabled"))

    docs_bridge = (  # docs/ros2.md's bridge.json5: says nothing about scouting
        '// bridge.json5\n{ mode: "client", connect: { endpoints: ["tls/router.lab:7447"] },\n'
        '  transport: { link: { tls: { root_ca_certificate: "/etc/ucr/zenoh/ca.pem" } } } }\n'
    )
    assert multicast(docs_bridge) is False
    assert multicast(docs_bridge, env=True) is False  # $ZENOH_SESSION_CONFIG_URI
    assert multicast("{ scouting: { multicast: { ttl: 2 } } }") is False
    assert multicast(docs_bridge, flag=True) is True
    assert multicast("{ scouting: { multicast: { enabled: true } } } // mine") is True
    assert multicast("{ scouting: { multicast: { enabled: false } } }", flag=True) is True
    assert multicast("scouting:\n  multicast:\n    enabled: true\n", "c.yaml") is True
    assert multicast("{ scouting: { multicast: { enabled: false } } }") is False


def test_missing_ros2_dependencies_give_one_line(monkeypatch, capsys):
    from interop.zenoh import cli

    monkeypatch.setattr(cli, "NEEDS", ("ucr_no_such_module_xyz",))
    rc = cli._guard(lambda a: 0)(SimpleNamespace(command="zenoh"))
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "pip install -e '" in err and "[ros2]'" in err
    assert "Traceback" not in err and sys.modules.get("ucr_no_such_module_xyz") is None
