"""Helpers shared by the host daemon tests (imported as ``daemon_helpers``: pytest puts this
directory on sys.path): the demo robot file, emulated-chain configurations, waiting."""

from __future__ import annotations

import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ROBOT_FILE = REPO / "robots" / "softrobot3.ucrdf"


def emulated_configs(robot):
    """Per-position segment config from the U(C)RDF, with the emulated servo driver."""
    from tools.segment_config import config_for

    names = list(robot.bendables)
    return lambda k: {**config_for(robot, names[k]), "servo_driver": "emulated"}


def wait_for(cond, timeout: float, step: float = 0.01) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return bool(cond())


def start_daemon(daemon, timeout: float = 15.0):
    """Start a daemon, retrying while the emulated segments are still booting."""
    from host.daemon import DaemonError

    end = time.monotonic() + timeout
    while True:
        try:
            return daemon.start()
        except DaemonError:
            if time.monotonic() > end:
                raise
            time.sleep(0.2)


def disturbances(daemon) -> tuple:
    """What the link did to the daemon so far: rebuilds, stalls, rate changes, gaps (a gap in a
    segment's states makes it hold where measured: docs/daemon.md "No motion without a command")."""
    st = daemon.status()
    hwi = daemon.hwi
    return (
        st["topology_changes"],
        st["stalls"],
        st["link_health"]["degradations"],
        id(hwi),
        hwi.gaps if hwi is not None else -1,
    )


class Disturbed(AssertionError):
    """An attempt's goal was aborted by what a starved emulated segment looks like to the
    daemon (it fell behind the path, its states stopped): the safety rules working, not the
    behaviour under test."""


# abort causes (host/controllers/trajectory.py ABORT_CAUSES) a loaded machine can produce by
# starving the segments' MicroPython processes
STARVATION_CAUSES = ("path_tolerance", "link_loss", "segment_fault", "topology_change")


def assert_succeeded(daemon, goal_id) -> dict:
    """The goal's final status, asserting it succeeded; an abort of a starvation cause raises
    :class:`Disturbed` (retried by :func:`retry_if_the_link_was_disturbed`)."""
    st = daemon.trajectory_status(goal_id)
    abort = st.get("abort") or {}
    if st["state"] == "aborted" and abort.get("cause") in STARVATION_CAUSES:
        raise Disturbed(f"goal aborted: {st['reason']}")
    assert st["state"] == "succeeded", st
    return st


def retry_if_the_link_was_disturbed(daemon, attempt, tries: int = 3, before=None):
    """Run ``attempt()`` (which asserts); when it fails while the emulated link was disturbed —
    a loaded machine starves the segment processes, the daemon then holds segments by its safety
    rules and aborts goals (:class:`Disturbed`) — run it again (after ``before()``), at most
    ``tries`` times. An attempt that fails on an undisturbed link fails the test at once."""
    for i in range(tries):
        if before is not None and i:
            before()
        mark = disturbances(daemon)
        try:
            return attempt()
        except AssertionError as e:
            disturbed = isinstance(e, Disturbed) or disturbances(daemon) != mark
            if i == tries - 1 or not disturbed:
                raise


#: the bendables of robots/softrobot3.ucrdf, in chain order
NAMES = ["segment_1", "segment_2", "segment_3"]


def all_back(d, names: list[str] = NAMES) -> bool:
    """The daemon ``d`` runs the whole chain ``names`` again, every segment with a valid state."""
    st = d.status()
    return (
        st["state"] == "connected"
        and st["segments"] == names
        and all(v["valid"] for v in st["joint_states"].values())
    )


def free_url() -> str:
    """A ws:// URL on a loopback port nothing listens on (just freed)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"ws://127.0.0.1:{s.getsockname()[1]}"
