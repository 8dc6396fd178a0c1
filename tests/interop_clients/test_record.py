"""`ucr record` against the emulated chain, read back by readers nobody here wrote: the Python
`mcap` library with mcap-ros2-support's decoder, rosbags' AnyReader, yourdfpy for the URDF."""

from __future__ import annotations

import json
import math
import re
import time
from collections import Counter

import numpy as np
import pytest

from .conftest import EXPECTED_TOPICS, GOAL, REPO, ROBOT_FILE

pytestmark = pytest.mark.timeout(240)


def _read_all(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        msgs = list(reader.iter_decoded_messages(log_time_order=True))
    return summary, msgs


def test_python_mcap_reader_decodes_every_message_with_ros2_schemas(recording):
    path, _, err = recording
    summary, msgs = _read_all(path)
    assert summary is not None and summary.statistics.message_count == len(msgs) > 100
    channels = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    for topic, typename in EXPECTED_TOPICS.items():
        assert topic in channels, topic
        assert channels[topic].name == typename and channels[topic].encoding == "ros2msg"
    assert all(c.message_encoding == "cdr" for c in summary.channels.values())
    assert summary.statistics.chunk_count >= 1
    assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
    # progress on the terminal: duration, messages, bytes
    assert re.search(r"recording .*run\.mcap\s+[\d.]+ s\s+\d+ messages\s+[\d.]+ (B|KiB|MiB)", err)


def test_rosbags_anyreader_deserializes_every_message(recording):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path, _, _ = recording
    summary, msgs = _read_all(path)
    counts = Counter()
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, _t, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] += 1
    assert sum(counts.values()) == len(msgs)
    assert counts == Counter(schema_channel[1].topic for schema_channel in msgs)


def test_recorded_joint_states_reach_the_goal_and_name_kappa_phi(recording):
    path, _, _ = recording
    _, msgs = _read_all(path)
    js = [m.decoded_message for m in msgs if m.channel.topic == "/joint_states"]
    last = dict(zip(js[-1].name, js[-1].position, strict=True))
    assert list(js[-1].name) == [f"segment_{i}/{v}" for i in (1, 2, 3) for v in ("kappa", "phi")]
    for seg, (kappa, phi) in GOAL.items():
        assert last[f"{seg}/kappa"] == pytest.approx(kappa, abs=0.05)
        assert math.remainder(last[f"{seg}/phi"] - phi, 2 * math.pi) == pytest.approx(0, abs=0.05)
    assert last["segment_2/kappa"] == pytest.approx(0.0, abs=0.05)
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in js]
    assert stamps == sorted(stamps) and abs(stamps[-1] - time.time()) < 120


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _tf_tree(*messages):
    """(child -> (parent, 4x4 transform), world(frame) -> 4x4 in the root frame) from decoded
    tf2_msgs/TFMessages (the later ones' edges replace the earlier ones')."""
    edges = {}
    for msg in messages:
        for tr in msg.transforms:
            t = np.eye(4)
            t[:3, :3] = _quat_matrix(tr.transform.rotation)
            v = tr.transform.translation
            t[:3, 3] = v.x, v.y, v.z
            edges[tr.child_frame_id] = (tr.header.frame_id, t)

    def world(frame):
        if frame not in edges:
            return np.eye(4)
        parent, t = edges[frame]
        return world(parent) @ t

    return edges, world


def test_tf_tree_and_arcs_follow_the_recorded_bend(recording):
    """/tf_static + /tf compose to each segment's tip as the U(C)RDF FK places it (within the
    pseudo-rigid export's error), and /ucr/arcs ends exactly at the FK tip."""
    from ucrdf.fk import RobotKinematics
    from ucrdf.parser import load

    path, _, _ = recording
    _, msgs = _read_all(path)
    last = {}
    for m in msgs:
        last[m.channel.topic] = m.decoded_message
    edges, world = _tf_tree(last["/tf_static"], last["/tf"])

    def stamp_of(msg):
        return msg.header.stamp.sec, msg.header.stamp.nanosec

    stamp = stamp_of(last["/tf"].transforms[0])
    js = [
        m.decoded_message
        for m in msgs
        if m.channel.topic == "/joint_states" and stamp_of(m.decoded_message) == stamp
    ][0]  # the state /tf was computed from
    pos = dict(zip(js.name, js.position, strict=True))
    robot = load(ROBOT_FILE)
    cfg = {n: {"kappa": pos[f"{n}/kappa"], "phi": pos[f"{n}/phi"]} for n in robot.bendables}
    fk = RobotKinematics(robot).fk(cfg, strict=False)
    subdivided = [f for f in edges if "_prb" in f]
    assert len(subdivided) >= 3 * 10 * 2  # frames along every arc
    for b in robot.bendables.values():
        assert np.linalg.norm(world(b.child)[:3, 3] - fk[b.child][:3, 3]) < 2e-3
        assert np.allclose(world(b.child)[:3, :3], fk[b.child][:3, :3], atol=1e-6)
    arcs = {m.text: m for m in last["/ucr/arcs"].markers}
    for name, b in robot.bendables.items():
        m = arcs[name]
        assert m.type == 4 and len(m.points) >= 10  # LINE_STRIP
        assert stamp_of(m) == stamp
        tip = m.points[-1]
        assert np.linalg.norm([tip.x, tip.y, tip.z] - fk[b.child][:3, 3]) < 1e-9


def test_robot_description_is_the_exported_urdf_and_ucrdf_is_kept(recording, tmp_path):
    import yourdfpy

    path, _, _ = recording
    _, msgs = _read_all(path)
    by_topic = {m.channel.topic: m.decoded_message for m in msgs}
    urdf_path = tmp_path / "desc.urdf"
    urdf_path.write_text(by_topic["/robot_description"].data)
    urdf = yourdfpy.URDF.load(str(urdf_path), load_meshes=False)
    assert "segment_1_prb0" in urdf.link_map and len(urdf.actuated_joint_names) == 3 * 21
    assert by_topic["/ucr/robot_description_ucrdf"].data == ROBOT_FILE.read_text()


def test_goal_and_result_are_recorded(recording):
    path, result, _ = recording
    _, msgs = _read_all(path)
    results = [json.loads(m.decoded_message.data) for m in msgs
               if m.channel.topic == "/ucr/trajectory/results"]  # fmt: skip
    goals = [json.loads(m.decoded_message.data) for m in msgs
             if m.channel.topic == "/ucr/trajectory/goals"]  # fmt: skip
    assert result["id"] in {g["id"] for g in goals}
    mine = [r for r in results if r["id"] == result["id"]]
    assert mine and mine[-1]["state"] == "succeeded"


def test_segment_status_and_loop_statistics_are_diagnostics(recording):
    path, _, _ = recording
    _, msgs = _read_all(path)
    segs = [m.decoded_message for m in msgs if m.channel.topic == "/ucr/segments"]
    for seg in segs:
        assert [s.name for s in seg.status] == ["ucr/segment_1", "ucr/segment_2", "ucr/segment_3"]
        assert all(s.level in (0, 1, 3) for s in seg.status)
    # at least one poll found every segment measured (OK) with its uid (a loaded machine may
    # make a segment miss a cycle at the moment of another poll: WARN)
    assert any(all(s.level == 0 and s.hardware_id for s in seg.status) for seg in segs)
    loop = [m.decoded_message for m in msgs if m.channel.topic == "/ucr/loop_stats"][-1]
    keys = {kv.key: kv.value for kv in loop.status[0].values}
    assert float(keys["cycles"]) > 0 and "jitter_us.p99" in keys


def test_commanded_goal_is_recorded_as_joint_trajectory(recording):
    """The goal the test sent (segment_1 and segment_3 at 1.5 s) is in the file as the daemon
    accepted it, every bendable of the cJTC filled in (segment_2 kept straight)."""
    path, result, _ = recording
    _, msgs = _read_all(path)
    cmds = [m.decoded_message for m in msgs if m.channel.topic == "/ucr/trajectory/commanded"]
    # one per goal sent: the fixture sends it again after an abort a loaded host caused
    assert len(cmds) == len(result["sent"]), (len(cmds), result["sent"])
    cmd = cmds[-1]
    names = [f"segment_{i}/{v}" for i in (1, 2, 3) for v in ("kappa", "phi")]
    assert list(cmd.joint_names) == names
    assert len(cmd.points) == 1
    pt = cmd.points[0]
    assert pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9 == pytest.approx(1.5)
    pos = dict(zip(names, pt.positions, strict=True))
    for seg, (kappa, phi) in GOAL.items():
        assert pos[f"{seg}/kappa"] == pytest.approx(kappa, abs=1e-5)
        assert pos[f"{seg}/phi"] == pytest.approx(phi, abs=1e-5)
    assert pos["segment_2/kappa"] == pytest.approx(0.0, abs=0.02)  # where straighten() left it
    # and the lossless JSON of the daemon's goal_accepted event names the goal that ran
    events = [json.loads(m.decoded_message.data) for m in msgs if m.channel.topic == "/ucr/events"]
    accepted = [e for e in events if e.get("event") == "goal_accepted"]
    assert [e["goal"] for e in accepted] == result["sent"]
    # and each event is a line for log panels on /rosout (rcl_interfaces/Log), as many
    logs = [m.decoded_message for m in msgs if m.channel.topic == "/rosout"]
    assert len(logs) == len(events)
    lines = [(x.level, x.name) for x in logs if x.name == "ucr.goal_accepted"]
    assert lines == [(20, "ucr.goal_accepted")] * len(result["sent"])  # INFO


def test_channels_carry_rosbag2_offered_qos_profiles(recording):
    """rosbag2's MCAP channel metadata (offered_qos_profiles YAML) as rosbags reads it:
    latched topics transient_local depth 1, the others volatile; all reliable."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosReliability
    from rosbags.typesys import Stores, get_typestore

    path, _, _ = recording
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
    assert set(EXPECTED_TOPICS) <= set(qos)
    for topic, profiles in qos.items():
        assert len(profiles) == 1, (topic, profiles)
        q = profiles[0]
        assert q.reliability == QosReliability.RELIABLE, topic
        latched = topic in ("/robot_description", "/ucr/robot_description_ucrdf", "/tf_static")
        want = QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE
        assert q.durability == want, (topic, q)
        assert q.depth == (1 if latched else 100 if topic.startswith("/tf") else 10), (topic, q)


def test_joint_state_velocities_are_the_rate_of_the_recorded_positions(recording):
    """/joint_states velocity: one per name, κ̇ (1/m/s) and φ̇ (rad/s) equal to the backward
    difference of consecutive positions (header stamps), read with rosbags; known while moving."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path, _, _ = recording
    js = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == "/joint_states"]
        for conn, _t, raw in reader.messages(connections=conns):
            js.append(reader.deserialize(raw, conn.msgtype))
    assert all(len(m.velocity) == len(m.name) == len(m.position) for m in js)
    i = list(js[0].name).index("segment_1/kappa")
    checked = moving = 0
    for a, b in zip(js, js[1:], strict=False):
        ta = a.header.stamp.sec + a.header.stamp.nanosec * 1e-9
        tb = b.header.stamp.sec + b.header.stamp.nanosec * 1e-9
        v = b.velocity[i]
        if not math.isfinite(v) or tb - ta > 0.2:
            continue
        # stamps are the daemon's sample times mapped to wall clock: same differences
        assert v == pytest.approx((b.position[i] - a.position[i]) / (tb - ta), rel=1e-3, abs=1e-3)
        checked += 1
        moving += abs(v) > 0.2
    assert checked > 0.8 * len(js), (checked, len(js))
    assert moving >= 5, moving  # the recorded goal bends segment_1 to 2 1/m in 1.5 s
    # φ̇ is unknown (NaN) while straight, known while bent
    p = list(js[0].name).index("segment_1/phi")
    assert math.isnan(js[1].velocity[p]) or js[1].position[i] >= 0.02
    assert math.isfinite(js[-1].velocity[p]) and abs(js[-1].velocity[p]) < 0.5


def test_a_refused_foxglove_server_leaves_no_file_behind(rig, tmp_path):
    """Issue 16 audit: `ucr record` created the MCAP before it checked the Foxglove options or
    bound the port, so a refused address (no token) or a port in use exited 1 leaving an empty
    file, and the retry was refused because that file "exists"."""
    import os
    import socket
    import subprocess
    import sys

    from .conftest import REPO

    url = rig.url
    env = {k: v for k, v in os.environ.items() if k != "UCR_FOXGLOVE_TOKEN"}

    def record(*extra: str) -> tuple[int, str]:
        path = tmp_path / "stub.mcap"
        res = subprocess.run(
            [sys.executable, "-m", "tools.cli", "record", "-o", str(path), "--url", url,
             "--robot", str(ROBOT_FILE), "--duration", "2", *extra],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert not path.exists(), (extra, res.stderr)
        return res.returncode, res.stderr

    code, err = record("--foxglove-port", "0", "--foxglove-host", "192.0.2.2")  # no token
    assert code == 1 and "token" in err and "Traceback" not in err, err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        code, err = record("--foxglove-port", str(busy.getsockname()[1]))
        assert code == 1 and "Traceback" not in err, err


def test_every_closed_chunk_is_fsynced(tmp_path, monkeypatch):
    """Issue 16 audit: the docs promised a file that survives a power cut, but a closed chunk
    was only handed to the OS (no fsync): it could still be lost from the page cache."""
    import os

    from interop import record
    from interop.sinks import Fanout
    from interop.topics import RobotTopics
    from ucrdf.parser import load

    synced: list[int] = []
    real = os.fsync
    monkeypatch.setattr(record.os, "fsync", lambda fd: (synced.append(fd), real(fd))[1])
    sink = record.McapSink(tmp_path / "r.mcap", flush_interval=0.0)
    fd = sink._file.fileno()
    topics = RobotTopics(load(ROBOT_FILE), "", 4)
    js = {"t": 0.0, "names": ["segment_1"], "kappa": [1.0], "phi": [0.0]}
    size = len(synced)
    Fanout([sink]).publish(topics.joint_states(js, 1_700_000_000_000_000_000))
    assert len(synced) > size and set(synced) == {fd}  # the chunk just closed is on disk
    sink.close()
    assert len(synced) >= 2  # the summary of a clean stop too


def test_foxglove_host_alone_serves_on_the_default_port_and_serve_options_need_a_server():
    """Issue 16 audit: `--foxglove-host H` without `--foxglove-port` was silently ignored (no
    server, no word); now it serves on 8766 (as `ucr foxglove`). The Foxglove door's options
    without any server are a usage error (test_cli.py)."""
    from interop.record import foxglove_address
    from tools.cli import build_parser

    def address(*extra: str):
        return foxglove_address(build_parser().parse_args(["record", "-o", "r.mcap", *extra]))

    assert address() == ("127.0.0.1", None)
    assert address("--foxglove-host", "0.0.0.0") == ("0.0.0.0", 8766)
    assert address("--foxglove-port", "9000") == ("127.0.0.1", 9000)
    assert address("--foxglove-host", "::1", "--foxglove-port", "0") == ("::1", 0)


def test_rigid_joints_are_recorded_in_joint_states_and_tf(tmp_path):
    """/joint_states carries every bendable "plus rigid joints" and /tf the whole tree; the
    recorded rig (softrobot3) has no rigid joint, so a hybrid arm (three revolute joints and a
    continuum wrist) is recorded to a real MCAP file here, with its joints away from zero, and
    read back by rosbags' AnyReader: the rigid joints are in /joint_states with their positions
    (velocity NaN: the daemon does not measure them), and /tf_static + /tf compose every link,
    the tool among them, where the U(C)RDF's FK puts it (within the pseudo-rigid export's
    error)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from interop import record
    from interop.sinks import Fanout, channels_of
    from interop.topics import TOPICS, RobotTopics
    from ucrdf.fk import RobotKinematics
    from ucrdf.parser import load

    path = REPO / "robots" / "hybrid_arm.ucrdf"
    robot = load(path)
    topics = RobotTopics(robot, path.read_text(), 4)
    rigid = {"shoulder_yaw": 0.4, "shoulder_pitch": -0.3, "elbow": 0.9}
    js = {"t": 1.0, "names": ["wrist"], "kappa": [5.0], "phi": [0.7], "valid": [True],
          "rigid": {k: {"position": v, "measured": False} for k, v in rigid.items()}}  # fmt: skip
    out = tmp_path / "arm.mcap"
    sink = record.McapSink(out, flush_interval=0.0)
    fan = Fanout([sink])
    fan.advertise(channels_of(TOPICS))
    t_ns = 1_700_000_000_000_000_000
    for m in [*topics.static_messages(t_ns), topics.joint_states(js, t_ns), topics.tf(js, t_ns)]:
        fan.publish(m)
    sink.close()

    got: dict[str, object] = {}
    with AnyReader([out], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, _t, raw in reader.messages():
            got[conn.topic] = reader.deserialize(raw, conn.msgtype)
    state = got["/joint_states"]
    pos = dict(zip(state.name, state.position, strict=True))
    vel = dict(zip(state.name, state.velocity, strict=True))
    for name, value in rigid.items():
        assert pos[name] == pytest.approx(value), (name, state.name)
        assert math.isnan(vel[name])
    assert pos["wrist/kappa"] == pytest.approx(5.0) and pos["wrist/phi"] == pytest.approx(0.7)

    _, world = _tf_tree(got["/tf_static"], got["/tf"])
    config = {"wrist": {"kappa": 5.0, "phi": 0.7}, **rigid}
    fk = RobotKinematics(robot).fk(config, strict=False)
    for link in ("shoulder", "upper_arm", "forearm", "wrist_base"):  # rigid: exact
        assert np.allclose(world(link), fk[link], atol=1e-9), link
    assert np.linalg.norm(world("tool")[:3, 3] - fk["tool"][:3, 3]) < 2e-3
    assert np.allclose(world("tool")[:3, :3], fk["tool"][:3, :3], atol=1e-6)
    # and the joints moved it: not where the straight, zeroed arm has its tool
    assert np.linalg.norm(world("tool")[:3, 3] - RobotKinematics(robot).fk()["tool"][:3, 3]) > 0.1


def test_a_write_error_stops_the_recording_at_once_exit_1(rig, tmp_path):
    """Defect: after `No space left on device` the recorder went on "recording" for the whole
    --duration and exited 0."""
    from tests.cli_run import run_ucr

    t = time.monotonic()
    res = run_ucr("record", "-o", "/dev/full", "--overwrite", "--duration", "30",
                  "--flush-interval", "0.2", "--url", rig.url,
                  "--robot", str(ROBOT_FILE))  # fmt: skip
    assert time.monotonic() - t < 25, res.stderr
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if not ln.startswith("recording ")]
    assert lines == ["ucr: recording stopped: cannot write /dev/full: No space left on device"]


def test_a_file_that_cannot_be_created_is_a_sentence(rig):
    """Defect: `ucr: [Errno 2] No such file or directory: '/proc/x.mcap'`."""
    from tests.cli_run import run_ucr

    res = run_ucr("record", "-o", "/proc/x.mcap", "--duration", "1", "--url", rig.url,
                  "--robot", str(ROBOT_FILE))  # fmt: skip
    assert res.returncode == 1 and res.stderr.strip().splitlines() == [
        "ucr: cannot create /proc/x.mcap: No such file or directory"
    ], res.stderr
