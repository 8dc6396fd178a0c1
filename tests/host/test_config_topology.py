"""Daemon configuration, interface limits from <ros2_control>, topology comparison and the
`ucr daemon` error paths (no chain needed)."""

from __future__ import annotations

import copy
import math

import pytest
from daemon_helpers import ROBOT_FILE, wait_for

from host.config import ConfigError, DaemonConfig, bendable_limits, load_config, parse_config
from host.loop import FixedRateLoop
from host.topology import adopted_path, chain_bendables, compare, truncate
from tools.cli import main


def test_defaults_without_a_file():
    cfg = load_config(None)
    assert cfg.rate_hz == 100.0 and cfg.api.bind == "127.0.0.1"
    assert cfg.baudrate is None  # not given: the U(C)RDF's, else 921600 (link_baudrate)
    assert cfg.active == ["jtc", "jsb", "rsp"] and set(cfg.controllers) == {
        "jtc",
        "ffc",
        "jsb",
        "rsp",
    }


def test_full_config_is_read(tmp_path):
    p = tmp_path / "daemon.yaml"
    p.write_text(
        "port: socket://localhost:7777\nbaudrate: 115200\nrate_hz: 250\n"
        "controllers:\n  traj: {type: cJTC, params: {goal_tolerance: 0.02}}\n"
        "  pad: {type: ffc}\nactive: [traj]\n"
        "api: {bind: 0.0.0.0, port: 9000, token: secret-token-0123456789}\n"
        "watchdog: {missed_cycles: 5, reply_timeout_s: 0.004}\n"
    )
    p.chmod(0o600)  # a config holding a token must be private (issue 13)
    cfg = load_config(p)
    assert cfg.port == "socket://localhost:7777" and cfg.rate_hz == 250.0
    assert cfg.controllers["traj"] == {"type": "cJTC", "params": {"goal_tolerance": 0.02}}
    assert cfg.active == ["traj"] and cfg.api.token == "secret-token-0123456789"
    assert cfg.watchdog.missed_cycles == 5


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("rate_hz: fast\n", "rate_hz"),
        ("rate_hz: 0\n", "rate_hz"),
        ("baudrate: 9600.5\n", "baudrate"),
        ("portt: /dev/ttyUSB0\n", "portt"),
        ("controllers: {x: {type: warp}}\n", "controllers.x.type"),
        ("controllers: {x: {type: jtc, param: {}}}\n", "controllers.x.param"),
        ("active: [nope]\n", "active"),
        ("api: {port: 70000}\n", "api.port"),
        ("watchdog: {missed_cycles: 0}\n", "watchdog.missed_cycles"),
        ("rate_hz: [1\n", "line"),
    ],
)
def test_bad_config_names_the_file_and_the_key(tmp_path, text, key):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    msg = str(ei.value)
    assert msg.startswith(f"{p}: {key}") and "\n" not in msg


def test_ucr_daemon_bad_config_is_one_line_exit_1(tmp_path, capsys):
    p = tmp_path / "bad.yaml"
    p.write_text("rate_hz: -5\n")
    rc = main(["daemon", "--robot", str(ROBOT_FILE), "--config", str(p), "--port", "/dev/null"])
    err = capsys.readouterr().err
    assert rc == 1
    assert err.strip() == f"ucr: error: {p}: rate_hz: must be >= 1.0, got -5"


def test_ucr_daemon_missing_robot_and_port_errors_are_clear(tmp_path, capsys):
    assert main(["daemon", "--robot", str(tmp_path / "none.ucrdf"), "--port", "x"]) == 1
    err = capsys.readouterr().err
    assert "none.ucrdf" in err and "Traceback" not in err
    bad_port = str(tmp_path / "no-such-tty")
    assert main(["daemon", "--robot", str(ROBOT_FILE), "--port", bad_port, "--no-api"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ucr: error: cannot open chain port") and "Traceback" not in err


def test_interface_limits_come_from_ros2_control(robot3):
    r = copy.deepcopy(robot3)
    lim = bendable_limits(r)
    assert list(lim) == ["segment_1", "segment_2", "segment_3"]
    assert lim["segment_1"].kappa_max == pytest.approx(math.pi / 3 / 0.316)
    assert lim["segment_1"].kappa_rate_max == 5.0
    itf = r.ros2_control[0].joints[1].command_interfaces[0]
    itf.params["max"] = 2.0  # tighter than the model: wins
    assert bendable_limits(r)["segment_2"].kappa_max == 2.0
    itf.params["max"] = "lots"
    with pytest.raises(ConfigError, match=r"command_interface\[kappa\]\.max: expected a number"):
        bendable_limits(r)


def descriptors_of(robot) -> list[dict]:
    out = []
    for i, name in enumerate(chain_bendables(robot)):
        b = robot.bendables[name]
        out.append(
            {
                "position": i,
                "uid": f"00ab{i:02x}",
                "name": name,
                "model": b.model.type,
                "length": b.length,
                "tendon_angles": list(b.actuation.angles),
                "tendon_radius": b.actuation.radius,
                "spool_radius": b.actuation.spool_radius,
                "kappa_max": b.model.limits.kappa_max,
                "kappa_rate_max": b.model.limits.kappa_rate_max,
                "downstream_present": i < len(robot.bendables) - 1,
            }
        )
    return out


def test_compare_matching_chain_is_ok(robot3):
    cmp = compare(robot3, descriptors_of(robot3))
    assert cmp.ok and cmp.matched == 3 and cmp.differences == []


def test_compare_says_exactly_what_differs(robot3):
    descs = descriptors_of(robot3)
    descs[1]["length"] = 0.25
    descs[1]["kappa_max"] = 9.0
    descs[2]["model"] = "ppc"
    cmp = compare(robot3, descs)
    assert not cmp.ok and cmp.matched == 1
    msgs = [d.message for d in cmp.differences]
    assert (
        "position 2 (segment_2): length 0.25 m on the segment, 0.316 m in the description" in msgs
    )
    assert any("kappa_max 9.0 1/m on the segment" in m for m in msgs)
    assert "position 3 (segment_3): model 'ppc' on the segment, 'pcc' in the description" in msgs
    short = compare(robot3, descriptors_of(robot3)[:2])
    assert short.matched == 2 and short.differences[0].kind == "count"
    assert "declares 3: missing segment_3" in short.differences[0].message


def test_compare_blocks_a_segment_that_refused_its_configuration(robot3):
    """Review: a segment without (or with an invalid) config.json holds and never moves, but the
    comparison did not say so: the daemon took it under control and its goals only failed their
    tolerances. Now a blocking `config` difference names it and how to fix it."""
    descs = descriptors_of(robot3)
    descs[1]["config_error"] = "no config.json: flash one (ucr flash)"
    cmp = compare(robot3, descs)
    assert not cmp.ok and cmp.matched == 1
    first = cmp.differences[0]
    assert first.kind == "config" and first.blocking and first.position == 1
    assert first.message.startswith(
        "position 2 (segment_2): the segment refused its configuration (no config.json"
    )
    assert "ucr flash --robot ROBOT --segment segment_2" in first.message


def test_compare_checks_identity_when_the_description_pins_uids(robot3):
    r = copy.deepcopy(robot3)
    r.ros2_control[0].hardware_params["segment_2/uid"] = "deadbeef"
    cmp = compare(r, descriptors_of(r))
    assert [d.kind for d in cmp.differences] == ["identity"]
    assert "uid '00ab01' on the segment, 'deadbeef' pinned" in cmp.differences[0].message


def test_truncate_cuts_the_chain_and_its_interfaces(robot3):
    two = truncate(robot3, 2)
    assert chain_bendables(two) == ["segment_1", "segment_2"]
    assert "segment_3_tip" not in two.links
    assert [j.name for j in two.ros2_control[0].joints] == ["segment_1", "segment_2"]
    assert chain_bendables(robot3) == ["segment_1", "segment_2", "segment_3"]  # untouched
    assert adopted_path(str(ROBOT_FILE), "x").name == "softrobot3.adopted.ucrdf"


def test_loop_runs_at_its_rate_and_counts_overruns():
    calls = []

    def step():
        calls.append(1)
        return 1e-5

    loop = FixedRateLoop(0.005, step)
    loop.start()
    assert wait_for(lambda: len(calls) >= 40, 5.0)
    loop.stop()
    s = loop.stats.snapshot(0.005)
    assert s["cycles"] >= 40 and s["compute_us"]["mean"] == pytest.approx(10.0)
    assert 3000 < s["period_us"]["mean"] < 8000  # loose: shared CI machine

    import time

    def slow():
        time.sleep(0.012)

    loop = FixedRateLoop(0.01, slow)
    loop.start()
    assert wait_for(lambda: loop.stats.cycles >= 5, 5.0)
    loop.stop()
    assert loop.stats.overruns >= 4


def test_overruns_a_late_chain_causes_are_told_apart_from_the_loop_s_own():
    """A cycle that waits 12 ms on I/O (the chain) with 0.1 ms of compute overran because of the
    chain; one that computes 12 ms overran by itself."""
    import time

    def waits_on_chain():
        time.sleep(0.012)
        return 1e-4

    def computes():
        end = time.perf_counter() + 0.012
        while time.perf_counter() < end:
            pass
        return 0.012

    for step, by_chain in ((waits_on_chain, True), (computes, False)):
        loop = FixedRateLoop(0.01, step)
        loop.start()
        assert wait_for(lambda: loop.stats.cycles >= 5, 5.0)  # noqa: B023 - called at once
        loop.stop()
        s = loop.stats.snapshot(0.01)
        assert s["overruns"] >= 4
        assert s["overruns_waiting_on_chain"] == (s["overruns"] if by_chain else 0), s


def test_daemon_refuses_without_a_port(robot3):
    from host.daemon import Daemon, DaemonError

    with pytest.raises(DaemonError, match="no chain port"):
        Daemon(robot3, DaemonConfig())
    with pytest.raises(ConfigError):
        parse_config({"rate_hz": True})


def test_the_chain_baudrate_comes_from_the_config_else_from_the_ucrdf(tmp_path):
    """Review 2026-11-26: the U(C)RDF's <param name="baudrate"> was read by nothing (the port
    param was). Precedence as for the port: the configuration's baudrate, else the file's."""
    from host.daemon import Daemon
    from ucrdf.parser import load

    text = (ROBOT_FILE.parent / "softrobot2.ucrdf").read_text()
    assert '<param name="baudrate">921600</param>' in text
    slow = tmp_path / "slow.ucrdf"
    slow.write_text(text.replace('<param name="baudrate">921600</param>',
                                 '<param name="baudrate">115200</param>'))  # fmt: skip
    for cfg, want in ((parse_config(None), 115200), (parse_config({"baudrate": 460800}), 460800)):
        assert Daemon(load(slow), cfg, port="loop://").cfg.baudrate == want
    cfg_file = tmp_path / "d.yaml"
    cfg_file.write_text("rate_hz: 50\n")
    assert Daemon(load(slow), load_config(cfg_file), port="x").cfg.baudrate == 115200


def test_a_rate_of_zero_is_refused_not_replaced_by_the_configs(robot3):
    """Review 2026-11-26: `ucr daemon --rate 0` ran at the config's 100 Hz without a word
    (`rate_hz or cfg.rate_hz`), while --rate 0.5 was refused."""
    from host.daemon import Daemon, DaemonError

    for rate in (0.0, 0.5):
        with pytest.raises(DaemonError, match="outside 1..2000 Hz"):
            Daemon(robot3, DaemonConfig(), port="loop://", rate_hz=rate)
