"""The view's sources and figures without a browser or a chain: a topology push is applied at
once (not by the 0.2 s status poll), the latency figure counts only real samples, and the slider
drive never lets the cFFC's setpoint pass a target (a simulated cFFC and lagging segment)."""

from __future__ import annotations

import math
import queue
import shutil
import threading
import time

import pytest
from view_helpers import ROBOT, wait_for

pytestmark = pytest.mark.timeout(120)
NAMES = ["segment_1", "segment_2", "segment_3"]


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
    """An API client whose daemon pushes what the test puts in ``pushes``; its ``status`` never
    answers (so only the push can tell the view about a hot-plug)."""

    def __init__(self) -> None:
        self.pushes: queue.Queue = queue.Queue()
        self.topo = {"robot": "softrobot3", "file": str(ROBOT), "expected": NAMES,
                     "controlled": list(NAMES)}  # fmt: skip

    def topology(self) -> dict:
        return dict(self.topo)

    def status(self) -> dict:
        raise RuntimeError("no status in this test")

    def controllers(self) -> list:
        return []

    def call(self, op: str, **params):  # the view's scope probe: a control token
        from host.api.client import ApiError

        raise ApiError("not_found", f"no upload {params.get('upload')} on this connection")

    def subscribe(self, kinds, max_rate=None) -> _Sub:
        return _Sub(self.pushes)

    def close(self) -> None:
        pass


def test_a_topology_push_rebuilds_the_scene_on_the_next_update(monkeypatch):
    """Defect (audit 15.5): a topology push only marked the topology dirty and the 0.2 s status
    poll thread fetched it again, so a hot-plug showed 56-210 ms late (or never, while status
    does not answer). Now the push itself is applied and the next scene update rebuilds."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import view.source as vs
    from view.app import ViewApp

    daemon = _Daemon()
    monkeypatch.setattr(vs, "connect", lambda *a, **k: daemon)
    src = vs.LiveSource("ws://127.0.0.1:9", None).start()
    app = ViewApp(src, port=0, control=False, always_update=True).start()
    try:
        assert wait_for(lambda: app.facts.get("tubes") == NAMES, 10), app.facts
        daemon.pushes.put({"kind": "topology", **daemon.topo, "controlled": NAMES[:2]})
        t_push = time.monotonic()
        assert wait_for(lambda: src.snap.present == NAMES[:2], 2.0), src.snap.present
        assert wait_for(lambda: app.facts.get("tubes") == NAMES[:2], 2.0), app.facts
        assert time.monotonic() - t_push < 1.0
        assert "missing:segment_3" in app.nodes and src.snap.status["segment_3"] == "missing"
    finally:
        app.stop()


def test_the_view_streams_joint_states_slowly_while_no_page_is_open(monkeypatch):
    """A view nobody looks at decoded every joint_states message at the full rate (about 28 ms
    of CPU per second in the view and 20 more in the API process, bench_view). Now it
    subscribes at IDLE_RATE_HZ while no page is open, and at the full rate again as soon as one
    is: the new subscription first, then the old one ends (no event falls in between)."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    import view.source as vs
    from view.app import ViewApp

    class Sub(_Sub):
        def __init__(self, q: queue.Queue, log: list) -> None:
            super().__init__(q)
            self.log = log

        def close(self) -> None:
            self.log.append("close")

    class Daemon(_Daemon):
        def __init__(self) -> None:
            super().__init__()
            self.log: list = []

        def subscribe(self, kinds, max_rate=None) -> Sub:
            self.log.append(max_rate)
            return Sub(self.pushes, self.log)

    daemon = Daemon()
    monkeypatch.setattr(vs, "connect", lambda *a, **k: daemon)
    src = vs.LiveSource("ws://127.0.0.1:9", None).start()
    app = ViewApp(src, port=0, control=False).start()  # no page
    pages: dict = {}
    monkeypatch.setattr(app.server, "get_clients", lambda: pages)
    try:
        assert wait_for(lambda: src.stream_rate_hz == vs.IDLE_RATE_HZ, 5), daemon.log
        pages[1] = object()  # a page opens
        assert wait_for(lambda: src.stream_rate_hz == src.rate_hz, 2), daemon.log
        pages.clear()  # and closes
        assert wait_for(lambda: daemon.log[-2:] == [vs.IDLE_RATE_HZ, "close"], 2), daemon.log
        # every change subscribed at the new rate before it closed the old subscription
        changes = [i for i, x in enumerate(daemon.log) if x == "close"]
        assert changes and all(isinstance(daemon.log[i - 1], float) for i in changes)
    finally:
        app.stop()
        src.stop()


def test_the_view_reads_the_parameters_of_the_cffc_its_sliders_drive(monkeypatch):
    """The slider drive models the daemon's cFFC (docs/view.md): the view reads that cFFC's
    deadzone, gain and deadman from controllers.list (the active cFFC, else the first, as the
    daemon's ffc.input picks it), once per connection."""
    import view.source as vs
    from view.control import FfcParams

    class Daemon(_Daemon):
        asked = 0

        def status(self) -> dict:
            return {"state": "connected", "segments": NAMES, "manual_control": [],
                    "active_controllers": ["jtc"], "running_goals": []}  # fmt: skip

        def controllers(self) -> list:
            self.asked += 1
            return [
                {"name": "jtc", "type": "jtc", "state": "active"},
                {
                    "name": "slow",
                    "type": "ffc",
                    "state": "inactive",
                    "deadzone": 0.0,
                    "gain": 0.5,
                    "deadman_timeout_s": 1.0,
                },  # fmt: skip
                {
                    "name": "fast",
                    "type": "ffc",
                    "state": "inactive",
                    "deadzone": 0.3,
                    "gain": 1.0,
                    "deadman_timeout_s": 0.3,
                },  # fmt: skip
            ]

    daemon = Daemon()
    monkeypatch.setattr(vs, "connect", lambda *a, **k: daemon)
    src = vs.LiveSource("ws://127.0.0.1:9", None).start()
    try:
        assert wait_for(lambda: src.ffc_params is not None, 5)
        assert src.ffc_params == FfcParams(deadzone=0.0, gain=0.5, deadman_timeout_s=1.0)
        time.sleep(0.5)
        assert daemon.asked == 1  # not polled while nobody holds manual control
    finally:
        src.stop()
    # a daemon that does not give them (older, or no cFFC): the defaults, asked once
    daemon = Daemon()
    daemon.controllers = lambda: (setattr(daemon, "asked", daemon.asked + 1), [])[1]
    src = vs.LiveSource("ws://127.0.0.1:9", None).start()
    try:
        assert wait_for(lambda: src.ffc_params is not None, 5)
        assert src.ffc_params == FfcParams()
        time.sleep(0.5)
        assert daemon.asked == 1
    finally:
        src.stop()


def test_the_latency_figure_counts_only_real_samples(tmp_path):
    """Defect (audit 15.6): every snapshot change counted as a latency sample aged from the last
    slider move, so saving the file offline showed "slider→page 3544.8 ms (p50)". Now only a
    slider move's own effect (offline) or a daemon message's stamp (live) is a sample."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    from view.app import ViewApp
    from view.source import OfflineSource

    robot = tmp_path / "robot.ucrdf"
    shutil.copy(ROBOT, robot)
    src = OfflineSource(robot, poll_s=0.05).start()
    app = ViewApp(src, port=0, always_update=True).start()
    try:
        assert wait_for(lambda: app.model is not None and app.pushes > 0, 10)
        assert list(app.latency_ms) == []  # the file's first load is no sample
        src.set_target("segment_1", 1.0, 0.0)
        assert wait_for(lambda: len(app.latency_ms) == 1, 5)
        time.sleep(0.6)
        pushes = app.pushes
        robot.write_text(robot.read_text() + "\n")  # a save: reloaded, redrawn
        assert wait_for(lambda: src.snap.robot_version == 2 and app.pushes > pushes, 5)
        time.sleep(0.3)
        assert len(app.latency_ms) == 1, list(app.latency_ms)
        assert app.latency_ms[0] < 500, list(app.latency_ms)
    finally:
        app.stop()


class _SimulatedFfc:
    """The daemon's cFFC (host/controllers/ffc.py: deadzone 0.05, gain 1, deadman 0.3 s,
    kappa_max clamp) at 100 Hz and a segment following its setpoint with a first-order lag."""

    def __init__(
        self,
        rate_max: float,
        kappa_max: float,
        lag_s: float = 0.25,
        slew: float = math.inf,
        meas_cap: float = math.inf,
        reports: bool = True,
        cmd: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.rate_max, self.kappa_max, self.lag_s = rate_max, kappa_max, lag_s
        self.slew, self.meas_cap = slew, meas_cap  # a slower firmware; a firmware limit
        self.reports = reports  # says its setpoint (this daemon) or not (an older one)
        self.cmd = list(cmd)
        self.meas = [0.0, 0.0]
        self.u: tuple[float, float] | None = None
        self.t_u = -math.inf
        self.peak = 0.0
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def ffc_input(self, rates: dict) -> dict:
        with self.lock:
            self.u = tuple(rates.get("segment_1", (0.0, 0.0)))
            self.t_u = time.monotonic()
            if self.reports:
                return {"accepted": True, "takeover": None, "setpoint": self._setpoint()}
        return {"accepted": True, "takeover": None}

    def _setpoint(self) -> dict:
        return {"segment_1": list(self.cmd)}

    def controllers(self) -> list:
        entry = {"name": "ffc", "type": "ffc", "state": "active"}
        with self.lock:
            if self.reports:
                entry["setpoint"] = self._setpoint()
        return [{"name": "jtc", "type": "jtc", "state": "inactive"}, entry]

    def _run(self) -> None:
        dt = 0.01
        while not self._stop.wait(dt):
            with self.lock:
                u = self.u if time.monotonic() - self.t_u <= 0.3 else None
                mag = math.hypot(*u) if u else 0.0
                if u and mag > 0.05:
                    k = self.rate_max * (min(mag, 1.0) - 0.05) / 0.95 / mag
                    x, y = self.cmd[0] + u[0] * k * dt, self.cmd[1] + u[1] * k * dt
                    r = math.hypot(x, y)
                    if r > self.kappa_max:
                        x, y = x * self.kappa_max / r, y * self.kappa_max / r
                    self.cmd = [x, y]
                a = dt / self.lag_s
                step = [(c - m) * a for m, c in zip(self.meas, self.cmd, strict=True)]
                n = math.hypot(*step)
                if n > self.slew * dt:
                    step = [d * self.slew * dt / n for d in step]
                x, y = self.meas[0] + step[0], self.meas[1] + step[1]
                r = math.hypot(x, y)
                if r > self.meas_cap:
                    x, y = x * self.meas_cap / r, y * self.meas_cap / r
                self.meas = [x, y]
                self.peak = max(self.peak, self.meas[0])

    def measured(self) -> dict:
        with self.lock:
            kx, ky = self.meas
        return {"segment_1": {"kappa": math.hypot(kx, ky), "phi": math.atan2(ky, kx)}}

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1)


def _drive_and_watch(driver, sim: _SimulatedFfc, kappa: float, seconds: float) -> float:
    """Set segment_1's slider target to ``kappa`` (phi 0) and watch the cFFC's setpoint for
    ``seconds``; returns the largest |setpoint| seen."""
    driver.set_target("segment_1", kappa, 0.0)
    peak = 0.0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        peak = max(peak, math.hypot(*sim.cmd))
        time.sleep(0.005)
    return peak


@pytest.mark.parametrize("reports", [True, False], ids=["daemon-says-setpoint", "older-daemon"])
def test_the_slider_drive_never_lets_the_setpoint_pass_the_target(reports):
    """Defect (audit 15.2), on a simulated cFFC and lagging segment: the drive steered the
    measurement, so the cFFC's setpoint ran past the target (to kappa_max) and the segment
    followed it. Now neither the setpoint nor the segment passes the target, and the segment
    gets there: steering the setpoint the daemon reports, or (an older daemon) a model of it."""
    from view.control import SliderDriver

    sim = _SimulatedFfc(rate_max=5.0, kappa_max=3.31, reports=reports)
    driver = SliderDriver(sim, sim.measured, lambda _n: 5.0, lambda: True, lambda _w: None).start()
    try:
        driver.set_target("segment_1", 3.0, 0.0)
        peak_cmd = 0.0
        end = time.monotonic() + 8.0  # it gets there in ~3.5 s; a loaded machine is slower
        while time.monotonic() < end and abs(sim.meas[0] - 3.0) >= 0.05:
            peak_cmd = max(peak_cmd, sim.cmd[0])
            time.sleep(0.005)
        assert peak_cmd <= 3.0 + 1e-6, peak_cmd
        assert sim.peak <= 3.0 + 1e-6, sim.peak
        assert abs(sim.meas[0] - 3.0) < 0.05, sim.meas
    finally:
        driver.close()
        sim.stop()


@pytest.mark.parametrize(
    "segment",
    [{"slew": 1.0}, {"meas_cap": 2.0}, {"slew": 1.0, "reports": False},
     {"meas_cap": 2.0, "reports": False}],
    ids=["firmware-slower-than-the-file", "firmware-limit-below-the-target",
         "firmware-slower-older-daemon", "firmware-limit-older-daemon"],
)  # fmt: skip
def test_a_segment_lagging_for_seconds_never_restarts_the_model_past_the_target(segment):
    """Defect (review of the fix above): one second after the last moving input the model was
    restarted from the measurement; a segment still lagging then (a firmware slewing slower than
    the file's rate, or held by its own lower limit) made the next inputs carry the setpoint on
    past the target (to kappa_max, ratcheting up with each restart). Now the model restarts from
    the measurement only once the segment has reached it."""
    from view.control import SliderDriver

    sim = _SimulatedFfc(rate_max=5.0, kappa_max=3.31, **segment)
    held = "meas_cap" in segment  # its firmware flags the clamping (STATE, LIMIT_CLAMPED)
    driver = SliderDriver(
        sim, sim.measured, lambda _n: 5.0, lambda: True, lambda _w: None,
        clamped=lambda _n: held,
    ).start()  # fmt: skip
    try:
        peak_cmd = _drive_and_watch(driver, sim, 3.0, seconds=4.0)
        # the defect ratcheted the setpoint up to kappa_max (3.31); on a loaded host the
        # simulated segment's thread can be starved long enough to look still, which costs a
        # few 1e-3 1/m here (the simulation's artefact: a real segment keeps moving)
        assert peak_cmd <= 3.0 + 0.02, peak_cmd
        assert sim.peak <= 3.0 + 0.02, sim.peak
    finally:
        driver.close()
        sim.stop()


def test_the_slider_drive_starts_from_the_setpoint_the_daemon_reports_not_the_measurement():
    """Defect (issue 15: "the slider drive models the cFFC's setpoint because the daemon does
    not publish it"): the model started from the measured state. A segment that stands short of
    its setpoint without flagging it (a stalled servo, a tendon caught; here the cFFC's setpoint
    is 2.5 1/m and the segment stays at 1.0) made the drive send full deflections from 1.0
    towards 3.0, and the true setpoint ran from 2.5 on past the target to kappa_max. Now the
    drive reads the setpoint (controllers.list at a move's start, each ffc.input reply after)
    and steers that."""
    from view.control import SliderDriver

    sim = _SimulatedFfc(rate_max=5.0, kappa_max=3.31, meas_cap=1.0, cmd=(2.5, 0.0))
    driver = SliderDriver(sim, sim.measured, lambda _n: 5.0, lambda: True, lambda _w: None)
    driver.start()
    try:
        peak_cmd = _drive_and_watch(driver, sim, 3.0, seconds=3.0)
        assert peak_cmd <= 3.0 + 1e-6, peak_cmd
        assert abs(sim.cmd[0] - 3.0) < 0.05, sim.cmd  # the setpoint got there
    finally:
        driver.close()
        sim.stop()


def test_the_robot_file_check_compares_contents_not_a_path_named_by_the_daemon(tmp_path):
    """Defect (review): when the daemon's topology named a relative file path, the view
    resolved it in its own working directory: another file of the same name there counted as the
    daemon's very file, and the name and bendables were never compared (controls allowed for the
    wrong robot). Now they are always compared."""
    import types

    from ucrdf.parser import load
    from view.source import LiveSource

    two = ROBOT.parent / "softrobot2.ucrdf"
    me = types.SimpleNamespace(_robot_file=str(two))
    robot = load(two)
    theirs = {"file": str(two), "robot": "softrobot3", "expected": ["segment_1", "segment_2",
              "segment_3"]}  # fmt: skip
    assert "is not the daemon's robot" in LiveSource._mismatch(me, robot, theirs)
    same = {"file": "elsewhere.ucrdf", "robot": robot.name, "expected": ["segment_1", "segment_2"]}
    assert LiveSource._mismatch(me, robot, same) == ""


def test_the_slider_drive_stops_when_a_page_that_set_its_targets_closes_though_another_stays():
    """Defect (docs/view.md "Limits"): the slider deadman counted any connected page with
    controls, so a page closed mid-motion left its targets driven for as long as another page
    stayed open (until the idle timeout, 10 s). Now the drive stops once any page that set one
    of its targets is gone, with one zero input, and a page that set none does not stop it."""
    from view.control import SliderDriver

    sim = _SimulatedFfc(rate_max=1.0, kappa_max=3.31)  # seconds from the target: streaming
    open_pages = {1, 2, 3}
    sent: list[dict] = []
    real_input = sim.ffc_input

    def recorded(rates: dict) -> dict:
        sent.append(dict(rates))
        return real_input(rates)

    sim.ffc_input = recorded
    driver = SliderDriver(
        sim, sim.measured, lambda _n: 1.0, lambda: bool(open_pages), lambda _w: None,
        pages=lambda: sorted(open_pages),
    ).start()  # fmt: skip
    try:
        driver.set_target("segment_1", 3.0, 0.0, "view page=1", page=1)
        driver.set_target("segment_1", 3.0, 0.0, "view page=2", page=2)
        assert wait_for(lambda: driver.streaming, 5), driver.stopped_reason
        open_pages.discard(3)  # a page that set no target: the drive goes on
        time.sleep(0.3)
        assert driver.targets and driver.stopped_reason == "", driver.stopped_reason
        open_pages.discard(1)  # page 2 stays open, page 1 set a target and is gone
        assert wait_for(lambda: driver.stopped_reason == "page closed", 2), (
            driver.stopped_reason, driver.targets,
        )  # fmt: skip
        assert not driver.targets and not driver.owners
        assert sent[-1] == {"segment_1": (0.0, 0.0)}, sent[-3:]
        # page 2 moves its slider again: a new drive, which page 2 alone keeps alive
        driver.set_target("segment_1", 2.0, 0.0, "view page=2", page=2)
        time.sleep(0.3)
        assert driver.targets and driver.stopped_reason == "", driver.stopped_reason
    finally:
        driver.close()
        sim.stop()
