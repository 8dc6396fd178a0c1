"""The view in a real browser (headless Chromium) against the emulated chain: the page shows one
tube per discovered segment, its sliders and tip gizmo move the real (emulated) segments through
the daemon's arbitration, a hot-plug rebuilds the scene, and closing the page stops the motion."""

from __future__ import annotations

import contextlib
import logging
import math
import re
import threading
import time

import numpy as np
import pytest
from view_helpers import ROOT, RawPage, page_controls, wait_for

pytestmark = pytest.mark.timeout(240)
# the page's initial camera (view/app.py) and gizmo size, to find the gizmo on the screen
CAMERA, LOOK_AT, FOV_DEG, GIZMO_SCALE = (1.5, -1.5, 1.2), (0.0, 0.0, 0.35), 75.0, 0.3


def measured(daemon, name: str, timeout: float = 10.0) -> tuple[float, float]:
    """Measured (kappa, phi) of a segment; waits out a moment without a valid state (the daemon
    rebuilding after segments missed replies on a heavily loaded machine)."""
    deadline = time.monotonic() + timeout
    while True:
        st = daemon.status()
        js = st["joint_states"].get(name)
        if js is not None and js["valid"] and st["state"] == "connected":
            return js["kappa"], js["phi"]
        if time.monotonic() > deadline:
            raise AssertionError(f"no valid state for {name}: {st}")
        time.sleep(0.05)


def kvec(daemon, name: str) -> tuple[float, float]:
    k, p = measured(daemon, name)
    return k * math.cos(p), k * math.sin(p)


def set_number(page, index: int, value: float) -> None:
    """Type a value into the number box of the index-th slider (as a person would) + Enter."""
    box = page.locator("input[inputmode='decimal'], input[type='number']").nth(index)
    box.fill(f"{value}")
    box.press("Enter")


def settle(daemon, view) -> None:
    """End any manual control and straighten the robot (the next test starts from rest)."""
    view.stop_motion("test cleanup")
    if daemon.status()["manual_control"]:
        daemon.hand_back("ffc")
    names = daemon.status()["segments"]
    gid = daemon.send_trajectory(
        [{"time_from_start": 1.5, "segments": {n: {"kappa": 0.0, "phi": 0.0} for n in names}}]
    )
    assert wait_for(lambda: daemon.trajectory_status(gid)["done"], 20)


def test_page_shows_one_tube_per_discovered_segment(rig, live_view, page):
    _, daemon, _ = rig
    # a starved emulator may cut the chain for a moment on a loaded machine: start whole
    assert wait_for(lambda: len(daemon.status()["segments"]) == 3, 30)
    segments = daemon.status()["segments"]
    page.get_by_text(f"tubes: {len(segments)} ({', '.join(segments)})").wait_for(timeout=60000)
    assert live_view.facts["tubes"] == sorted(segments)
    # and the tubes really are scene meshes, one per segment
    assert sorted(k[5:] for k in live_view.nodes if k.startswith("tube:")) == sorted(segments)
    page.get_by_text("control:").wait_for(timeout=10000)


def test_slider_bends_the_emulated_segment_and_changes_the_picture(rig, live_view, page):
    _, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    time.sleep(1.0)
    canvas = page.locator("canvas").first
    before = canvas.screenshot()
    assert measured(daemon, "segment_1")[0] < 0.1
    set_number(page, 0, 1.5)  # segment_1 kappa, 1/m
    assert wait_for(lambda: abs(measured(daemon, "segment_1")[0] - 1.5) < 0.1, 20), measured(
        daemon, "segment_1"
    )
    # it went through the arbitration as a manual source
    assert daemon.status()["manual_control"] == ["ffc"]
    page.get_by_text("this view's page sliders").wait_for(timeout=10000)
    time.sleep(1.0)
    assert canvas.screenshot() != before
    settle(daemon, live_view)


def test_sliders_follow_motion_made_by_another_source_and_move_nothing(rig, live_view, page):
    """Defect (docs/view.md "Limits", 2026-11-27): the sliders showed their last target, so
    after a trajectory (or a gamepad, or another page) moved the robot they showed where it had
    been. Now, while they drive nothing, they show the measured κ, φ; setting them moves nothing."""
    _, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    gid = daemon.send_trajectory(
        [{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1.2, "phi": 0.5}}}]
    )
    assert wait_for(lambda: daemon.trajectory_status(gid)["done"], 20)
    k, ph = measured(daemon, "segment_1")
    assert abs(k - 1.2) < 0.05, (k, ph, daemon.trajectory_status(gid))
    boxes = page.locator("input[inputmode='decimal'], input[type='number']")

    def shown() -> tuple[float, float]:
        return float(boxes.nth(0).input_value()), float(boxes.nth(1).input_value())

    def agrees() -> bool:
        # against the measured pose now: a segment still settling by a few 0.01 1/m after
        # the goal's end moved away from a pose read once (a loaded machine, CI)
        k, ph = measured(daemon, "segment_1")
        return abs(shown()[0] - k) <= 0.011 and abs(shown()[1] - math.degrees(ph)) <= 1.01

    assert wait_for(agrees, 30), (shown(), measured(daemon, "segment_1"))
    assert not live_view.driver.targets  # the page drives nothing ...
    assert daemon.status()["manual_control"] == []  # ... and took no control
    settle(daemon, live_view)


class _Sampler:
    """kx of a segment, sampled every 20 ms from the daemon until stopped (min, max, last)."""

    def __init__(self, daemon, name: str):
        self.daemon, self.name, self.kx = daemon, name, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            js = self.daemon.status()["joint_states"].get(self.name)
            if js is not None and js["valid"]:
                self.kx.append(js["kappa"] * math.cos(js["phi"]))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2)


def test_sliders_never_drive_past_their_target_and_closing_the_page_stops_it(
    rig, live_view, browser
):
    """Defect (audit 15.2): the slider drive steered the lagging measured κ while the cFFC's
    setpoint ran ahead: a target of κ 3.0 drove to ≈ κ_max 3.31 and back, and closing the page
    left the setpoint beyond the target. Now the measured κ never exceeds the target, and closing
    the page mid-motion stops the robot at or before it, where it holds, though another page
    with controls stays open (which kept the drive going until its idle timeout before).
    segment_2's servos follow its setpoint through a slow first-order simple controller here
    (``p_slew``, gain 0.02 per tick): a segment lagging well behind the setpoint. (Not a lower
    kappa_rate_max on the segment: that limit is part of its descriptor, and a rediscovery on a
    loaded machine then rightly refuses a segment slower than the file — it dropped out of the
    chain for the rest of the module once in CI.)"""
    _, daemon, _ = rig
    tol = 0.03  # 1/m: the emulated segment's measurement and tracking
    ctx = browser.new_context(viewport={"width": 1000, "height": 700})
    pg = ctx.new_page()
    pg.goto(live_view.url)
    pg.get_by_text("tubes: 3").wait_for(timeout=60000)
    sc, gain = 3, 4  # PARAM ids of sc and sc_gain (device/params.py PARAM_NAMES)
    flashed = daemon.link.param_get(1, sc), daemon.link.param_get(1, gain)
    daemon.link.param_set(1, gain, 0.02)
    daemon.link.param_set(1, sc, "p_slew")
    sampler = _Sampler(daemon, "segment_2")
    other = None
    try:
        set_number(pg, 2, 3.0)  # segment_2 kappa to 3 1/m at phi 0
        assert wait_for(lambda: abs(kvec(daemon, "segment_2")[0] - 3.0) < 0.1, 20), (
            kvec(daemon, "segment_2"),
            live_view.driver.targets,
            live_view.driver.sent,
            live_view.driver.stopped_reason,
            live_view.refusal,
            daemon.status(),
        )
        time.sleep(1.0)
        assert max(sampler.kx) <= 3.0 + tol, (max(sampler.kx), sampler.kx[::10])
        # the far side: phi 180 deg, a 6 1/m path through straight at <= 5 1/m/s (where the
        # setpoint ran furthest ahead: to -kappa_max 3.31, then back)
        set_number(pg, 3, 180)
        assert wait_for(lambda: abs(kvec(daemon, "segment_2")[0] + 3.0) < 0.1, 20)
        time.sleep(1.5)
        assert min(sampler.kx) >= -3.0 - tol, (min(sampler.kx), sampler.kx[-60::5])
        # a second page with controls stays open: it set no target, so it does not keep the
        # first page's drive alive (the deadman counted any page with controls before)
        other = browser.new_context(viewport={"width": 800, "height": 600})
        other.new_page().goto(live_view.url)
        assert wait_for(lambda: len(live_view.pages) == 2, 30), live_view.pages
        # and back to phi 0; the person closes the tab near the target, mid-motion
        set_number(pg, 3, 0)
        assert wait_for(lambda: kvec(daemon, "segment_2")[0] > 1.5, 10)
        ctx.close()
        t_closed = time.monotonic()
        assert wait_for(lambda: live_view.driver.stopped_reason == "page closed", 5), (
            live_view.driver.stopped_reason,
            live_view.server.get_clients(),
            live_view.refusal,
        )
        # the daemon's deadman (0.3 s) would stop it even without the zero input; the segment
        # then still closes its lag on the last setpoint (slower on a loaded host)
        time.sleep(1.5)
        a = kvec(daemon, "segment_2")
        time.sleep(1.0)
        b = kvec(daemon, "segment_2")
        assert math.dist(a, b) < 0.05, (a, b)  # holds still
        assert max(sampler.kx) <= 3.0 + tol, (max(sampler.kx), sampler.kx[-60::5], b,
                                              time.monotonic() - t_closed)  # fmt: skip
    finally:
        sampler.stop()
        daemon.link.param_set(1, sc, flashed[0])
        daemon.link.param_set(1, gain, flashed[1])
        if other is not None:
            other.close()
    settle(daemon, live_view)


def test_who_has_control_follows_the_daemon_and_shows_another_clients_override(
    rig, live_view, page
):
    """Defect (audit 15.3): once the page had driven a slider, the control line kept crediting
    "this view's page sliders" while another client (a gamepad) streamed ffc.input, and a page
    slider moved meanwhile was not shown as overridden. Now the line follows who sent the manual
    cFFC's input, and a page input overridden by another client is shown under refused, both
    naming that client as the daemon saw it (program, whom it acts for, address: the cFFC's
    input_from; before, "another API client (gamepad/teleop)", a guess from timing)."""
    from host.api.client import ApiError, connect, on_behalf_of

    _, daemon, srv = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    set_number(page, 0, 1.0)  # segment_1 kappa
    page.get_by_text("this view's page sliders").wait_for(timeout=20000)
    assert wait_for(lambda: abs(measured(daemon, "segment_1")[0] - 1.0) < 0.1, 20)
    pad = connect(srv.url, timeout=5, agent="gamepad")
    named = f"API client 'gamepad' for 'stick js0' at {pad.session()['peer']}"
    done = threading.Event()

    refused: list[str] = []

    def stream() -> None:
        # a gamepad goes on streaming through a refusal or a timeout (a loaded machine: the
        # daemon rebuilding the chain after a starved emulated segment went silent). Before, the
        # first one ended this thread silently, and nobody overrode the page any more: what a
        # stressed run showed (no override for 10 s, the page's own input the latest)
        with on_behalf_of("stick js0"):
            while not done.is_set():
                try:
                    pad.ffc_input({"segment_3": (0.12, 0.0)})
                except ApiError as exc:
                    refused.append(str(exc))
                time.sleep(0.04)
            pad.ffc_input({"segment_3": (0.0, 0.0)})

    th = threading.Thread(target=stream, daemon=True)
    th.start()
    try:
        assert wait_for(lambda: named in live_view.g_control.content, 10), (
            live_view.g_control.content
        )
        # the page can lag the view by seconds: with software WebGL (this headless Chromium) it
        # renders the scene slower than the view sends it, and what was sent waits in the
        # browser (docs/view.md "Limits"; seen here: 13 s behind after the test above)
        page.get_by_text(named).first.wait_for(timeout=45000)
        assert "this view's page sliders" not in live_view.g_control.content
        # The takeover may already have overridden the page's first target (κ 1.0) and said so
        # (the view thread wrote that refusal before the control line above): forget it, so
        # that only an override of the slider moved below can satisfy the wait. The browser's
        # slider events reach the view asynchronously (one may come after an override: a new
        # attempt, overridden in turn while the gamepad streams), so the wait is for the state
        # the view settles in, not for the first sign of it.
        live_view.refusal = ""
        set_number(page, 0, 1.5)  # the page moves a slider while the gamepad streams
        assert wait_for(
            lambda: "overridden" in live_view.refusal and not live_view.driver.targets, 10
        ), (live_view.refusal, live_view.driver.targets, live_view.g_control.content, refused)
        assert named in live_view.refusal, live_view.refusal
        overridden = re.compile("refused: page slider input overridden: " + re.escape(named))
        page.get_by_text(overridden).wait_for(timeout=45000)
    finally:
        done.set()
        th.join(5)
        pad.close()
        settle(daemon, live_view)  # also after a failure: the next test finds no manual control


def test_a_robot_file_that_is_not_the_daemons_refuses_controls(rig, live_view, caplog):
    """Defect (audit 15.4): `ucr view FILE` against a daemon running another robot silently drew
    FILE (2 tubes for 3 segments, IK on the wrong kinematics) with controls. Now the mismatch is
    said on the terminal and on the page, and no page gets controls."""
    from view.app import ViewApp
    from view.source import LiveSource

    _, _, srv = rig
    other = ROOT / "robots" / "softrobot2.ucrdf"
    with caplog.at_level(logging.WARNING, logger="ucr.view"):
        app = ViewApp(LiveSource(srv.url, None, str(other)).start(), port=0).start()
    try:
        assert "is not the daemon's robot" in caplog.text, caplog.text
        raw = RawPage(app.port, path=app.page_token.page_path.rstrip("/"))
        try:

            def refused(m: dict) -> bool:
                return "controls refused:" in str(m.get("props", {}).get("_markdown", ""))

            assert raw.read_until(refused, 30), raw.seen[-5:]
            raw.read_until(lambda m: False, 1.0)
            assert raw.labels("GuiSliderMessage") == []
            assert raw.labels("GuiButtonMessage") == []
        finally:
            raw.close()
        assert wait_for(lambda: "robot file mismatch" in app.g_errors.content, 10)
        assert app.driver.targets == {} and app.pages == {}
    finally:
        app.stop()
    # the daemon's own file given as FILE is no mismatch
    same = LiveSource(srv.url, None, str(live_view.source.snap.robot_file))
    try:
        assert same.snap.mismatch == ""
    finally:
        same.stop()


def test_gizmo_drag_plans_ik_and_the_chain_executes_the_move(rig, live_view, page):
    _, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    time.sleep(1.0)
    gizmo = page_controls(live_view).gizmo  # this page's own gizmo (it has the page token)
    start = tuple(gizmo.position)
    box = page.locator("canvas").first.bounding_box()
    # drag from the gizmo's centre (the camera looks at the robot; the gizmo sits at the tip)
    moved = drag_gizmo(page, live_view, box)
    assert moved, f"the gizmo did not follow the mouse (still at {start})"
    page.get_by_text(re.compile(r"m — reachable")).wait_for(timeout=20000)
    tip_link = live_view.model.tip_link
    names = ["segment_1", "segment_2", "segment_3"]

    def tip_error(target) -> float:
        st = daemon.status()["joint_states"]
        cfg = {n: {"kappa": v["kappa"], "phi": v["phi"]} for n, v in st.items()}
        tip = live_view.model.kin.fk(cfg, strict=False)[tip_link][:3, 3]
        return float(math.dist(tip, target))

    def whole() -> bool:
        return daemon.status()["segments"] == names and live_view.source.snap.present == names

    for _attempt in range(3):
        # a starved emulator on a loaded machine may cut the chain for a moment (the view then
        # plans for the segments present) or trip the path tolerance: execute on a whole chain,
        # and try again when the daemon's supervision got in the way
        assert wait_for(whole, 30), daemon.status()["segments"]
        before = live_view.plan_text
        page.get_by_role("button", name="Execute move").click()

        def sent(b: str = before) -> bool:
            content = live_view.plan_text
            return content.startswith("move ") and content != b

        assert wait_for(sent, 10), (live_view.plan_text, live_view.refusal)
        page.get_by_text(live_view.plan_text).wait_for(timeout=10000)  # shown on the page
        target, planned = live_view.planner.executed  # the plan the page showed when clicked
        assert planned.success
        goal = re.search(r"move (\S+) sent", live_view.plan_text).group(1)
        assert wait_for(lambda g=goal: daemon.trajectory_status(g)["done"], 30)
        status = daemon.trajectory_status(goal)
        if status["state"] == "succeeded" and wait_for(lambda t=target: tip_error(t) < 0.01, 10):
            break
    assert status["state"] == "succeeded", status
    assert tip_error(target) < 0.01, (tip_error(target), status)
    settle(daemon, live_view)


def project(p, box, cam=CAMERA, look=LOOK_AT, fov_deg=FOV_DEG) -> tuple[float, float]:
    """Screen pixel of a world point for the page's initial camera (pinhole, vertical fov)."""
    c, aim, up = np.asarray(cam, float), np.asarray(look, float), np.array([0.0, 0.0, 1.0])
    f = (aim - c) / np.linalg.norm(aim - c)
    r = np.cross(f, up) / np.linalg.norm(np.cross(f, up))
    u = np.cross(r, f)
    d = np.asarray(p, float) - c
    t = math.tan(math.radians(fov_deg) / 2)
    nx = (d @ r) / ((d @ f) * t * box["width"] / box["height"])
    ny = (d @ u) / ((d @ f) * t)
    return box["x"] + (nx + 1) / 2 * box["width"], box["y"] + (1 - ny) / 2 * box["height"]


def drag_gizmo(page, view, box) -> bool:
    """Grab the gizmo's z arrow (found by projecting it) and pull it down by 0.12 m."""
    gizmo = page_controls(view).gizmo
    start = np.asarray(gizmo.position, float)
    for frac in (0.6, 0.75, 0.45, 0.9, 0.3):
        grab = start + [0.0, 0.0, frac * GIZMO_SCALE]
        x0, y0 = project(grab, box)
        x1, y1 = project(grab - [0.0, 0.0, 0.12], box)
        page.mouse.move(x0, y0, steps=3)
        page.wait_for_timeout(300)  # a software-rendered page on a loaded machine is slow
        page.mouse.down()
        page.wait_for_timeout(300)
        for k in range(1, 11):
            page.mouse.move(x0 + (x1 - x0) * k / 10, y0 + (y1 - y0) * k / 10)
            page.wait_for_timeout(50)
        page.mouse.up()
        if wait_for(lambda: np.linalg.norm(np.asarray(gizmo.position) - start) > 0.02, 3.0):
            return True
    return False


def test_unplugging_the_tip_removes_its_tube_and_plugging_back_restores_it(rig, live_view, page):
    chain, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    chain.unplug(2)
    try:
        # (45 s: a software-WebGL page lags the view by seconds; docs/view.md "Limits")
        page.get_by_text("tubes: 2 (segment_1, segment_2)").wait_for(timeout=45000)
        assert live_view.facts["tubes"] == ["segment_1", "segment_2"]
        assert "missing:segment_3" in live_view.nodes
        page.get_by_text("segment_3: missing").wait_for(timeout=15000)
    finally:
        chain.plug(2)
    page.get_by_text("tubes: 3").wait_for(timeout=45000)
    assert live_view.facts["tubes"] == ["segment_1", "segment_2", "segment_3"]


def _red_pixels(png: bytes, box=None, at=None, half: int = 6) -> int:
    """Pixels of the fault red (230, 40, 40), shaded: strongly red, little green and blue; only
    in the (2 half)^2 square around page pixel ``at`` if given (``box``: the canvas box)."""
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    if at is not None:
        x, y = int(at[0] - box["x"]), int(at[1] - box["y"])
        img = img[max(0, y - half) : y + half, max(0, x - half) : x + half]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 120) & (r > 2 * g + 40) & (r > 2 * b + 40)).sum())


def _middle_of(view, name: str) -> np.ndarray:
    """World point halfway along a segment's drawn backbone."""
    with view.source.lock:
        state = {n: dict(v) for n, v in view.source.snap.state.items()}
    frames = view.model.frame(state).backbones[name]
    return frames[len(frames) // 2][:3, 3]


def _tube_colour(view, name: str) -> tuple[int, ...]:
    return tuple(int(c) for c in view.nodes[f"tube:{name}"].color)


def test_a_faulted_segment_turns_red_until_the_fault_is_cleared(rig, live_view, page):
    """An exception in segment_2's control tick (fault injection on the emulated servos): the
    page says `segment_2: fault` and its tube turns red, and stays red (FAULT is left only by an
    explicit clear), then blue again once cleared."""
    pytest.importorskip("PIL", reason="Pillow (a dependency of viser) is missing")
    from view.app import COLOURS

    _, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    page.get_by_text("segment_2: ok").wait_for(timeout=30000)
    time.sleep(1.0)
    canvas = page.locator("canvas").first
    box = canvas.bounding_box()
    # the screen pixels around segment_2's middle (the page's initial camera; nothing moves)
    at = project(_middle_of(live_view, "segment_2"), box)
    assert wait_for(lambda: _red_pixels(canvas.screenshot(), box, at) < 20, 20)  # blue now
    daemon.link.param_set(1, 5, "0:raise")
    try:
        page.get_by_text("segment_2: fault").wait_for(timeout=30000)
        assert wait_for(lambda: _tube_colour(live_view, "segment_2") == COLOURS["fault"], 10)
        assert wait_for(lambda: _red_pixels(canvas.screenshot(), box, at) > 60, 20), (
            at,
            _red_pixels(canvas.screenshot(), box, at),
        )
        daemon.link.param_set(1, 5, "none")  # the cause is gone, the FAULT is not
        time.sleep(3.0)  # well past the 1.5 s an event colour is held
        assert _tube_colour(live_view, "segment_2") == COLOURS["fault"]
        assert live_view.source.snap.status["segment_2"] == "fault"
    finally:
        daemon.link.param_set(1, 5, "none")
        daemon.clear_fault("segment_2")
    page.get_by_text("segment_2: ok").wait_for(timeout=30000)
    assert wait_for(lambda: _tube_colour(live_view, "segment_2") == COLOURS["ok"], 10)
    settle(daemon, live_view)


def test_a_segment_clamping_its_setpoints_turns_orange(rig, live_view, page):
    """segment_1 holds 2 1/m; then its firmware limit is lowered below that (PARAM kappa_max =
    1 1/m, below the robot file's): the segment clamps the setpoints the daemon sends and reports
    LIMIT_CLAMPED; the page shows `segment_1: clamped` and the tube orange."""
    from host.daemon import DaemonError
    from view.app import COLOURS

    _, daemon, _ = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    page.get_by_text("segment_1: ok").wait_for(timeout=30000)
    for _attempt in range(3):  # a starved emulator may abort a goal on a loaded machine
        if daemon.status()["manual_control"]:
            daemon.hand_back("ffc")
        gid = daemon.send_trajectory(
            [{"time_from_start": 3.0, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.0}}}]
        )
        assert wait_for(lambda g=gid: daemon.trajectory_status(g)["done"], 40)
        if abs(measured(daemon, "segment_1")[0] - 2.0) < 0.1:
            break
    assert abs(measured(daemon, "segment_1")[0] - 2.0) < 0.1, daemon.trajectory_status(gid)
    kappa_max = 1  # PARAM id of kappa_max (device/params.py PARAM_NAMES)
    flashed = daemon.link.param_get(0, kappa_max)
    seen: list[tuple] = []
    daemon.link.param_set(0, kappa_max, 1.0)
    try:

        def orange() -> bool:
            seen.append((live_view.source.snap.status.get("segment_1"),
                         _tube_colour(live_view, "segment_1")))  # fmt: skip
            return seen[-1] == ("clamped", COLOURS["clamped"])

        assert wait_for(orange, 30, 0.02), (
            seen[-5:],
            [e["event"] for e in daemon.fanout.recent_events][-10:],
            daemon.status()["joint_states"]["segment_1"],
        )
        # the page lags the view by seconds on a loaded machine, and shows a clamp for
        # EVENT_HOLD_S (1.5 s) after its last event; a stall makes the hold adopt the measured
        # (clamped) κ, which ends the clamping: keep the daemon commanding beyond the segment's
        # limit (the cFFC pushed outwards) until the page has shown it
        pushing = threading.Event()

        def push() -> None:
            while not pushing.wait(0.05):
                try:
                    daemon.ffc_input({"segment_1": (0.3, 0.0)})
                except DaemonError:  # refused while the chain is rebuilt: push on after it
                    pass

        pusher = threading.Thread(target=push, daemon=True)
        pusher.start()
        try:
            page.get_by_text("segment_1: clamped").wait_for(timeout=30000)
        finally:
            pushing.set()
            pusher.join(2)
            with contextlib.suppress(DaemonError):  # (else the deadman stops it in 0.3 s)
                daemon.ffc_input({"segment_1": (0.0, 0.0)})
            if daemon.status()["manual_control"]:
                daemon.hand_back("ffc")  # (the JTC holds the measured pose: within 1 1/m)
    finally:
        daemon.link.param_set(0, kappa_max, flashed)
    settle(daemon, live_view)
    page.get_by_text("segment_1: ok").wait_for(timeout=30000)
