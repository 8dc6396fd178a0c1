"""Review defects of interop/topics.py, the ROS 2 messages of `ucr record`, `ucr foxglove` and
`ucr zenoh`: an unplugged or invalid segment was drawn straight on /tf and /ucr/arcs (a pose never
measured), and /rosout levels were guessed from parts of the event names."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from .conftest import REPO, ROBOT_FILE

NAMES = ["segment_1", "segment_2", "segment_3"]
T0_NS = 1_700_000_000_000_000_000
#: /ucr/arcs colours (RGBA) as docs/ros2.md names them: measured (blue), stale (translucent grey)
BLUE = {"r": 0.1, "g": 0.6, "b": 0.95, "a": 1.0}
GREY = {"r": 0.6, "g": 0.6, "b": 0.6, "a": 0.4}


def _js(t: float, kappa: dict, phi: dict | None = None, valid: dict | None = None) -> dict:
    """An API joint_states message (host/controllers/jsb.py) for the bendables in ``kappa``."""
    names = list(kappa)
    phi = phi or {}
    valid = valid or {}
    return {"kind": "joint_states", "t": t, "names": names,
            "kappa": [kappa[n] for n in names], "phi": [phi.get(n, 0.6) for n in names],
            "valid": [valid.get(n, True) for n in names], "rigid": {}}  # fmt: skip


def _topics():
    from interop.topics import RobotTopics
    from ucrdf.parser import load

    return RobotTopics(load(ROBOT_FILE), ROBOT_FILE.read_text(), 4)


def _record(tmp_path: Path, states: list[dict]) -> Path:
    """Write ``states`` as `ucr record` does (LiveFeed -> Fanout -> McapSink): /joint_states,
    /tf and /ucr/arcs of every state (viz rate high enough for each)."""
    from interop import record
    from interop.live import LiveFeed
    from interop.sinks import Fanout, channels_of
    from interop.topics import TOPICS

    out = tmp_path / "run.mcap"
    sink = record.McapSink(out, flush_interval=0.0)
    fan = Fanout([sink])
    fan.advertise(channels_of(TOPICS))
    feed = LiveFeed(None, _topics(), fan, viz_rate=1000.0)
    next_viz = 0.0
    for js in states:
        next_viz = feed._publish_stream(js, next_viz)
    sink.close()
    return out


def _read(path: Path) -> list[tuple[str, object]]:
    """(topic, message) of every /joint_states, /tf and /ucr/arcs message, decoded by rosbags
    (independent of ucr's CDR); the mcap library's ROS 2 decoder must agree on the count."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    topics = ("/joint_states", "/tf", "/ucr/arcs")
    got = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        for conn, _t, raw in reader.messages(connections=conns):
            got.append((conn.topic, reader.deserialize(raw, conn.msgtype)))
    with path.open("rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        assert sum(1 for _ in r.iter_decoded_messages(topics=list(topics))) == len(got)
    return got


def _by_sample(got: list[tuple[str, object]]) -> list[dict[str, object]]:
    """Group the decoded messages per joint state: [{topic: message}, ...]."""
    out: list[dict[str, object]] = []
    for topic, msg in got:
        if topic == "/joint_states":
            out.append({})
        out[-1][topic] = msg
    return out


def _seg3_tf(tf) -> dict[str, tuple]:
    return {t.child_frame_id: (t.transform.rotation.x, t.transform.rotation.y,
                               t.transform.rotation.z, t.transform.rotation.w)
            for t in tf.transforms if t.child_frame_id.startswith("segment_3")}  # fmt: skip


def _arc(arcs, name: str):
    found = [m for m in arcs.markers if m.text == name]
    return found[0] if found else None


def _tip(marker) -> np.ndarray:
    p = marker.points[-1]
    return np.array([p.x, p.y, p.z])


def _rgba(marker) -> tuple[float, float, float, float]:
    c = marker.color
    return (c.r, c.g, c.b, c.a)


def test_an_unplugged_segment_keeps_its_last_measured_pose_and_a_stale_arc(tmp_path):
    """Defect: segment_3 held at κ = 1.5 and then unplugged (no longer in the joint states)
    was drawn straight on /tf and /ucr/arcs, in the measured colour, while /joint_states
    rightly left it out. Now it keeps the pose last measured (recorded, read back by rosbags
    and the mcap decoder) and its arc is drawn in STALE_COLOR, the others in ARC_COLOR."""
    bent = {"segment_1": 0.5, "segment_2": 0.8, "segment_3": 1.5}
    states = [_js(10.0 + 0.02 * i, bent) for i in range(3)]
    states += [_js(10.06 + 0.02 * i, {"segment_1": 0.5, "segment_2": 0.8}) for i in range(3)]
    samples = _by_sample(_read(_record(tmp_path, states)))
    assert len(samples) == 6 and all(len(s) == 3 for s in samples)
    measured, unplugged = samples[2], samples[3:]
    q_measured = _seg3_tf(measured["/tf"])
    assert q_measured and max(abs(q[0]) for q in q_measured.values()) > 0.01  # really bent
    tip = _tip(_arc(measured["/ucr/arcs"], "segment_3"))
    assert _rgba(_arc(measured["/ucr/arcs"], "segment_3")) == pytest.approx(tuple(BLUE.values()))
    for s in unplugged:
        assert "segment_3/kappa" not in s["/joint_states"].name
        q = _seg3_tf(s["/tf"])
        assert q.keys() == q_measured.keys()
        for frame, quat in q.items():  # the pose last measured, not straight (q.x 0)
            assert quat == pytest.approx(q_measured[frame], abs=1e-9), frame
        arc = _arc(s["/ucr/arcs"], "segment_3")
        assert np.allclose(_tip(arc), tip, atol=1e-9)
        assert _rgba(arc) == pytest.approx(tuple(GREY.values()))
        assert _rgba(arc) != pytest.approx(tuple(BLUE.values()))
        assert _rgba(_arc(s["/ucr/arcs"], "segment_1")) == pytest.approx(tuple(BLUE.values()))


@pytest.mark.parametrize(
    "invalid",
    [{"kappa": None}, {"phi": None}, {"valid": False, "kappa": 0.0, "phi": 0.0},
     {"kappa": float("nan")}],
    ids=["kappa-missing", "phi-missing", "not-valid-zeros", "kappa-nan"],
)  # fmt: skip
def test_an_invalid_sample_keeps_the_last_measured_pose(invalid):
    """Defect: a single sample of segment_3 without a valid measurement (κ or φ missing, or
    ``valid`` false with the daemon's placeholder zeros of a segment it never measured) made
    /tf and /ucr/arcs straight for that sample. Now the pose last measured, arc stale; and the
    next valid sample is drawn as measured again."""
    topics = _topics()
    bent = {"segment_1": 0.5, "segment_2": 0.8, "segment_3": 1.5}
    good = _js(5.0, bent, {"segment_3": 1.0})
    tf0 = topics.tf(good, T0_NS).msg["transforms"]
    arcs0 = topics.arcs(good, T0_NS).msg["markers"]
    bad = _js(5.02, bent, {"segment_3": 1.0})
    i = bad["names"].index("segment_3")
    for key, value in invalid.items():
        if key == "valid":
            bad["valid"][i] = value
        else:
            bad[key][i] = value
    topics.joint_states(bad, T0_NS + 1)
    tf1 = topics.tf(bad, T0_NS + 1).msg["transforms"]
    arcs1 = topics.arcs(bad, T0_NS + 1).msg["markers"]
    assert [t["transform"] for t in tf1] == [t["transform"] for t in tf0]
    assert [m["points"] for m in arcs1] == [m["points"] for m in arcs0]
    assert [m["color"] for m in arcs1] == [BLUE, BLUE, GREY]
    again = _js(5.04, {**bent, "segment_3": 1.2}, {"segment_3": 1.0})
    arcs2 = topics.arcs(again, T0_NS + 2).msg["markers"]
    assert [m["color"] for m in arcs2] == [BLUE] * 3
    assert arcs2[2]["points"] != arcs0[2]["points"]  # the new measurement
    from interop.topics import ARC_COLOR, STALE_COLOR

    assert (ARC_COLOR, STALE_COLOR) == (BLUE, GREY)  # the module's names for them


def test_a_segment_never_measured_has_no_transforms_and_no_arc():
    """Before a bendable is measured at all, nothing is made up for it: /tf has none of its
    joints (its child links have no transform to the root) and /ucr/arcs no marker for it nor
    for any bendable it carries (their place in the root frame depends on it). Was: straight."""
    topics = _topics()
    only_first = _js(1.0, {"segment_1": 0.7, "segment_3": 1.0})  # segment_2 never measured
    frames = {t["child_frame_id"] for t in topics.tf(only_first, T0_NS).msg["transforms"]}
    assert not any(f.startswith("segment_2") for f in frames), sorted(frames)
    assert any(f.startswith("segment_1") for f in frames)
    assert any(f.startswith("segment_3") for f in frames)  # measured: relative to its base
    arcs = topics.arcs(only_first, T0_NS).msg["markers"]
    assert [m["text"] for m in arcs] == ["segment_1"]
    assert [m["id"] for m in arcs] == [0]  # ids stay the bendable's index
    everything = _js(1.02, {"segment_1": 0.7, "segment_2": 0.2, "segment_3": 1.0})
    arcs = topics.arcs(everything, T0_NS).msg["markers"]
    assert [(m["id"], m["text"]) for m in arcs] == list(enumerate(NAMES))
    assert len(topics.tf(everything, T0_NS).msg["transforms"]) == len(topics.movable)


# -- /rosout levels ----------------------------------------------------------------------------

#: The emitter's name in host/ (Fanout.emit_event, passed on as _emit / _emit_event).
_EMITTERS = ("emit_event", "_emit", "_emit_event")


def _daemon_event_names() -> set[str]:
    """Every event name the daemon can emit, read from host/: the literal first argument of each
    call of the event emitter; the one call with a computed name (host/supervision.py, a
    segment's EVENT frame, ``name.lower()``) emits the lower-cased protocol EVENT_NAMES. Any
    other computed name fails here, so a new event cannot go without a level."""
    from protocol.constants import EVENT_NAMES

    names: set[str] = set()
    dynamic: list[str] = []
    for path in sorted((REPO / "host").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Call):
                continue
            func = node.func
            attr = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            if attr not in _EMITTERS:
                continue
            arg = node.args[0] if node.args else None
            if arg is None:
                arg = next((k.value for k in node.keywords if k.arg == "event"), None)
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                names.add(arg.value)
            else:
                where = f"{path.relative_to(REPO)}:{ast.unparse(arg) if arg else None}"
                dynamic.append(where)
    assert dynamic == ["host/supervision.py:name.lower()"], dynamic
    names |= {n.lower() for n in EVENT_NAMES.values()}
    assert len(names) > 25, sorted(names)  # the extraction found the emitters
    return names


def _feed_event_names() -> set[str]:
    """The events the feed makes itself (interop/): ``{"event": "<name>", …}`` literals, and
    the names given to live.py's ``_gap_event(feed, "<name>", …)``."""
    names: set[str] = set()
    for path in sorted((REPO / "interop").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Dict):
                for k, v in zip(node.keys, node.values, strict=True):
                    if isinstance(k, ast.Constant) and k.value == "event":
                        if isinstance(v, ast.Constant) and isinstance(v.value, str):
                            names.add(v.value)
            elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "_gap_event":
                arg = node.args[1]
                assert isinstance(arg, ast.Constant), f"{path}: {ast.unparse(node)}"
                names.add(arg.value)
    assert "goal_waypoints_incomplete" in names
    return names


def test_every_event_the_daemon_emits_has_an_explicit_rosout_level():
    """Defect: the level came from parts of the name ("hold", "fault", "lost", …). Now a table,
    which must name every event the daemon can emit (read from host/), its topology messages
    and the events the feed makes itself (read from interop/)."""
    from interop import topics

    expected = _daemon_event_names() | _feed_event_names() | {"topology"}
    EVENT_LEVELS = getattr(topics, "EVENT_LEVELS", {})  # noqa: N806 - the module's name
    missing = sorted(expected - EVENT_LEVELS.keys())
    assert not missing, f"events without a /rosout level in EVENT_LEVELS: {missing}"
    for name, level in EVENT_LEVELS.items():
        assert level in (20, 30, 40), name  # INFO, WARN, ERROR
        log = topics.RobotTopics.event({"kind": "event", "event": name, "message": "m"}, T0_NS)[0]
        assert log.msg["level"] == level and log.msg["name"] == f"ucr.{name}"
    topo = topics.RobotTopics.event({"kind": "topology", "reason": "rebuilt"}, T0_NS)[0]
    assert topo.msg["level"] == EVENT_LEVELS["topology"]


@pytest.mark.parametrize(
    ("name", "lowest", "highest"),
    [("segments_held", 30, 30), ("misaddressed", 30, 50), ("segment_refused", 30, 50),
     ("link_degraded", 30, 50), ("link_too_slow", 30, 50), ("fault_clear_sent", 20, 20),
     ("watchdog_tripped", 30, 50), ("fault", 40, 50), ("link_lost", 40, 50),
     ("manual_takeover", 30, 30), ("goal_accepted", 20, 20)],
)  # fmt: skip
def test_rosout_levels_the_review_found_wrong(name, lowest, highest):
    """Defect (review): segments_held was INFO (docs: WARN for holds); misaddressed,
    segment_refused, link_degraded, link_too_slow INFO; fault_clear_sent, the user's own
    request, ERROR."""
    from interop.topics import RobotTopics

    log = RobotTopics.event({"kind": "event", "event": name, "message": name}, T0_NS)[0]
    assert lowest <= log.msg["level"] <= highest, (name, log.msg["level"])


def test_an_unknown_event_gets_the_documented_default_level():
    """A name not in the table (a newer daemon's, or a segment event code this version does not
    know: ``event_<code>``) is WARN, EVENT_LEVEL_DEFAULT."""
    from interop.topics import RobotTopics

    for name in ("event_12", "something_new", "hold_info"):
        log = RobotTopics.event({"kind": "event", "event": name}, T0_NS)[0]
        assert log.msg["level"] == 30, name  # WARN
    from interop.topics import EVENT_LEVEL_DEFAULT, LOG_WARN

    assert EVENT_LEVEL_DEFAULT == LOG_WARN == 30


def test_docs_list_every_event_at_its_rosout_level():
    """docs/ros2.md "Log levels on /rosout" names each event of EVENT_LEVELS in the row of its
    level, and the default."""
    from interop import topics

    EVENT_LEVELS = getattr(topics, "EVENT_LEVELS", {})  # noqa: N806 - the module's name
    assert EVENT_LEVELS
    text = (REPO / "docs" / "ros2.md").read_text()
    start = text.index("### Log levels on /rosout")
    section = text[start : text.index("\n#", start + 5)]
    rows = {}
    for line in section.splitlines():
        m = re.match(r"\| (INFO|WARN|ERROR) \((\d+)\) \| (.*) \|$", line)
        if m:
            rows[int(m.group(2))] = set(re.findall(r"`([a-z_]+)`", m.group(3)))
    for level in set(EVENT_LEVELS.values()):
        want = {n for n, v in EVENT_LEVELS.items() if v == level}
        assert rows.get(level) == want, (level, sorted(want ^ rows.get(level, set())))
    assert "unknown" in section.lower() and "WARN" in section
