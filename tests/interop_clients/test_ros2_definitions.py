"""The ROS 2 message definitions ucr ships match the published ROS 2 (Jazzy) ones as rosbags
carries them, and our CDR bytes (mcap-ros2-support) decode with rosbags' independent CDR codec."""

from __future__ import annotations

import pytest

from interop import ros2

rosbags_typesys = pytest.importorskip("rosbags.typesys", reason="rosbags (dev extra) missing")


@pytest.fixture(scope="module")
def store():
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


def _published(store, typename):
    """Skip (with the reason) a type rosbags does not carry: control_msgs, checked instead by
    the FollowJointTrajectory hashes equal to rosidl's (test_zenoh_services.py)."""
    if typename not in store.fielddefs:
        pytest.skip(f"rosbags carries no {typename}: see test_zenoh_services.py")


@pytest.mark.parametrize("typename", ros2.shipped_types())
def test_shipped_definition_matches_the_published_one(store, typename):
    """Fields (names, types, array kinds) and constants equal the published definition."""
    from rosbags.typesys import get_types_from_msg

    _published(store, typename)
    ours = get_types_from_msg(ros2.message_text(typename), typename)[typename]
    published = store.fielddefs[typename]
    assert ours[0] == published[0], "constants differ"
    assert ours[1] == published[1], "fields differ"


@pytest.mark.parametrize("typename", ros2.shipped_types())
def test_concatenated_definition_generates_the_same_md5_as_published(store, typename):
    """The whole type tree (with dependencies, as the MCAP schema carries it) equals the
    published one: rosbags derives the same ROS 2 definition text and hash from it."""
    from rosbags.typesys import get_types_from_msg
    from rosbags.typesys.store import Typestore

    _published(store, typename)
    mine = Typestore()
    text = ros2.definition(typename)
    sections = text.split("=" * 80 + "\n")
    types = get_types_from_msg(sections[0], typename)
    for sec in sections[1:]:
        head, _, body = sec.partition("\n")
        assert head.startswith("MSG: ")
        types.update(get_types_from_msg(body, ros2.full_name(head[5:].strip())))
    mine.register(types)
    assert mine.generate_msgdef(typename, ros_version=2) == store.generate_msgdef(
        typename, ros_version=2
    )


SAMPLES = {
    "sensor_msgs/msg/JointState": {
        "header": {"stamp": {"sec": 12, "nanosec": 345}, "frame_id": "base"},
        "name": ["segment_1/kappa", "segment_1/phi"],
        "position": [2.0, -0.5],
    },
    "tf2_msgs/msg/TFMessage": {
        "transforms": [
            {
                "header": {"frame_id": "base"},
                "child_frame_id": "segment_1_prb0",
                "transform": {
                    "translation": {"x": 0.1, "y": 0.0, "z": 0.3},
                    "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
            }
        ]
    },
    "visualization_msgs/msg/MarkerArray": {
        "markers": [{"type": 4, "points": [{"x": 1.0, "y": 2.0, "z": 3.0}], "text": "s1"}]
    },
    "diagnostic_msgs/msg/DiagnosticArray": {
        "status": [{"level": 1, "name": "ucr/s1", "values": [{"key": "k", "value": "v"}]}]
    },
    "rcl_interfaces/msg/Log": {"level": 30, "name": "ucr.x", "msg": "hello"},
    "std_msgs/msg/String": {"data": "<robot/>"},
}


@pytest.mark.parametrize("typename", sorted(SAMPLES))
def test_our_cdr_decodes_with_rosbags(store, typename):
    pytest.importorskip("mcap_ros2", reason="the 'record' extra is not installed")
    data = ros2.codec(typename).encode(SAMPLES[typename])
    msg = store.deserialize_cdr(data, typename)
    assert store.serialize_cdr(msg, typename) == data  # byte for byte the same encoding


def test_definition_layout_is_rosbag2s():
    text = ros2.definition("sensor_msgs/msg/JointState")
    assert text.startswith("std_msgs/Header header\n")
    assert "\nMSG: std_msgs/Header\n" in text and "\nMSG: builtin_interfaces/Time\n" in text
    with pytest.raises(ros2.UnknownMessageType):
        ros2.definition("nav_msgs/msg/Odometry")
