"""Audit of issue 15 (the browser view), without a browser or a chain where the logic allows:
the token's scope, the robot file's content, escaping, display toggles, unreachable moves, the
stop reason, named materials, the tip trail and what `ucr view FILE` says when it falls back."""

from __future__ import annotations

import queue
import time

import pytest
from view_helpers import (
    CONTROL_TOKEN,
    NAMES,
    READ_TOKEN,
    ROBOT,
    ROOT,
    RawPage,
    fake_topology,
    two_token_server,
    wait_for,
)

pytestmark = pytest.mark.timeout(120)


class _Sub:
    def __init__(self, q: queue.Queue) -> None:
        self.q = q

    def __enter__(self) -> _Sub:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def get(self, timeout: float) -> dict | None:
        try:
            return self.q.get(timeout=timeout)
        except queue.Empty:
            return None


class _Daemon:
    """An API client on a pretend daemon running softrobot3; ``scope``: its token's."""

    def __init__(self, scope: str = "control") -> None:
        self.scope = scope
        self.pushes: queue.Queue = queue.Queue()
        self.topo = fake_topology(str(ROBOT))

    def topology(self) -> dict:
        return dict(self.topo)

    goals: list[str] = []

    def status(self) -> dict:
        return {"state": "connected", "segments": list(NAMES), "running_goals": list(self.goals),
                "active_controllers": ["jtc"]}  # fmt: skip

    def controllers(self) -> list:
        return []

    def call(self, op: str, **params):
        from host.api.client import ApiError

        if op not in ("ping", "status", "topology") and self.scope == "read":
            raise ApiError("forbidden", f"{op!r} needs a token with the control scope")
        raise ApiError("not_found", "no such upload")

    def subscribe(self, kinds, max_rate=None) -> _Sub:
        return _Sub(self.pushes)

    def close(self) -> None:
        pass


def _live(monkeypatch, daemon: _Daemon, robot_file: str | None = None, **kw):
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import view.source as vs
    from view.app import ViewApp

    monkeypatch.setattr(vs, "connect", lambda *a, **k: daemon)
    src = vs.LiveSource("ws://127.0.0.1:9", None, robot_file).start()
    return src, ViewApp(src, port=0, always_update=True, **kw).start()


def _markdown(raw: RawPage) -> str:
    return " ".join(str(m.get("props", {}).get("_markdown", "")) for m in raw.seen)


# -- 1. a read token ----------------------------------------------------------------------------
def test_the_scope_probe_tells_a_read_token_from_a_control_token():
    """For a daemon older than ``session``: the probe (a control-scope op that changes nothing)
    against the real API server answers forbidden to a read token, not_found to a control
    token."""
    from host.api.client import connect
    from view.source import LiveSource

    with two_token_server(publish_hz=100.0) as srv:
        with connect(srv.url, token=READ_TOKEN) as c:
            assert LiveSource._probe_scope(c) == "read"
        with connect(srv.url, token=CONTROL_TOKEN) as c:
            assert LiveSource._probe_scope(c) == "control"


def test_a_read_token_gives_no_page_controls_and_says_so(monkeypatch):
    """Defect (audit 15.1): control_enabled never looked at the token's scope: a read token got
    sliders, gizmo, Execute and Stop (each refused by the daemon only when used)."""
    src, app = _live(monkeypatch, _Daemon("read"))
    raw = None
    try:
        assert src.scope == "read"
        assert not app.control_enabled and not app.has_controls and app.page_token is None
        raw = RawPage(app.port)
        assert raw.read_until(lambda m: "read token" in str(m.get("props", {})), 30)
        raw.read_until(lambda m: False, 1.0)
        assert "view only: read token" in _markdown(raw)
        assert raw.labels("GuiSliderMessage") == [] and raw.labels("GuiButtonMessage") == []
        assert app.pages == {}
    finally:
        if raw is not None:
            raw.close()
        app.stop()


# -- 2. the robot file's content ----------------------------------------------------------------
def test_a_file_with_the_same_names_but_other_lengths_gets_no_controls(monkeypatch):
    """Defect (audit 15.2): only names were compared: a FILE with 0.39 m segments against the
    daemon's 0.316 m had full controls (the page drew and solved IK for another robot)."""
    from view.source import LiveSource

    long3 = ROOT / "tests" / "view" / "_long3.ucrdf"
    long3.write_text(ROBOT.read_text().replace('length="0.316"', 'length="0.39"'))
    try:
        import types

        from ucrdf.parser import load

        me = types.SimpleNamespace(_robot_file=str(long3))
        why = LiveSource._mismatch(me, load(long3), _Daemon().topo)
        assert "is not the daemon's robot" in why, why
        assert "segment_1 length: the daemon's 0.316, the file's 0.39" in why, why
        same = types.SimpleNamespace(_robot_file=str(ROBOT))
        assert LiveSource._mismatch(same, load(ROBOT), _Daemon().topo) == ""
    finally:
        long3.unlink()


# -- 3. escaping ----------------------------------------------------------------------------------
def test_untrusted_text_is_shown_literally_not_as_html():
    """Defect (audit 15.3): check errors, the mismatch and daemon/event text went into the page's
    markdown raw: `<tendon>` vanished and `<img src=x onerror=…>` became an element."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    from view.app import _who, md

    evil = "link <img src=x onerror=alert(1)> [x](javascript:alert(1)) <tendon>"
    out = md(evil)
    assert "<" not in out and ">" not in out and "&lt;tendon&gt;" in out, out
    assert "[x](" not in out and "\\[x\\](" in out, out  # no markdown link either
    line = _who({"last_event": evil, "manual": [], "goals": ["<b>g</b>"], "active": []}, None)
    assert "<img" not in line and "<b>" not in line, line


def test_check_errors_on_the_page_are_escaped(tmp_path):
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    from view.app import ViewApp
    from view.source import OfflineSource

    f = tmp_path / "r.ucrdf"
    f.write_text(ROBOT.read_text())
    src = OfflineSource(f).start()
    app = ViewApp(src, port=0, always_update=True).start()
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        evil = '<parent link="&lt;img src=x onerror=alert(1)&gt; &lt;tendon&gt;"/>'
        f.write_text(ROBOT.read_text().replace('<parent link="base"/>', evil, 1))
        assert wait_for(lambda: bool(src.snap.errors), 10)
        assert wait_for(lambda: "check errors" in app.g_errors.content, 5)
        assert "<img" not in app.g_errors.content, app.g_errors.content
        assert "&lt;tendon&gt;" in app.g_errors.content, app.g_errors.content
    finally:
        app.stop()


# -- 6. display toggles ---------------------------------------------------------------------------
def test_a_page_without_the_token_has_no_display_toggles(monkeypatch):
    """Defect (audit 15.6): Frames/Tendons/Tip trail were shared checkboxes every page had: a
    page opened without the token changed the operator's display. Now only pages with controls
    have them."""
    src, app = _live(monkeypatch, _Daemon())
    viewer = operator = None
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        viewer = RawPage(app.port)
        assert viewer.read_until(lambda m: "view only:" in str(m.get("props", {})), 30)
        viewer.read_until(lambda m: False, 1.0)
        assert viewer.labels("GuiCheckboxMessage") == []
        operator = RawPage(app.port, f"/t/{app.page_token.secret}")
        assert operator.read_until(lambda m: m.get("props", {}).get("label") == "Tip trail", 30), (
            operator.labels("GuiCheckboxMessage")
        )
    finally:
        for r in (viewer, operator):
            if r is not None:
                r.close()
        app.stop()


# -- 9. unreachable targets -------------------------------------------------------------------
def test_execute_is_disabled_for_an_unreachable_target(monkeypatch):
    """Defect (audit 15.9): a gizmo at (0, 0, 1.3) showed "NOT reachable (best error 0.352 m)"
    with Execute move enabled (it would send the best effort)."""
    import numpy as np

    src, app = _live(monkeypatch, _Daemon())
    operator = None
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        operator = RawPage(app.port, f"/t/{app.page_token.secret}")
        assert wait_for(lambda: any(p.execute is not None for p in app.pages.values()), 30)
        page = next(iter(app.pages.values()))
        target = np.array([0.0, 0.0, 1.3])
        res = app.planner.plan(target, {})
        assert not res.success
        app._show_plan(target, res)
        assert page.execute.disabled
        assert "Execute move disabled" in app.plan_text
        sent = []
        monkeypatch.setattr(src.client, "send_trajectory", lambda *a, **k: sent.append(a),
                            raising=False)  # fmt: skip
        app.execute_move(page)
        assert sent == [] and "NOT reachable" in app.refusal
    finally:
        if operator is not None:
            operator.close()
        app.stop()


# -- 10. a stale stop reason --------------------------------------------------------------------
def test_a_stop_reason_is_cleared_when_a_trajectory_takes_control(monkeypatch):
    """Defect (audit 15.10): "sliders stopped: stop button" stayed on the control line while a
    later trajectory ran."""
    daemon = _Daemon()
    src, app = _live(monkeypatch, daemon)
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        app.driver.stopped_reason = "stop button"
        assert wait_for(lambda: "sliders stopped: stop button" in app.g_control.content, 5)
        daemon.goals = ["jtc-1"]
        assert wait_for(lambda: "trajectory jtc-1" in app.g_control.content, 5)
        assert wait_for(lambda: "sliders stopped" not in app.g_control.content, 5), (
            app.g_control.content
        )
    finally:
        app.stop()


class _NamingDaemon(_Daemon):
    """A daemon that names who sent each goal (trajectory.status "from") and tells the view its
    own connection's address (session "peer")."""

    VIEW_PEER = "127.0.0.1:50123"
    senders = {
        "jtc-7": {"peer": "10.0.0.5:4242", "client": "ucr zenoh", "for": "ros2 goal 7"},
        "jtc-8": {"peer": VIEW_PEER, "client": "ucr view", "for": "view page=1 peer=x"},
    }

    def call(self, op: str, **params):
        if op == "session":
            return {"scope": self.scope, "authenticated": False, "peer": self.VIEW_PEER,
                    "agent": "ucr view"}  # fmt: skip
        return super().call(op, **params)

    def trajectory_status(self, goal):
        return {"id": goal, "from": self.senders.get(goal)}


def test_the_control_line_names_who_sent_the_running_trajectory(monkeypatch):
    """Issue 15: "always visible who has control (page, gamepad, trajectory)". The line said
    "trajectory jtc-7" whoever sent it; now it names the sender as the daemon does (the goal's
    "from": program, whom it acts for, address), and the view's own Execute move as such."""
    daemon = _NamingDaemon()
    src, app = _live(monkeypatch, daemon)
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        assert list(src.own_peers) == [_NamingDaemon.VIEW_PEER]
        daemon.goals = ["jtc-7"]
        other = (
            "trajectory jtc-7 (jtc) from API client 'ucr zenoh' for 'ros2 goal 7' at 10.0.0.5:4242"
        )
        assert wait_for(lambda: other in app.g_control.content, 5), app.g_control.content
        daemon.goals = ["jtc-8"]
        ours = "trajectory jtc-8 (jtc) from this view's page (Execute move)"
        assert wait_for(lambda: ours in app.g_control.content, 5), app.g_control.content
        daemon.goals = ["jtc-9"]  # a goal the daemon does not name the sender of

        def unnamed() -> bool:
            line = app.g_control.content.split("<br/>")[0]
            return line == "**control:** trajectory jtc-9 (jtc)"

        assert wait_for(unnamed, 5), app.g_control.content
    finally:
        daemon.goals = []
        app.stop()


# -- 5. named materials -------------------------------------------------------------------------
def test_a_visual_naming_a_robot_level_material_gets_its_colour(tmp_path):
    """Defect (audit 15.5): `<material name="grey"/>` referring to a robot-level `<material>` was
    drawn in the default colour."""
    from ucrdf.parser import load
    from view.scene import parse_visuals

    arm = ROBOT.parent / "hybrid_arm.ucrdf"  # base_link's visual: <material name="grey"/>
    text = arm.read_text()
    assert '<material name="grey"/>' in text
    i = text.index('<material name="grey">')
    j = text.index("</material>", i) + len("</material>")
    text = text[:i] + '<material name="grey"><color rgba="1 0 0 1"/></material>' + text[j:]
    f = tmp_path / "m.ucrdf"
    f.write_text(text)
    base = [v for v in parse_visuals(load(f), tmp_path) if v.link == "base_link"]
    assert base and base[0].color == (255, 0, 0) and base[0].color_given, base


# -- 11. the tip trail --------------------------------------------------------------------------
def test_the_trail_keeps_its_path_while_the_robot_rests(monkeypatch):
    """Defect (audit 15.11): a point per 40 Hz update, 300 kept: 7.5 s of path, collapsing onto
    one point at rest. Now a point per TRAIL_STEP_M moved."""
    src, app = _live(monkeypatch, _Daemon())
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts
        for k in (0.5, 1.0, 1.5):
            with src.lock:
                src.snap.state["segment_1"] = {"kappa": k, "phi": 0.0}
                src.snap.valid["segment_1"] = True
                src.snap.seq += 1
            time.sleep(0.2)
        n = len(app.trail)
        assert n >= 3, n
        for _ in range(20):  # at rest: many updates, no new point
            with src.lock:
                src.snap.seq += 1
            time.sleep(0.03)
        assert len(app.trail) == n
    finally:
        app.stop()


# -- 7. what `ucr view FILE` says ---------------------------------------------------------------
def test_a_broken_file_with_a_daemon_is_not_called_no_daemon(monkeypatch, tmp_path, capsys):
    """Defect (audit 15.7): a reachable daemon and a FILE failing `ucr check` printed "no daemon
    (<errors>); offline on FILE"."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import argparse

    import view.source as vs
    from view.cli import cmd_view

    bad = tmp_path / "bad.ucrdf"
    bad.write_text(ROBOT.read_text().replace("<robot ", "<robot bogus='1' ", 1)[:-30])
    monkeypatch.setattr(vs, "connect", lambda *a, **k: _Daemon())
    args = argparse.Namespace(
        file=str(bad), offline=False, url="ws://127.0.0.1:9", token_file=None, timeout=1.0,
        host="127.0.0.1", port=0, allow_host=[], rate=40.0, nice=0, exit_with_parent=False,
    )  # fmt: skip
    assert cmd_view(args) == 1
    err = capsys.readouterr().err
    assert "no daemon" not in err, err
    assert "the daemon answers, but" in err and f"{bad}:" in err, err


def test_a_refused_token_is_said_as_such(monkeypatch, capsys):
    """A PermissionError (the daemon refused the token) is not "no daemon" either."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import argparse

    import view.source as vs
    from host.api.client import ApiAuthError
    from view.cli import cmd_view

    def refuse(*a, **k):
        raise ApiAuthError("the server refused the token (HTTP 401)")

    monkeypatch.setattr(vs, "connect", refuse)
    args = argparse.Namespace(
        file=str(ROBOT), offline=False, url="ws://127.0.0.1:9", token_file=None, timeout=1.0,
        host="127.0.0.1", port=0, allow_host=[], rate=40.0, nice=0, exit_with_parent=False,
    )  # fmt: skip
    assert cmd_view(args) == 1
    err = capsys.readouterr().err
    assert "no daemon" not in err and "refused this view's token" in err, err


# -- 4. the latency figure ----------------------------------------------------------------------
def test_the_latency_figure_is_shown_only_for_a_daemon_on_this_machine(monkeypatch):
    """Defect (audit 15.4): the figure is our monotonic clock minus the daemon's monotonic
    stamp: meaningless for a daemon on another machine. Shown only for a local daemon."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import view.source as vs
    from view.app import ViewApp

    assert vs.daemon_is_local("ws://127.0.0.1:8765") and vs.daemon_is_local("wss://localhost:1")
    assert not vs.daemon_is_local("wss://10.1.2.3:8765")
    monkeypatch.setattr(vs, "connect", lambda *a, **k: _Daemon())
    src = vs.LiveSource("wss://10.1.2.3:8765", None).start()
    app = ViewApp(src, port=0, always_update=True).start()
    try:
        with src.lock:
            src.snap.t_daemon, src.snap.sample_seq = 5.0, src.snap.sample_seq + 1
            src.snap.seq += 1
        assert wait_for(lambda: "latency not shown" in app.g_facts.content, 10), app.g_facts.content
        assert not app.latency_ms
    finally:
        app.stop()


def test_while_one_page_drives_the_other_pages_sliders_show_the_measured_state(monkeypatch):
    """docs/view.md "Limits": while one page's sliders drove, every page's sliders stayed
    where they were, so a second page showed stale values while the robot moved. Now a slider
    shows the measured κ, φ unless its own page set the target being driven."""
    import math
    from types import SimpleNamespace

    from view.app import _Page

    daemon = _Daemon()
    src, app = _live(monkeypatch, daemon)
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 20), app.facts

        def page(pid: int) -> _Page:
            pg = _Page(SimpleNamespace(client_id=pid), f"127.0.0.1:{pid}")
            for name in ("segment_1", "segment_2"):
                pg.sliders[name] = (SimpleNamespace(value=0.0), SimpleNamespace(value=0.0))
                pg.shown[name] = (0.0, 0.0)
            return pg

        a, b = page(101), page(102)
        a.sliders["segment_1"][0].value = 2.0  # page a's own target, shown on page a
        a.shown["segment_1"] = (2.0, 0.0)
        with app.lock:
            app.pages.update({101: a, 102: b})
        app.driver.set_target("segment_1", 2.0, 0.0, "view page=101", page=101)
        measured = {
            "segment_1": {"kappa": 1.2, "phi": 0.5},
            "segment_2": {"kappa": 0.4, "phi": -0.3},
        }
        snap = SimpleNamespace(state=measured, valid={"segment_1": True, "segment_2": True})
        with app.lock:
            app._follow_sliders(snap)
        assert a.sliders["segment_1"][0].value == 2.0  # page a's target stands on page a
        assert b.sliders["segment_1"][0].value == 1.2  # page b sees the robot move
        assert b.sliders["segment_1"][1].value == round(math.degrees(0.5))
        assert a.sliders["segment_2"][0].value == 0.4  # and a segment nobody drives, anywhere
        assert b.sliders["segment_2"][1].value == round(math.degrees(-0.3))
    finally:
        with app.lock:
            app.pages.clear()
        app.stop()
