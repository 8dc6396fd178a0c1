"""Pipelining in the daemon (docs/daemon.md "Pipelining", issue 14): with ``pipeline`` on, each
cycle sends its SYNC and then collects the previous SYNC's STATEs, so a chain whose exchange is
longer than the reply window still answers every cycle. On a fake link (what is sent and
collected, in which order) and end to end on the emulated chain (a goal succeeds, hot-plug)."""

from __future__ import annotations

import pytest
from daemon_helpers import (
    assert_succeeded,
    emulated_configs,
    retry_if_the_link_was_disturbed,
    start_daemon,
    wait_for,
)

from host.config import DaemonConfig, parse_config
from host.daemon import Daemon
from host.hwi import HardwareInterface
from host.limits import BendableLimits
from tools.emulator import EmulatedChain

pytestmark = pytest.mark.timeout(240)


class PipeLink:
    """Records sync_send / sync_collect / sync_abandon / heartbeat calls; a collected cycle's
    STATEs carry that cycle's number as kappa, so a test sees which SYNC it measured."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.calls: list[tuple] = []
        self.cycle = 0
        self.open: set[int] = set()

    def _states(self, cycle: int, expected: int) -> list[dict | None]:
        return [
            {
                "position": i,
                "cycle": cycle,
                "t_ms": cycle,
                "kappa": float(cycle),
                "phi": 0.0,
                "kx": float(cycle),
                "ky": 0.0,
                "status": set(),
            }  # fmt: skip
            for i in range(expected)
        ]

    def sync_send(self, setpoints, *, expected=None, resume=False):
        self.cycle += 1
        self.open.add(self.cycle)
        self.calls.append(("send", self.cycle, expected))
        return (self.cycle, expected)

    def sync_collect(self, pending, timeout=0.1):
        cycle, expected = pending
        self.open.remove(cycle)
        self.calls.append(("collect", cycle))
        return self._states(cycle, expected)

    def sync_abandon(self, pending) -> None:
        self.open.discard(pending[0])
        self.calls.append(("abandon", pending[0]))

    def heartbeat(self, timeout=0.1, *, expected=None):
        self.cycle += 1
        self.calls.append(("heartbeat", self.cycle))
        return self._states(self.cycle, self.n)


def _hwi(link: PipeLink) -> HardwareInterface:
    limits = {
        f"segment_{i + 1}": BendableLimits(f"segment_{i + 1}", 0.3, 5.0, 10.0)
        for i in range(link.n)
    }
    hwi = HardwareInterface(limits, link, 0.01, pipeline=True)
    hwi.configure()
    hwi.activate()
    return hwi


def test_each_cycle_sends_its_sync_then_collects_the_previous_one() -> None:
    link = PipeLink(2)
    hwi = _hwi(link)
    link.calls.clear()
    measured = []
    for _ in range(4):
        hwi.write()
        hwi.read()
        measured.append(hwi.raw_states[0]["cycle"])
    # cycle 1 was the configure HEARTBEAT; the first SYNC (2) starts the pipeline and is
    # collected by the next cycle, after SYNC 3 left: always one SYNC in flight, never two
    assert link.calls == [
        ("send", 2, 2),
        ("send", 3, 2),
        ("collect", 2),
        ("send", 4, 2),
        ("collect", 3),
        ("send", 5, 2),
        ("collect", 4),
    ]
    assert measured == [1, 2, 3, 4]  # read() never skips a SYNC nor takes one twice
    assert link.open == {5}


def test_a_probe_is_pipelined_and_its_states_are_read_as_probed() -> None:
    link = PipeLink(1)
    hwi = _hwi(link)
    hwi.write()  # SYNC 2, in flight
    hwi.probe_extra = 1
    hwi.write()  # SYNC 3 waits beyond the tip; collects 2 (not probed)
    hwi.read()
    assert hwi.exchange_probed is False and hwi.extra_states == []
    hwi.probe_extra = 0
    hwi.write()  # collects 3: probed, its second STATE is from beyond the tip
    hwi.read()
    assert ("send", 3, 2) in link.calls
    assert hwi.exchange_probed is True and [s["cycle"] for s in hwi.extra_states] == [3]


def test_going_inactive_closes_the_open_cycle_without_waiting() -> None:
    link = PipeLink(1)
    hwi = _hwi(link)
    hwi.write()
    hwi.deactivate()
    hwi.write()
    assert link.calls[-2:] == [("abandon", 2), ("heartbeat", 3)]
    assert link.open == set()


def test_the_config_file_and_its_errors() -> None:
    assert parse_config({"pipeline": True}).pipeline is True
    assert parse_config({}).pipeline is False
    with pytest.raises(ValueError, match="pipeline"):
        parse_config({"pipeline": "yes"})


def test_the_daemon_runs_a_goal_and_follows_a_hot_plug_pipelined(robot3) -> None:
    names = ["segment_1", "segment_2", "segment_3"]
    with EmulatedChain(3, config_for=emulated_configs(robot3)) as chain:
        d = Daemon(robot3, DaemonConfig(port=chain.host_port, pipeline=True))
        start_daemon(d)
        try:
            assert d.topo.hwi.pipeline

            def goal() -> None:
                gid = d.send_trajectory(
                    [
                        {
                            "time_from_start": 0.6,
                            "segments": {n: {"kappa": 1.0, "phi": 0.5} for n in names},
                        },
                        {
                            "time_from_start": 1.2,
                            "segments": {n: {"kappa": 0.0, "phi": 0.0} for n in names},
                        },
                    ]  # fmt: skip
                )
                assert wait_for(lambda: d.trajectory_status(gid)["done"], 20.0)
                assert_succeeded(d, gid)

            retry_if_the_link_was_disturbed(d, goal)
            chain.unplug(2)
            assert wait_for(lambda: d.status()["segments"] == names[:2], 20.0), d.status()
            chain.plug(2)
            assert wait_for(
                lambda: (
                    d.status()["segments"] == names
                    and all(v["valid"] for v in d.status()["joint_states"].values())
                ),
                30.0,
            ), d.status()
            retry_if_the_link_was_disturbed(d, goal)
        finally:
            d.stop()


def test_the_rate_warning_knows_the_pipelined_window() -> None:
    """8 segments at 921600 bd need 8.3 ms per exchange: more than a 100 Hz loop's 8 ms reply
    window (the warning suggests pipelining), less than the 18 ms a pipelined loop allows."""
    from host.chain_report import largest_rate_hz, rate_warning

    plain = rate_warning(8, 921600, 0.008, 0.02, 100)
    assert plain is not None and "pipeline: true" in plain
    assert rate_warning(8, 921600, 0.008, 0.02, 100, pipeline=True) is None
    slow = rate_warning(8, 115200, 0.008, 0.02, 100, pipeline=True)
    assert slow is not None and "(pipelined)" in slow and "rate_hz <= 27" in slow
    # never above what link 0 carries at one exchange per period
    assert largest_rate_hz(1, 921600, pipeline=True) <= 921600 / 10 / 34
