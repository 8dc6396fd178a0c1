"""Real-time scheduling of the daemon's loop and link reader threads (host/realtime.py): only the
thread that enters takes SCHED_FIFO, nothing it starts inherits it, a refusal degrades to normal
scheduling with a warning, and the daemon reports what each thread got."""

from __future__ import annotations

import logging
import os
import threading

import pytest
from daemon_helpers import emulated_configs, start_daemon, wait_for

from host import realtime
from host.config import ConfigError, DaemonConfig, parse_config
from host.daemon import Daemon, DaemonError
from host.loop import FixedRateLoop

linux_only = pytest.mark.skipif(
    not hasattr(os, "sched_setscheduler"), reason="SCHED_FIFO is Linux-only"
)


@pytest.fixture(autouse=True)
def _normal_afterwards():
    yield
    realtime.configure(0)


def _fifo_allowed() -> bool:
    """Whether this process may use SCHED_FIFO (root, or an RLIMIT_RTPRIO above 0)."""
    if not hasattr(os, "sched_setscheduler"):
        return False
    result = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=probe)  # a thread of its own: it ends, and its policy with it
    t.start()
    t.join()
    return result[0]


def test_priorities_outside_1_to_98_or_not_integers_are_refused(robot3):
    for bad in (-1, 99, 1.5, True, "10", None):
        with pytest.raises(ValueError, match="real-time priority"):
            realtime.check_priority(bad)
    assert realtime.check_priority(0) == 0 and realtime.check_priority(98) == 98
    with pytest.raises(ConfigError, match="realtime_priority"):
        parse_config({"realtime_priority": 99})
    with pytest.raises(ConfigError, match="realtime_priority"):
        parse_config({"realtime_priority": 2.5})
    assert parse_config({"realtime_priority": 10}).realtime_priority == 10
    assert DaemonConfig().realtime_priority == 0  # off unless asked for
    with pytest.raises(DaemonError, match="real-time priority"):
        Daemon("robots/softrobot3.ucrdf", DaemonConfig(port="loop://"), realtime_priority=120)


def test_priority_0_leaves_scheduling_alone(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a), raising=False)
    realtime.configure(0)
    assert realtime.enter("control loop") == "normal"
    assert calls == [] and realtime.report() == {"control loop": "normal"}


@linux_only
def test_the_calling_thread_takes_fifo_and_what_it_starts_does_not(monkeypatch):
    calls = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    realtime.configure(10)
    assert realtime.enter("link reader") == "SCHED_FIFO 10"
    (pid, policy, param) = calls[0]
    assert pid == 0  # the calling thread, not the process
    assert policy == os.SCHED_FIFO | os.SCHED_RESET_ON_FORK and param.sched_priority == 10


@linux_only
def test_a_refusal_warns_and_the_thread_runs_at_normal_priority(monkeypatch, caplog):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    realtime.configure(10)
    with caplog.at_level(logging.WARNING, logger="ucr.daemon"):
        got = realtime.enter("control loop")
    assert got.startswith("normal (SCHED_FIFO 10 refused: Operation not permitted")
    assert "LimitRTPRIO" in caplog.text and "control loop" in caplog.text


@pytest.mark.skipif(not _fifo_allowed(), reason="SCHED_FIFO not permitted here (not root)")
def test_the_loop_thread_really_runs_fifo_and_threads_it_starts_run_normal():
    realtime.configure(1)
    seen = {}

    def child():
        seen["child"] = os.sched_getscheduler(0)

    def step():
        if "loop" not in seen:
            seen["loop"] = os.sched_getscheduler(0)
            t = threading.Thread(target=child)
            t.start()
            t.join()

    loop = FixedRateLoop(0.01, step)
    loop.start()
    assert wait_for(lambda: "child" in seen, 5.0)
    loop.stop()
    assert seen["loop"] & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
    assert seen["child"] == os.SCHED_OTHER  # SCHED_RESET_ON_FORK: it does not spread
    assert realtime.report()["control loop"] == "SCHED_FIFO 1"


@pytest.mark.skipif(not _fifo_allowed(), reason="SCHED_FIFO not permitted here (not root)")
@pytest.mark.timeout(60)
def test_daemon_runs_its_loop_and_link_reader_fifo_and_reports_it(robot3):
    from tools.emulator import EmulatedChain

    with EmulatedChain(3, config_for=emulated_configs(robot3)) as chain:
        d = Daemon(robot3, DaemonConfig(port=chain.host_port, realtime_priority=1))
        start_daemon(d)
        try:
            assert wait_for(lambda: len(d.loop_stats()["scheduling"]) == 2, 5.0)
            assert d.loop_stats()["scheduling"] == {
                "control loop": "SCHED_FIFO 1",
                "link reader": "SCHED_FIFO 1",
            }
            assert wait_for(lambda: d.loop_stats()["cycles"] > 50, 10.0)
        finally:
            d.stop()
