"""Clients nobody here wrote, in another language: @mcap/core reads our recording (indexed, and as
a stream after the recorder was killed mid-run) and @foxglove/ws-protocol subscribes to the live
Foxglove server; both decode the ROS 2 CDR with @foxglove/rosmsg2-serialization."""

from __future__ import annotations

import json
import re
import signal
import time

import pytest

from .conftest import (
    EXPECTED_TOPICS,
    GOAL,
    ROBOT_FILE,
    run_node,
    stop,
    straighten,
    ucr,
    wait_for,
)

pytestmark = pytest.mark.timeout(300)


def _python_counts(path) -> dict[str, int]:
    from collections import Counter

    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return dict(Counter(ch.topic for _, ch, _ in make_reader(f).iter_messages()))


def test_node_mcap_reader_reads_schemas_counts_and_every_message(recording, node_clients):
    path, _, _ = recording
    out = run_node(node_clients, "read_mcap.mjs", str(path))
    assert out["_returncode"] == 0, out["_stderr"]
    for topic, typename in EXPECTED_TOPICS.items():
        assert out["topics"][topic] == {"schema": typename, "encoding": "ros2msg",
                                        "messageEncoding": "cdr"}  # fmt: skip
    assert out["counts"] == _python_counts(path)
    assert out["decoded"] == sum(out["counts"].values()) == out["statistics"]
    last = dict(zip(out["last"]["/joint_states"]["name"], out["last"]["/joint_states"]["position"],
                    strict=True))  # fmt: skip
    for seg, (kappa, _) in GOAL.items():
        assert last[f"{seg}/kappa"] == pytest.approx(kappa, abs=0.05)


def test_sigkill_mid_run_leaves_a_file_readable_up_to_the_last_chunk(rig, tmp_path, node_clients):
    """`ucr record` killed with SIGKILL (no chance to write the summary): the Python mcap stream
    reader and @mcap/core's stream reader both read every message of the closed chunks."""
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader
    from mcap_ros2.decoder import DecoderFactory

    url = rig.ensure_whole()
    path = tmp_path / "killed.mcap"
    proc = ucr("record", "-o", str(path), "--url", url, "--robot", str(ROBOT_FILE),
               "--flush-interval", "0.3")  # fmt: skip
    try:
        # wait until several chunks are on disk (each flush adds one)
        assert wait_for(lambda: path.exists() and path.stat().st_size > 20_000, 60), (
            path.stat().st_size if path.exists() else None
        )
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    data = path.read_bytes()
    assert not data.endswith(b"\x89MCAP0\r\n")  # no footer magic: the file really was cut short

    decoder = DecoderFactory()
    n, topics = 0, set()
    with open(path, "rb") as f:
        try:
            for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                decoder.decoder_for(channel.message_encoding, schema)(message.data)
                n += 1
                topics.add(channel.topic)
        except (McapError, EOFError, ValueError):
            pass  # the torn last record
    assert n > 50 and {"/joint_states", "/tf", "/robot_description"} <= topics

    out = run_node(node_clients, "read_mcap.mjs", str(path), "--stream")
    assert out["_returncode"] == 0, out["_stderr"]
    assert out["complete"] is False
    assert out["decoded"] == n  # the same messages: everything up to the last whole chunk

    # and `ucr replay` plays it (reads up to the last chunk, no traceback)
    proc = ucr("replay", str(path), "--rate", "0", "--port", "0")
    outp, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    assert f"{n} messages replayed" in err


def test_a_foxglove_port_in_use_is_one_sentence_naming_the_address_once(rig):
    # before: "ucr: cannot serve Foxglove on 127.0.0.1:P: cannot listen on 127.0.0.1:P: ..."
    import socket

    url = rig.ensure_whole()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = ucr("foxglove", "--port", str(port), "--url", url, "--robot", str(ROBOT_FILE))
        _, err = proc.communicate(timeout=60)
    said = (
        f"ucr: cannot serve Foxglove: cannot listen on 127.0.0.1:{port}: address already in use "
        "(another program uses the port: --port P, or 0 for any free port)"
    )
    assert proc.returncode == 1 and err.strip().splitlines() == [said], err


def test_node_foxglove_client_decodes_live_joint_states(rig, node_clients):
    from host.api.client import connect

    url = rig.ensure_whole()
    proc = ucr("foxglove", "--port", "0", "--url", url, "--robot", str(ROBOT_FILE))
    try:
        fox_url = None

        def announced() -> bool:
            nonlocal fox_url
            line = proc.stderr.readline()
            m = re.search(r"(ws://127\.0\.0\.1:\d+)", line or "")
            fox_url = m.group(1) if m else None
            return fox_url is not None or proc.poll() is not None

        assert wait_for(announced, 60) and fox_url, "no server URL printed"
        with connect(url) as c:
            want = {n: s["kappa"] for n, s in c.status()["joint_states"].items()}
        out = run_node(node_clients, "foxglove_client.mjs", fox_url, "5")
        assert out["_returncode"] == 0, (out, out["_stderr"])
    finally:
        code, _, err = stop(proc)
    assert code == 130, err  # Ctrl-C (before: 0)
    assert out["serverInfo"]["capabilities"] == []  # read-only: no publish, services, params
    for topic, typename in EXPECTED_TOPICS.items():  # all advertised from the start
        assert out["channels"][topic]["schemaName"] == typename
        assert out["channels"][topic]["encoding"] == "cdr"
    assert out["robotDescription"] > 1000  # latched: sent to a client that came later
    js = out["jointStates"]
    assert len(js) == 5
    names = js[-1]["name"]
    assert names == [f"segment_{i}/{v}" for i in (1, 2, 3) for v in ("kappa", "phi")]
    last = dict(zip(names, js[-1]["position"], strict=True))
    for seg, kappa in want.items():
        assert last[f"{seg}/kappa"] == pytest.approx(kappa, abs=0.05)


ONE_SHOT = ("/ucr/trajectory/goals", "/ucr/trajectory/commanded", "/ucr/trajectory/results")


def test_node_foxglove_client_gets_the_one_shot_topics_of_a_single_goal(rig, node_clients):
    """Defect: the server advertised a topic with its first message, so no client could be
    subscribed to it yet: the one message of a one-shot topic (a goal's /ucr/trajectory/...)
    reached nobody. Every topic is advertised before data flows; a client that subscribes to
    what is advertised (as Foxglove does) and is watching when a goal is sent gets all three."""
    import subprocess

    from host.api.client import connect

    url = rig.ensure_whole()
    with connect(url) as c:
        straighten(c)  # before the server starts: it sees one goal only, the test's
    proc = ucr("foxglove", "--port", "0", "--url", url, "--robot", str(ROBOT_FILE))
    node = None
    try:
        fox_url = None

        def announced() -> bool:
            nonlocal fox_url
            m = re.search(r"(ws://127\.0\.0\.1:\d+)", proc.stderr.readline() or "")
            fox_url = m.group(1) if m else None
            return fox_url is not None or proc.poll() is not None

        assert wait_for(announced, 60) and fox_url, "no server URL printed"
        node = subprocess.Popen(["node", "foxglove_topics.mjs", fox_url, "90", *ONE_SHOT],
                                cwd=node_clients, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        assert node.stderr.readline().strip() == "ready", node.communicate(timeout=30)
        with connect(url) as c:  # one goal: goals, commanded and results once each
            pts = [{"time_from_start": 1.5, "segments": {n: {"kappa": k, "phi": p}
                    for n, (k, p) in GOAL.items()}}]  # fmt: skip
            c.send_trajectory(pts, timeout=30)
        outp, err = node.communicate(timeout=120)
        out = json.loads(outp.strip().splitlines()[-1])
    finally:
        if node is not None and node.poll() is None:
            node.kill()
            node.communicate()
        code, _, serr = stop(proc, signal.SIGTERM)
    assert code == 0, serr  # a requested stop
    assert set(EXPECTED_TOPICS) <= set(out["advertised"]), out  # all before any goal
    for topic in ONE_SHOT:
        assert out["counts"].get(topic, 0) >= 1, (topic, out, err)


def test_foxglove_refuses_a_non_loopback_address_without_a_token(rig):
    url = rig.ensure_whole()
    proc = ucr("foxglove", "--host", "0.0.0.0", "--url", url, "--robot", str(ROBOT_FILE))
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1
    assert "without a token" in err and "Traceback" not in err
