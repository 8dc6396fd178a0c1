"""Review 2026-11-27 (configuration and teleop): controller parameters checked when the daemon's
configuration is read (before the chain port is opened), cFFC bounds, watchdog bounds, teleop
driving the cFFC's own joints, a lost gamepad as a failure, repeated keys in recordings, and
``--speed`` without ``--replay``. Each test says what happened before the fix."""

from __future__ import annotations

import io
import json
import os
import select
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from daemon_helpers import free_url

import host.client_motion as client_motion
from host.api.server import ApiServer
from host.client_common import CliError
from host.config import ConfigError, load_config, parse_config
from host.controller_manager import ControllerManager
from host.controllers.base import ControllerContext, ControllerError, RobotState
from host.controllers.ffc import FeedForwardController
from host.daemon import Daemon
from host.limits import bendable_limits
from host.teleop import InputEvent, Recorder, Teleop, TeleopError, parse_recording
from tools.cli import main as ucr

pytestmark = pytest.mark.timeout(60)
REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"

from test_api_protocol import FacadeStub  # noqa: E402 - the in-memory facade


def config_error(tmp_path: Path, text: str) -> str:
    p = tmp_path / "daemon.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith(f"{p}: "), msg
    return msg.removeprefix(f"{p}: ")


# ------------------------------------------------------------------ 1. controller params
@pytest.mark.parametrize(
    ("text", "key", "needle"),
    [
        # before: accepted; the daemon then ran without the cFFC ("controller ffc not loaded")
        (
            "controllers: {ffc: {type: ffc, params: {deadman_timout: 0.5}}}\n",
            "ffc",
            "deadman_timout",
        ),
        ("controllers: {traj: {type: cJTC, params: {rate_margin: 5}}}\n", "traj", "rate_margin"),
        ("controllers: {jsb: {type: jsb, params: {rate_hz: fast}}}\n", "jsb", "rate_hz"),
        ("controllers: {rsp: {type: rsp, params: {backbone_samples: 1}}}\n", "rsp", "backbone"),
        ("controllers: {jtc: {type: jtc, params: {joints: segment_1}}}\n", "jtc", "joints"),
    ],
)
def test_a_bad_controller_parameter_is_refused_when_the_config_is_read(tmp_path, text, key, needle):
    msg = config_error(tmp_path, text)
    assert msg.startswith(f"controllers.{key}.params: controller {key!r}"), msg
    assert needle in msg


def test_good_controller_parameters_are_read_and_still_build_the_controllers(robot3):
    cfg = parse_config(
        {
            "controllers": {
                "jtc": {"type": "jtc", "params": {"goal_tolerance": 0.02, "rate_margin": 1}},
                "pad": {"type": "cFFC", "params": {"joints": ["segment_2"], "gain": 0.5}},
                "jsb": {"type": "jsb", "params": {"rate_hz": 10}},
                "rsp": {"type": "rsp", "params": {"backbone_samples": 4}},
            }
        }
    )
    ctx = ControllerContext(bendable_limits(robot3), robot3)
    cm = ControllerManager(cfg.controllers, ctx)
    assert cm.failed == {} and cm.controllers["pad"].joints == ["segment_2"]
    assert cm.controllers["pad"].gain == 0.5 and cm.controllers["jtc"].goal_tolerance == 0.02


def test_joints_naming_no_bendable_of_the_robot_are_refused_when_the_daemon_is_built(robot3):
    """Before: accepted; the controller silently commanded only the bendables it found."""
    cfg = parse_config(
        {"controllers": {"jtc": {"type": "jtc", "params": {"joints": ["segment_1", "segmnt_2"]}}}},
        "daemon.yaml",
    )
    with pytest.raises(ConfigError) as ei:
        Daemon(robot3, cfg, port="never-opened")
    msg = str(ei.value)
    assert msg.startswith("daemon.yaml: controllers.jtc.params: joints: 'segmnt_2' is not a")
    assert "segment_1, segment_2, segment_3" in msg
    # --adopt: the robot comes from the chain, whose names the file may not know
    Daemon(robot3, cfg, port="never-opened", adopt=True)


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("controllers: {ffc: {type: ffc, params: {deadman_timout: 0.5}}}\n", "controllers.ffc"),
        ("controllers: {jtc: {type: jtc, params: {joints: [segment_9]}}}\n", "controllers.jtc"),
    ],
)
def test_ucr_daemon_stops_with_one_line_before_the_port_is_opened(tmp_path, text, key):
    """Before: the port was opened, the chain discovered, and the daemon ran on without the
    controller (the log said `controller ffc not loaded`; teleop then found no cFFC)."""
    master, slave = os.openpty()
    try:
        cfg = tmp_path / "daemon.yaml"
        cfg.write_text(text)
        argv = ["daemon", "--robot", str(ROBOT), "--config", str(cfg), "--no-api"]
        res = subprocess.run(
            [sys.executable, "-m", "tools.cli", *argv, "--port", os.ttyname(slave)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert res.returncode == 1, res
        assert res.stderr.startswith(f"ucr: error: {cfg}: {key}.params: "), res.stderr
        assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
        ready, _, _ = select.select([master], [], [], 0.2)
        assert not ready, os.read(master, 256)  # nothing was sent: the port was never opened
    finally:
        os.close(master)
        os.close(slave)


# ------------------------------------------------------------------ 4. cFFC bounds
@pytest.mark.parametrize(
    ("params", "needle"),
    [
        ({"gain": 0}, "'gain' must be a number > 0 and <= 1"),  # before: accepted
        ({"deadman_timeout": 100.0}, "'deadman_timeout' must be a number >= 0.01 and <= 2"),
        ({"gain": 1.5}, "'gain'"),
        ({"deadzone": 1.0}, "'deadzone' must be < 1"),
    ],
)
def test_ffc_gain_must_move_and_the_deadman_must_be_short(robot3, params, needle):
    ctx = ControllerContext(bendable_limits(robot3), robot3)
    with pytest.raises(ControllerError, match=needle):
        FeedForwardController("ffc", params, ctx)
    with pytest.raises(ConfigError, match="controllers.ffc.params"):
        parse_config({"controllers": {"ffc": {"type": "ffc", "params": params}}})
    ok = FeedForwardController("ffc", {"deadman_timeout": 2.0, "gain": 0.01}, ctx)
    assert ok.deadman_timeout == 2.0 and ok.gain == 0.01


# ------------------------------------------------------------------ 5. watchdog bounds
@pytest.mark.parametrize(
    ("text", "key"),
    [
        # before: accepted, and the first reconnect waited 50 s
        ("watchdog: {reconnect_min_s: 50, reconnect_max_s: 0.1}\n", "watchdog.reconnect_min_s"),
        ("watchdog: {reconnect_max_s: 0.05}\n", "watchdog.reconnect_max_s"),  # min 0.1 default
        ("watchdog: {discover_timeout_s: 1000}\n", "watchdog.discover_timeout_s"),
        ("watchdog: {silence_s: 3600}\n", "watchdog.silence_s"),
        ("watchdog: {missed_cycles: 1000000}\n", "watchdog.missed_cycles"),
        ("watchdog: {reconnect_max_s: 86400}\n", "watchdog.reconnect_max_s"),
    ],
)
def test_watchdog_values_have_upper_bounds_and_a_minimum_below_the_maximum(tmp_path, text, key):
    assert config_error(tmp_path, text).startswith(f"{key}: must be ")


def test_the_documented_watchdog_maxima_are_accepted():
    wd = parse_config(
        {
            "watchdog": {
                "missed_cycles": 100,
                "silence_s": 5,
                "discover_timeout_s": 10,
                "reconnect_min_s": 60,
                "reconnect_max_s": 60,
            }
        }
    ).watchdog
    assert (wd.missed_cycles, wd.silence_s, wd.discover_timeout_s) == (100, 5.0, 10.0)


# ------------------------------------------------------------------ 2. teleop's segments
class SubsetFacade(FacadeStub):
    """A daemon whose cFFC commands segment s2 only, and refuses other names as the real one
    does (FeedForwardController.validate_input)."""

    def topology(self) -> dict:
        return {"robot": "stub", "expected": ["s1", "s2"], "controlled": ["s1", "s2"]}

    def controllers(self) -> list[dict]:
        return [
            {"name": "jtc", "type": "jtc", "state": "active", "joints": ["s1", "s2"]},
            {"name": "pad", "type": "ffc", "state": "inactive", "joints": ["s2"]},
        ]

    def ffc_input(self, rates: dict, source: dict | None = None) -> dict:
        bad = sorted(set(rates) - {"s2"})
        if bad:
            raise ControllerError(f"ffc input: bendable {bad[0]!r} is not commanded by 'pad'")
        return super().ffc_input(rates, source)


@pytest.fixture
def subset_url():
    stub = SubsetFacade()
    srv = ApiServer(stub, "127.0.0.1", 0).start()
    yield srv.url, stub
    srv.stop()
    stub.close()


def run(capsys, *argv) -> tuple[int, str, str]:
    rc = ucr(list(argv))
    out, err = capsys.readouterr()
    err = "".join(ln for ln in err.splitlines(True) if " AUDIT " not in ln)
    return rc, out, err


def test_keyboard_teleop_drives_the_cffcs_own_joints(capsys, subset_url, monkeypatch):
    """Before: the keyboard source got every controlled segment (s1, s2) and sent zeros for
    s1, which a cFFC with `joints: [s2]` refused: teleop could not drive it at all."""
    import host.teleop as teleop

    url, stub = subset_url
    seen: list[list[str]] = []

    class Keys:
        def __init__(self, names: list[str]) -> None:
            seen.append(list(names))
            self.names = list(names)
            self.sent = False

        def read(self, timeout: float) -> list[InputEvent]:
            if not self.sent:
                self.sent = True
                return [InputEvent("rates", {n: (0.5, 0.0) for n in self.names})]
            return [InputEvent("quit")]

        def close(self) -> None:
            pass

    monkeypatch.setattr(teleop, "KeyboardSource", Keys)
    monkeypatch.setattr(sys, "stdin", SimpleNamespace(isatty=lambda: True))
    rc, out, err = run(capsys, "teleop", "--url", url, "--keyboard")
    assert rc == 0, err
    assert seen == [["s2"]] and "1=s2" in out
    assert stub.ffc_calls[-1] == {"s2": (0.0, 0.0)}  # the quit's zero, accepted


def test_ctrl_c_zero_names_only_the_cffcs_joints(capsys, subset_url, monkeypatch):
    """Before: the Ctrl-C zero named every controlled segment and was refused (`interrupted:
    the cFFC's deadman stops the segments`)."""
    import host.teleop as teleop

    url, stub = subset_url

    def interrupt(self, source):
        raise KeyboardInterrupt

    monkeypatch.setattr(teleop.Teleop, "run", interrupt)
    monkeypatch.setattr(sys, "stdin", SimpleNamespace(isatty=lambda: True))
    monkeypatch.setattr(teleop.KeyboardSource, "__init__", lambda self, names: None)
    monkeypatch.setattr(teleop.KeyboardSource, "close", lambda self: None)
    rc, _, err = run(capsys, "teleop", "--url", url, "--keyboard")
    assert rc == 130 and "zero input sent" in err, err
    assert stub.ffc_calls == [{"s2": (0.0, 0.0)}]


class DeadmanFacade(SubsetFacade):
    def controllers(self) -> list[dict]:
        return [{**d, "deadman_timeout_s": 0.3} for d in super().controllers()]

    def status(self) -> dict:
        return {**super().status(), "manual_control": ["pad"]}


def test_teleop_refuses_a_rate_slower_than_the_deadman_allows(capsys, monkeypatch):
    """Review finding (teleop pass): `--rate 2` was accepted with the cFFC's 0.3 s deadman, so
    the deadman stopped the segments between commands (stutter). Now a period above half the
    deadman is a usage error naming the rate that works; 7 Hz (143 ms < 150 ms) is accepted."""
    import host.teleop as teleop

    stub = DeadmanFacade()
    srv = ApiServer(stub, "127.0.0.1", 0).start()
    monkeypatch.setattr(sys, "stdin", SimpleNamespace(isatty=lambda: True))

    class Keys:
        def __init__(self, names: list[str]) -> None:
            self.names = names

        def read(self, timeout: float) -> list[InputEvent]:
            return [InputEvent("quit")]

        def close(self) -> None:
            pass

    monkeypatch.setattr(teleop, "KeyboardSource", Keys)
    try:
        rc, _, err = run(capsys, "teleop", "--url", srv.url, "--keyboard", "--rate", "2")
        assert rc == 2 and "deadman (300 ms)" in err and "use --rate 7 or more" in err, err
        assert stub.ffc_calls == []
        rc, out, err = run(capsys, "teleop", "--url", srv.url, "--keyboard", "--rate", "7")
        assert rc == 0, err
        # the hint after teleop no longer promises the trajectory controller back (review: after
        # `switch --stop jtc` there was nothing to hand back to)
        assert "restarts the controllers it took over from, if any" in out, out
    finally:
        srv.stop()
        stub.close()


def test_teleop_segments_read_the_real_controller_description(robot3):
    """What `controllers.list` carries from a real controller manager: the active cFFC, else
    the first; a failed one is named with its error (the daemon would say only "no cFFC")."""
    ctx = ControllerContext(bendable_limits(robot3), robot3)
    specs = {
        "jtc": {"type": "jtc", "params": {}},
        "pad": {"type": "cFFC", "params": {"joints": ["segment_3", "segment_2"]}},
        "pad2": {"type": "ffc", "params": {"joints": ["segment_1"]}},
    }
    cm = ControllerManager(specs, ctx)
    client = SimpleNamespace(controllers=cm.describe, topology=lambda: {"controlled": []})
    # chain order, as the daemon's cFFC holds them
    assert client_motion.teleop_segments(client) == ("pad", ["segment_2", "segment_3"], 0.3)
    names = ["segment_1", "segment_2", "segment_3"]
    cm.switch(["pad2"], [], RobotState.zeros(names))
    assert client_motion.teleop_segments(client) == ("pad2", ["segment_1"], 0.3)
    broken = SimpleNamespace(
        controllers=lambda: [{"name": "pad", "type": "cFFC", "state": "failed", "error": "x"}]
    )
    with pytest.raises(CliError, match="the cFFC 'pad' failed to load: x"):
        client_motion.teleop_segments(broken)
    old = SimpleNamespace(
        controllers=lambda: [{"name": "jtc"}], topology=lambda: {"controlled": ["a"]}
    )
    # a daemon that does not say which cFFC: the controlled segments, as before
    assert client_motion.teleop_segments(old) == (None, ["a"], None)


# ------------------------------------------------------------------ 6. lost gamepad
class LostPad:
    """An evdev-like device that fails on its first read (unplugged)."""

    def __init__(self, evdev) -> None:
        self.r, self.w = os.pipe()
        os.write(self.w, b"x")  # readable: select() returns, read() then fails
        self.fd = self.r
        self.name = "Test Pad"
        info = SimpleNamespace(min=-32768, max=32767)
        e = evdev.ecodes
        self._caps = {e.EV_ABS: [(c, info) for c in (e.ABS_X, e.ABS_Y, e.ABS_RX, e.ABS_RY)]}

    def capabilities(self):
        return self._caps

    def read(self):
        raise OSError(19, "No such device")

    def close(self) -> None:
        os.close(self.r)
        os.close(self.w)


def test_a_gamepad_lost_mid_session_is_a_failure(capsys, subset_url, monkeypatch):
    """Before: `teleop ended (end: gamepad lost: No such device)` and exit 0."""
    evdev = pytest.importorskip("evdev")
    import host.teleop as teleop

    url, _ = subset_url
    real = teleop.GamepadSource
    monkeypatch.setattr(
        teleop, "GamepadSource", lambda names, path=None: real(names, device=LostPad(evdev))
    )
    rc, out, err = run(capsys, "teleop", "--url", url)
    assert rc == 1, (out, err)
    assert err == (
        "ucr: teleop cut off: gamepad lost: No such device (the cFFC's deadman stops the "
        "segments)\n"
    )
    assert "teleop ended (gamepad lost: No such device)" in out


def test_a_lost_device_is_recorded_as_the_end_of_the_input():
    """A recording of a session cut off must replay: it ends there (`end`), as before."""

    class Gone:
        names = ["s1"]

        def read(self, timeout: float) -> list[InputEvent]:
            return [InputEvent("lost", note="gamepad lost: No such device")]

    buf = io.StringIO()
    source = Recorder(Gone(), buf, clock=lambda: 0.0)
    result = Teleop(lambda rates: None).run(source, max_duration=1.0)
    assert result.reason == "lost"
    assert json.loads(buf.getvalue().splitlines()[0]) == {"t": 0.0, "end": True}
    assert parse_recording(buf.getvalue().splitlines())[0][1].kind == "end"


# ------------------------------------------------------------------ 7. repeated keys
@pytest.mark.parametrize(
    ("line", "key"),
    [
        ('{"t": 0, "rates": {"a": [1, 0], "a": [0, 0]}}', "a"),
        ('{"t": 0, "t": 5, "stop": true}', "t"),
    ],
)
def test_a_recording_line_with_a_repeated_key_is_refused_with_its_line(line, key):
    """Before: accepted, the last value winning."""
    with pytest.raises(TeleopError) as ei:
        parse_recording(['{"t": 0, "stop": true}', line], "stick.jsonl")
    assert str(ei.value) == f"stick.jsonl:2: duplicate key {key!r} in an object"
    with pytest.raises(TeleopError, match=r"stick.jsonl:1: not JSON"):
        parse_recording(["{"], "stick.jsonl")


# ------------------------------------------------------------------ 8. --speed alone
def test_speed_without_replay_is_a_usage_error_before_connecting(capsys):
    """Before: accepted and ignored (here: exit 1, the daemon unreachable)."""
    rc, _, err = run(capsys, "teleop", "--url", free_url(), "--keyboard", "--speed", "2")
    assert rc == 2
    assert err == "ucr: --speed is the speed of a replay: give it with --replay FILE\n"


def test_speed_with_replay_still_plays_faster(capsys, stub_url, tmp_path):
    rec = tmp_path / "stick.jsonl"
    rec.write_text('{"t": 0.0, "rates": {"s1": [0.5, 0.0]}}\n{"t": 0.4, "stop": true}\n')
    argv = ["teleop", "--url", stub_url, "--replay", str(rec), "--speed", "4"]
    rc, out, err = run(capsys, *argv)
    assert rc == 0, err
    assert "teleop ended (end: end of recording)" in out


@pytest.mark.parametrize(
    ("option", "said"),
    [
        (["--rate", "0"], "argument --rate: must be a finite number of Hz >= 1"),
        (["--rate", "nan"], "argument --rate: must be a finite number of Hz >= 1"),
        (["--rate", "2001"], "argument --rate: must be <= 2000"),
        (["--rt-priority", "99"], "argument --rt-priority: must be <= 98"),
        (["--adopt-out", "x.ucrdf"], "--adopt-out needs --adopt"),
    ],
)
def test_ucr_daemon_option_values_no_run_could_use_are_usage_errors(option, said, capsys):
    # before: --rate 0/nan and --rt-priority 99 exited 1 (a DaemonError after loading), and
    # --adopt-out without --adopt was silently ignored
    from tools.cli import main

    robot = str(Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf")
    argv = ["daemon", "--robot", robot, "--port", "/dev/null", "--no-api", *option]
    with pytest.raises(SystemExit) as exc:
        raise SystemExit(main(argv))
    assert exc.value.code == 2
    assert said in capsys.readouterr().err
