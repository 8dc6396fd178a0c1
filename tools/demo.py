"""``ucr demo``: the host daemon driving an emulated 3-segment robot (real firmware on the
MicroPython VM): discovery, a demo trajectory with live state, then segment 3 unplugged and plugged
back during a motion. Lives in tools/ because it needs the emulator; ``./run.sh demo`` runs it.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

from host.cli import api_start_error, print_error, setup_logging, start_api
from host.client_common import format_missing, port_arg

REPO = Path(__file__).resolve().parents[1]
DEMO_ROBOT = REPO / "robots" / "softrobot3.ucrdf"


def register(subparsers: Any) -> None:
    d = subparsers.add_parser(
        "demo",
        help="the daemon driving an emulated 3-segment robot (no hardware needed)",
        description="Starts 3 emulated segments (real firmware on the MicroPython VM), the daemon "
        "and its API, runs a demo trajectory with live state, then unplugs and replugs segment 3.",
    )
    d.add_argument(
        "--forever",
        action="store_true",
        help="keep running (API up; a state line at most once a second, when it changed) "
        "until Ctrl-C",
    )
    d.add_argument("--no-api", action="store_true", help="do not start the network API")
    d.add_argument(
        "--api-port",
        type=port_arg,
        default=0,
        metavar="N",
        help="API port, 0..65535 (default 0: a free one); a port in use fails the demo",
    )
    d.add_argument("--no-view", action="store_true", help="do not start `ucr view`")
    d.add_argument(
        "--view-port",
        type=port_arg,
        default=0,
        metavar="N",
        help="view page port (default 0: a free one); a given port that fails fails the demo",
    )
    d.add_argument("--quiet-log", action="store_true", help="only warnings from the daemon log")
    d.set_defaults(func=cmd_demo)


# -- demo -------------------------------------------------------------------------------------


#: s: the demo prints a state line at most this often, and only when it changed (an idle robot
#: under --forever prints none); events and topology changes print at once
STATE_LINE_PERIOD_S = 1.0

_OUT = threading.Lock()


def say(line: str) -> None:
    """One whole line on stdout: the printer thread and the script never interleave mid-line."""
    with _OUT:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


class DemoFailed(Exception):
    """A part the user asked for did not start: one line, exit 1."""


def _start_view(api_url: str, port: int) -> Any:
    """`ucr view` on the demo's API in its own process; None (with the reason) if it cannot.
    A view on a port the user chose (``port`` not 0) that does not start fails the demo
    (:class:`DemoFailed`); the view's extra not installed never does."""
    import importlib.util  # noqa: PLC0415

    try:
        from view.launch import start_view_process  # noqa: PLC0415 - optional part

        view = start_view_process(api_url, port)
    except (ModuleNotFoundError, RuntimeError, OSError) as exc:
        if port and importlib.util.find_spec("viser") is not None:
            raise DemoFailed(
                f"demo: view not started on port {port}: {exc}; choose another with "
                "--view-port N (0: any free port) or run without it (--no-view)"
            ) from None
        say(f"view not started: {exc}")
        return None
    say(f"view on {view.url} (open it in a browser)")
    return view


def _fmt_state(js: dict | None, tf: dict | None) -> str:
    """The robot in one line: per segment kappa (1/m) and phi (degrees), the tip in mm."""
    if js is None:
        return "(no state yet)"
    parts = []
    for name, k, p, ok in zip(js["names"], js["kappa"], js["phi"], js["valid"], strict=True):
        short = name.replace("segment_", "s")
        parts.append(f"{short} κ={k:4.2f} 1/m φ={math.degrees(p):6.1f}°" if ok else f"{short} --")
    line = " | ".join(parts)
    if tf is not None:
        x, y, z = (v * 1000 for v in tf["tip"]["xyz"])
        line += f" | tip ({x:6.1f}, {y:6.1f}, {z:6.1f}) mm"
    return line


class StateThrottle:
    """When the demo prints a state line: at most once per ``period`` s, and only when the line
    differs from the last one printed (``ucr demo --forever`` printed 5 lines a second, the
    same line while the robot held)."""

    def __init__(self, period: float = STATE_LINE_PERIOD_S) -> None:
        self.period = period
        self.last_line: str | None = None
        self.last_t = -math.inf

    def due(self, line: str, now: float) -> bool:
        """True if ``line`` is to be printed at ``now`` (s, monotonic); then it is the last."""
        if line == self.last_line or now - self.last_t < self.period:
            return False
        self.last_line, self.last_t = line, now
        return True

    def final(self, line: str) -> bool:
        """True if ``line``, the state as the printer stops, differs from the last printed
        (a motion's end pose is shown, however soon after the last line it came)."""
        if line == self.last_line:
            return False
        self.last_line = line
        return True


class _Printer(threading.Thread):
    """Prints a compact state line (:class:`StateThrottle`) and every event/topology message."""

    def __init__(self, daemon: Any, t0: float):
        super().__init__(name="ucr-demo-printer", daemon=True)
        self.q = daemon.subscribe(["joint_states", "transforms", "event", "topology"])
        self.daemon_ = daemon
        self.t0 = t0
        self.stop = threading.Event()
        self.js: dict | None = None
        self.tf: dict | None = None
        self.topologies: list[dict] = []
        self._last_event: dict[tuple, float] = {}
        self.throttle = StateThrottle()

    def _quiet(self, msg: dict) -> bool:
        """Repeated segment events (e.g. LIMIT_CLAMPED on every step) print once per 2 s."""
        if msg.get("source") != "segment":
            return False
        key = (msg["event"], msg.get("position"))
        now = time.monotonic()
        if now - self._last_event.get(key, -1e9) < 2.0:
            return True
        self._last_event[key] = now
        return False

    def _handle(self, msg: dict) -> None:
        kind = msg["kind"]
        if kind == "joint_states":
            self.js = msg
        elif kind == "transforms":
            self.tf = msg
        elif kind == "event" and self._quiet(msg):
            pass
        elif kind == "event":
            text = msg.get("message", "")
            say(f"[{time.monotonic() - self.t0:5.1f}s] event {msg['event']}: {text}")
        elif kind == "topology":
            self.topologies.append(msg)
            missing = "".join(f"; {ln.strip()}" for ln in format_missing(msg))
            say(
                f"[{time.monotonic() - self.t0:5.1f}s] topology: "
                f"{len(msg['controlled'])} segment(s): {', '.join(msg['controlled'])}" + missing
            )

    def run(self) -> None:
        import queue  # noqa: PLC0415

        while not self.stop.is_set():
            try:
                self._handle(self.q.get(timeout=0.05))
            except queue.Empty:
                pass
            state = _fmt_state(self.js, self.tf)
            now = time.monotonic()
            if self.throttle.due(state, now):
                say(f"[{now - self.t0:5.1f}s] {state}")
        while True:  # what came meanwhile, then the last state if not yet shown (the end pose)
            try:
                self._handle(self.q.get_nowait())
            except queue.Empty:
                break
        state = _fmt_state(self.js, self.tf)
        if self.throttle.final(state):
            say(f"[{time.monotonic() - self.t0:5.1f}s] {state}")
        self.daemon_.unsubscribe(self.q)


def demo_trajectory(names: list[str], kappa: float) -> list[dict]:
    """Bend each segment in turn, sweep phi around a full circle, return to straight."""
    pts: list[dict] = []
    t = 0.0
    for i, n in enumerate(names):
        t += 1.2
        pts.append({"time_from_start": t, "segments": {n: {"kappa": kappa, "phi": 2.0944 * i}}})
    steps = 12
    for k in range(1, steps + 1):
        t += 0.35
        phi = math.atan2(math.sin(2 * math.pi * k / steps), math.cos(2 * math.pi * k / steps))
        pts.append(
            {
                "time_from_start": t,
                "segments": {n: {"kappa": kappa * 0.7, "phi": phi} for n in names},
            }
        )
    t += 1.5
    pts.append({"time_from_start": t, "segments": {n: {"kappa": 0.0, "phi": 0.0} for n in names}})
    return pts


def _wait(cond: Any, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def cmd_demo(args: argparse.Namespace) -> int:
    from host.config import DaemonConfig  # noqa: PLC0415
    from host.daemon import Daemon, DaemonError  # noqa: PLC0415
    from tools.emulator import EmulatedChain  # noqa: PLC0415 - keep `ucr --help` fast
    from tools.segment_config import config_for  # noqa: PLC0415
    from ucrdf.parser import load  # noqa: PLC0415

    setup_logging("WARNING" if args.quiet_log else "INFO")
    if not DEMO_ROBOT.is_file():
        return print_error(
            f"demo: its robot {DEMO_ROBOT} is not here: the demo runs from a source checkout "
            "(./run.sh demo in the repository); an installed wheel does not carry robots/"
        )
    robot = load(DEMO_ROBOT)
    names = list(robot.bendables)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t0 = time.monotonic()
    say(
        f"ucr demo: starting {len(names)} emulated segments (real firmware on the MicroPython "
        f"VM) for {DEMO_ROBOT.name}"
    )
    with EmulatedChain(len(names), config_for=lambda k: config_for(robot, names[k])) as chain:
        cfg = DaemonConfig(port=chain.host_port)
        daemon = Daemon(robot, cfg)
        api = view = None
        started = False
        try:
            # The API first, as `ucr daemon` does: a port in use fails the demo at once, before
            # the segments boot (until the chain runs, requests answer "daemon is not running").
            if not args.no_api:
                try:
                    api = start_api(
                        daemon,
                        "127.0.0.1",
                        args.api_port,
                        None,
                        log_level="warning" if args.quiet_log else "info",
                    )
                except Exception as exc:  # noqa: BLE001 - bind errors are the user's to fix
                    why = api_start_error(exc, "127.0.0.1", args.api_port, "--api-port N")
                    raise DemoFailed(f"demo: {why}") from None
            deadline = time.monotonic() + 15.0
            while True:  # the segments need a moment to boot
                try:
                    daemon.start()
                    started = True
                    break
                except DaemonError as exc:
                    if time.monotonic() > deadline:
                        raise DemoFailed(f"demo: {exc}") from None
                    time.sleep(0.3)
            if api is not None:
                say(f"API on {api.url} (try `ucr status --url {api.url}`)")
            if api is not None and not args.no_view:
                view = _start_view(api.url, args.view_port)
            topo = daemon.topology()
            say(
                f"discovered {len(topo['segments'])} segment(s): "
                + ", ".join(
                    f"{s['bendable']} (uid {s['uid']}, fw {s['fw_version']})"
                    for s in topo["segments"]
                )
            )
            printer = _Printer(daemon, t0)
            printer.start()
            try:
                rc = _run_script(daemon, chain, names, printer, stop, args.forever)
                if args.forever:
                    say("== running until Ctrl-C")
                    try:
                        while not stop.wait(0.5):
                            pass
                    except KeyboardInterrupt:
                        pass
            finally:
                printer.stop.set()
                printer.join(1.0)
            stats = daemon.loop_stats()
            say(
                f"loop: {stats['cycles']} cycles at {stats['rate_hz']:.0f} Hz, compute mean "
                f"{stats['compute_us']['mean']:.0f} µs (p99 {stats['compute_us']['p99']:.0f}), "
                f"jitter p99 {stats['jitter_us']['p99']:.0f} µs, overruns {stats['overruns']} "
                "(this process also runs the emulator; see benchmarks/bench_host.py)"
            )
            for h in stats["hotplug"]:
                say(f"hot-plug: {h['reason']} -> {h['segments']} in {h['rebuild_s'] * 1000:.0f} ms")
        except DemoFailed as exc:
            return print_error(str(exc))
        finally:
            if view is not None:
                view.stop()
            if api is not None:
                api.stop()
            if started:
                daemon.stop(hold=True)
    say(f"ucr demo: done in {time.monotonic() - t0:.1f} s")
    return rc


class ClientTookOver(Exception):
    """A client's command replaced the demo's motion: the script yields, the daemon serves."""


def _run_script(
    daemon: Any,
    chain: Any,
    names: list[str],
    printer: _Printer,
    stop: threading.Event,
    forever: bool,
) -> int:
    """The demo script; clients may command the robot from the moment the API is up. A client
    command that replaces the demo's motion ends the script (not the daemon); with ``--forever``
    a script failure is reported and the daemon keeps serving too."""
    from host.controllers.base import ControllerError  # noqa: PLC0415
    from host.errors import DaemonError  # noqa: PLC0415

    try:
        return _demo_script(daemon, chain, names, printer, stop)
    except ClientTookOver as exc:
        say(f"== a client took over ({exc}): demo script stopped, serving clients")
        return 0
    except (ControllerError, DaemonError) as exc:
        if not forever:
            raise
        say(f"== demo script stopped: {exc}; serving clients")
        return 0


def _ours(daemon: Any, gid: str) -> dict:
    """Status of the demo's goal; ClientTookOver when a client's command replaced it."""
    st = daemon.trajectory_status(gid)
    cause = (st.get("abort") or {}).get("cause")
    if st["state"] == "aborted" and cause == "replaced":
        raise ClientTookOver(st["reason"])
    return st


def _send(daemon: Any, points: list[dict]) -> str:
    """Start a demo goal; a manual takeover by a client refuses it: ClientTookOver."""
    from host.controllers.base import ControllerError  # noqa: PLC0415

    try:
        return daemon.send_trajectory(points)
    except ControllerError as exc:
        if "manual control" in str(exc) or "not active" in str(exc):
            raise ClientTookOver(str(exc)) from None
        raise


def _demo_script(
    daemon: Any,
    chain: Any,
    names: list[str],
    printer: _Printer,
    stop: threading.Event,
) -> int:
    kappa = 0.6 * min(daemon.hwi.limits[n].kappa_max for n in names)
    say("== demo trajectory: bend each segment in turn, a circle of phi, back to straight")
    for _ in range(3):  # a goal aborted by a gap in a segment's states (a loaded host) reruns
        gid = _send(daemon, demo_trajectory(names, kappa))
        ok = _wait(lambda g=gid: _ours(daemon, g)["done"] or stop.is_set(), 40.0)
        st = _ours(daemon, gid)
        if (st.get("abort") or {}).get("cause") != "link_loss" or stop.is_set():
            break
        say(f"== trajectory aborted ({st['reason']}); once more")
    say(
        f"== trajectory {st['state']}{': ' + st['reason'] if st['reason'] else ''} "
        f"(duration {st['duration']:.1f} s, max path error {st['max_path_error']:.3f} 1/m)"
    )
    if not ok or st["state"] != "succeeded":
        return 1
    if stop.is_set():
        return 0
    say("== hot-plug: unplugging segment 3 during a motion")
    _send(
        daemon,
        [{"time_from_start": 3.0, "segments": {n: {"kappa": kappa, "phi": 1.0} for n in names}}],
    )
    time.sleep(1.0)
    t_unplug = time.monotonic()
    chain.unplug(len(names) - 1)
    if not _wait(lambda: len(daemon.status()["segments"]) == len(names) - 1, 5.0):
        say("== segment 3 removal was not detected")
        return 1
    say(
        f"== rebuilt as {len(names) - 1} segments {time.monotonic() - t_unplug:.2f} s after "
        "the unplug; plugging it back"
    )
    time.sleep(1.0)
    t_plug = time.monotonic()
    chain.plug(len(names) - 1)
    if not _wait(lambda: len(daemon.status()["segments"]) == len(names), 5.0):
        say("== segment 3 was not found again")
        return 1
    say(
        f"== {len(names)} segments again {time.monotonic() - t_plug:.2f} s after the plug; "
        "back to straight"
    )
    gid = _send(
        daemon,
        [{"time_from_start": 2.0, "segments": {n: {"kappa": 0.0, "phi": 0.0} for n in names}}],
    )
    _wait(lambda: _ours(daemon, gid)["done"], 10.0)
    return 0
