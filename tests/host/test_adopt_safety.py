"""`--adopt` writes safely and never trusts a segment's own limits beyond the envelope (issue 13,
finding 7): atomic write, a symlink at the output is replaced and never followed, limits capped
by the configured envelope and the difference reported."""

from __future__ import annotations

import math
import os

import pytest

from host.config import bendable_limits
from host.topology import adopt, adopted_path
from ucrdf.parser import load


def _desc(kappa_max: float, rate: float | None = None) -> dict:
    d = {
        "name": "segment",
        "length": 0.316,
        "tendon_angles": [math.pi / 2 + k * 2 * math.pi / 3 for k in range(3)],
        "tendon_radius": 0.06,
        "spool_radius": 0.01,
        "kappa_max": kappa_max,
    }
    if rate is not None:
        d["kappa_rate_max"] = rate
    return d


def test_a_symlink_at_the_output_path_is_replaced_not_followed(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    out = tmp_path / "robot.adopted.ucrdf"
    out.symlink_to(victim)
    adopt([_desc(3.0, 5.0)], "r", out)
    assert victim.read_text() == "precious\n"
    assert not out.is_symlink() and "<bendable" in out.read_text()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp left


def test_adopted_limits_are_capped_by_the_envelope_and_reported(tmp_path):
    from host.topology import Envelope, adopt_capped

    out = tmp_path / "a.ucrdf"
    robot, capped = adopt_capped(
        [_desc(3.0, 2.0), _desc(9.0, 50.0)], "r", out, Envelope(kappa_max=4.0, kappa_rate_max=5.0)
    )
    assert capped == [
        "segment_2: kappa_max 9 1/m capped to 4 1/m",
        "segment_2: kappa_rate_max 50 1/m/s capped to 5 1/m/s",
    ]
    for r in (robot, load(out)):  # in memory and in the file written
        lim = bendable_limits(r)
        assert lim["segment_1"].kappa_max == pytest.approx(3.0)
        assert lim["segment_2"].kappa_max == pytest.approx(4.0)
        assert lim["segment_2"].kappa_rate_max == pytest.approx(5.0)


def test_the_envelope_comes_from_the_description(robot3):
    from host.topology import envelope_from

    env = envelope_from(robot3)
    kmax = max(b.model.limits.kappa_max for b in robot3.bendables.values())
    assert env.kappa_max == pytest.approx(kmax)


def _with_interface_max(robot, kmax: float):
    """``robot`` with every ``<ros2_control>`` kappa command interface ``max`` set to ``kmax``."""
    import copy

    out = copy.deepcopy(robot)
    for block in out.ros2_control:
        for joint in block.joints:
            for itf in joint.command_interfaces:
                if itf.name == "kappa":
                    itf.params["max"] = str(kmax)
    return out


def test_the_envelope_is_the_files_effective_kappa_max_with_its_interface_max(tmp_path, robot3):
    """The file's <ros2_control> kappa max (1.0) tightens its model kappa_max (3.3) for the host
    (host.limits); an adopted segment reporting 3.3 gets 1.0, and that is reported."""
    from host.topology import adopt_capped, envelope_from

    tight = _with_interface_max(robot3, 1.0)
    assert {lim.kappa_max for lim in bendable_limits(tight).values()} == {1.0}
    env = envelope_from(tight)
    assert env.kappa_max == pytest.approx(1.0)
    out = tmp_path / "a.ucrdf"
    robot, capped = adopt_capped([_desc(3.3, 5.0)], tight.name, out, env)
    assert capped == ["segment: kappa_max 3.3 1/m capped to 1 1/m"]
    for r in (robot, load(out)):
        assert bendable_limits(r)["segment"].kappa_max == pytest.approx(1.0)


def test_an_unset_rate_in_the_file_caps_adopted_segments_at_the_hosts_default(tmp_path, robot3):
    """A file without kappa_rate_max runs at DEFAULT_KAPPA_RATE_MAX: an adopted segment
    reporting 1000 1/m/s is capped to it, and that is reported."""
    import copy

    from host.limits import DEFAULT_KAPPA_RATE_MAX
    from host.topology import adopt_capped, envelope_from

    norate = copy.deepcopy(robot3)
    for b in norate.bendables.values():
        b.model.limits.kappa_rate_max = None
    assert {lim.kappa_rate_max for lim in bendable_limits(norate).values()} == {
        DEFAULT_KAPPA_RATE_MAX
    }
    env = envelope_from(norate)
    assert env.kappa_rate_max == pytest.approx(DEFAULT_KAPPA_RATE_MAX)
    out = tmp_path / "a.ucrdf"
    robot, capped = adopt_capped([_desc(3.0, 1000.0)], norate.name, out, env)
    assert capped == [
        f"segment: kappa_rate_max 1000 1/m/s capped to {DEFAULT_KAPPA_RATE_MAX:g} 1/m/s"
    ]
    for r in (robot, load(out)):
        assert bendable_limits(r)["segment"].kappa_rate_max == pytest.approx(DEFAULT_KAPPA_RATE_MAX)


def test_adopted_file_goes_to_the_state_directory(tmp_path, monkeypatch):
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path))
    assert adopted_path("/usr/share/ucr/robot.ucrdf", "x") == tmp_path / "robot.adopted.ucrdf"
    monkeypatch.delenv("STATE_DIRECTORY")
    assert str(adopted_path("/x/robot.ucrdf", "x")) == os.path.join("/x", "robot.adopted.ucrdf")


def test_daemon_adopting_a_chain_caps_limits_at_the_descriptions_envelope(tmp_path, robot3):
    """A 2-segment description with kappa_max halved, a 3-segment chain: --adopt runs the chain
    with no segment allowed more than the description's envelope, and says so."""
    import copy

    from daemon_helpers import ROBOT_FILE, emulated_configs, start_daemon, wait_for

    from host.config import DaemonConfig
    from host.daemon import Daemon
    from host.link import ChainLink
    from tools.emulator import EmulatedChain

    two = load(ROBOT_FILE.with_name("softrobot2.ucrdf"))
    small = copy.deepcopy(two)
    for b in small.bendables.values():
        b.model.limits.kappa_max /= 2
    cap = max(b.model.limits.kappa_max for b in small.bendables.values())
    out = tmp_path / "adopted.ucrdf"
    with EmulatedChain(3, config_for=emulated_configs(robot3)) as chain:
        with ChainLink(chain.host_port) as link:  # all three booted (adopt takes what answers)
            assert wait_for(lambda: len(link.discover(timeout=0.3)) == 3, 20.0, 0.1)
        d = Daemon(small, DaemonConfig(port=chain.host_port), adopt=True, adopt_path=out)
        q = d.subscribe(["event"])
        start_daemon(d)
        try:
            assert d.status()["segments"] == ["segment_1", "segment_2", "segment_3"]
            assert all(lim.kappa_max <= cap + 1e-9 for lim in d.hwi.limits.values())
            events = []
            while not q.empty():
                events.append(q.get_nowait())
            (adopted,) = [e for e in events if e.get("event") == "adopted"]
            assert len(adopted["capped"]) == 3 and "capped to" in adopted["capped"][0]
        finally:
            d.stop()
    assert all(b.model.limits.kappa_max <= cap + 1e-9 for b in load(out).bendables.values())
