"""The host daemon: one fixed-rate loop driving the segment chain, and the thread-safe facade the
API server (and the demo) use. The daemon only composes its parts:

- :class:`host.loop.FixedRateLoop` (loop supervision): the thread, rate, statistics;
- :class:`host.topology_follower.TopologyFollower`: link, discovery, comparison with the U(C)RDF,
  ``--adopt``, hot-plug rebuilds, port reopen; owns the :class:`host.hwi.HardwareInterface`;
- :class:`host.supervision.Supervisor` (ACROSET SMCS): segment events, silent segments,
  unexpected HOLDs → a reason for the follower to act on;
- :class:`host.motion.Motion`: controller manager, goals, arbitration between sources;
- :class:`host.usable_rate.UsableRate` over :class:`host.link_health.LinkHealth`: a slow link
  lowers the loop rate (:meth:`Daemon._apply_period` says which parts follow);
- :class:`host.publisher.Fanout` / :class:`host.publisher.PublisherThread`: state publication.

One cycle (:meth:`Daemon._step`, in the loop thread): read (STATEs of the last exchange → state
interfaces) → supervise → update (active controllers → command interfaces) → write (one SYNC
down the chain). Safety and topology supervision sit beside the control path: they act before
the controllers, never through them.

Facade methods take the daemon lock (shared with the parts); the loop holds it only for the
controller update, never while waiting on the bus.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import queue
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from host import realtime
from host.api.schema import robot_description
from host.arbitration import Arbitrator
from host.config import DaemonConfig, check_controller_joints, link_baudrate
from host.controller_manager import ControllerManager
from host.errors import DaemonError, GoalNotFound, TopologyError
from host.hwi import ACTIVE, HardwareInterface, robot_state_from
from host.link import ChainLink
from host.link_health import LinkHealth
from host.loop import FixedRateLoop
from host.motion import Motion
from host.publisher import KINDS, Fanout, PublisherThread
from host.supervision import Supervisor, gap_cycles
from host.topology import Comparison, adopted_path
from host.topology_follower import TopologyFollower
from host.usable_rate import UsableRate
from ucrdf.parser import load

log = logging.getLogger("ucr.daemon")

__all__ = ["KINDS", "Daemon", "DaemonError", "GoalNotFound", "PublisherThread", "TopologyError"]

SWITCH_INTERVAL_S = 0.0005  # GIL switch interval while the daemon runs (s)
REPLY_SHARE = 0.8  # share of the loop period one exchange may wait for the states


class Daemon:
    """Drives one chain described by ``robot`` (a :class:`ucrdf.model.Robot` or a file path).

    ``port``/``rate_hz``/``realtime_priority`` override the config; ``adopt`` composes the robot
    from the descriptors when the chain differs and writes it to ``adopt_path`` (default
    ``<file>.adopted.ucrdf``).
    ``link_factory(url, baudrate)`` opens the chain (default :class:`host.link.ChainLink`).
    """

    def __init__(
        self,
        robot: Any,
        config: DaemonConfig | None = None,
        *,
        port: str | None = None,
        rate_hz: float | None = None,
        realtime_priority: int | None = None,
        adopt: bool = False,
        adopt_path: str | Path | None = None,
        link_factory: Callable[[str, int], Any] | None = None,
    ):
        robot = load(robot) if isinstance(robot, str | Path) else robot
        self.file_robot = robot
        self.cfg = config or DaemonConfig()
        check_controller_joints(self.cfg, None if adopt else robot)  # --adopt: the chain's names
        baud = link_baudrate(self.cfg, robot)
        if baud != self.cfg.baudrate:
            self.cfg = dataclasses.replace(self.cfg, baudrate=baud)
        self.port = port or self.cfg.port
        if not self.port:
            raise DaemonError("no chain port given (--port URL or 'port:' in the config)")
        self.rate_hz = float(self.cfg.rate_hz if rate_hz is None else rate_hz)
        if not 1.0 <= self.rate_hz <= 2000.0:
            raise DaemonError(f"loop rate {self.rate_hz} Hz outside 1..2000 Hz")
        prio = self.cfg.realtime_priority if realtime_priority is None else realtime_priority
        try:
            self.realtime_priority = realtime.check_priority(prio)
        except ValueError as exc:
            raise DaemonError(str(exc)) from None
        self.period = 1.0 / self.rate_hz
        self.reply_timeout = min(self.cfg.watchdog.reply_timeout_s, REPLY_SHARE * self.period)
        self._lock = threading.RLock()
        self._t_started = 0.0
        self.fanout = Fanout()
        self._publisher = PublisherThread()
        self.motion = Motion(
            self.cfg, self._lock, self.fanout.emit_event, self._require_running, self.period
        )
        self.topo = TopologyFollower(
            self.cfg,
            robot,
            port=self.port,
            rate_hz=self.rate_hz,
            reply_timeout=self.reply_timeout,
            adopt=adopt,
            adopt_path=Path(adopt_path) if adopt_path else adopted_path(robot.source, robot.name),
            link_factory=link_factory or ChainLink,
            lock=self._lock,
            motion=self.motion,
            fanout=self.fanout,
            submit=self._publisher.submit,
        )
        self.topo.gap_cycles = gap_cycles(self.period, self.cfg.watchdog)
        self.health = LinkHealth(self.period, REPLY_SHARE, min_rate_hz=10.0)
        self.usable_rate = UsableRate(
            self.health, self.rate_hz, self.fanout.emit_event, self._apply_period
        )
        self.supervisor = Supervisor(
            self.cfg.watchdog, self.period, self.fanout.emit_event, self.motion.rehold
        )
        self.loop = FixedRateLoop(self.period, self._step, self._on_loop_error, name="ucr-daemon")

    # -- the parts' state, read-only views (tests, benchmarks and the demo read these) --------
    @property
    def hwi(self) -> HardwareInterface | None:
        return self.topo.hwi

    @property
    def link(self) -> Any:
        return self.topo.link

    @property
    def cm(self) -> ControllerManager | None:
        return self.motion.cm

    @property
    def arb(self) -> Arbitrator:
        return self.motion.arb

    @property
    def robot(self) -> Any:
        return self.topo.robot

    @property
    def full_robot(self) -> Any:
        return self.topo.full_robot

    @property
    def link_state(self) -> str:
        return self.topo.link_state

    @property
    def comparison(self) -> Comparison | None:
        return self.topo.comparison

    @property
    def hotplug_log(self) -> deque[dict]:
        return self.topo.hotplug_log

    @property
    def recent_events(self) -> deque[dict]:
        return self.fanout.recent_events

    @property
    def _subs(self) -> dict[queue.Queue, set[str]]:
        return self.fanout.subs

    def _build(self, descs: list[dict], cmp: Comparison, reason: str) -> None:
        self.topo.build(descs, cmp, reason)

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Daemon:
        """Open the port, discover, compare, build, start the loop. Raises DaemonError."""
        self.topo.stopping = False
        # The loop thread shares the GIL with the link reader (and, in the demo, the emulator):
        # a shorter switch interval bounds how long it waits for it (default 5 ms).
        if sys.getswitchinterval() > SWITCH_INTERVAL_S:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        realtime.configure(self.realtime_priority)  # before the link reader and the loop start
        self.topo.open()
        self.usable_rate.start(self.topo.link)
        self._t_started = time.monotonic()
        realtime.freeze_heap()  # full GC collections stay short (host/realtime.py)
        self._publisher.start()
        self.loop.start()
        log.info(
            "daemon running: %d segment(s) %s at %.0f Hz on %s",
            len(self.hwi.names),
            self.hwi.names,
            self.rate_hz,
            self.port,
        )
        return self

    def stop(self, hold: bool = True) -> None:
        """Stop the loop; abort goals; HOLD every segment (best effort); close the port."""
        self.topo.stopping = True
        self.loop.stop()
        self._publisher.stop()
        self.motion.abort_goals("daemon stopping", "stopped")
        if hold and self.topo.link is not None:
            try:
                self.topo.link.hold()
            except OSError as exc:
                log.warning("HOLD on stop failed: %s", exc)
        self.topo.close_link()
        self.topo.link_state = "stopped"
        log.info("daemon stopped%s", " (segments told to HOLD)" if hold else "")

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- loop --------------------------------------------------------------------------------
    def _step(self) -> float | None:
        """One cycle: read → supervise → update → write; returns compute time (s) or None."""
        topo = self.topo
        if not topo.connected:
            topo.recover()
            return None
        t0 = time.perf_counter()
        now = time.monotonic()
        hwi = topo.hwi
        try:
            hwi.read()
            events = topo.take_events() + topo.link.events()
        except OSError as exc:
            topo.link_lost(exc)
            return None
        if not hwi.exchange_probed and hwi.exchanges:
            self.usable_rate.observe(hwi, topo.link, now)
        if hwi.exchange_probed:
            topo.note_probe(bool(hwi.extra_states), now)
        state = robot_state_from(hwi, now)
        sup = self.supervisor
        # a rejoin (only what lies beyond the tip) waits for the hysteresis (docs/daemon.md
        # "Rejoin by itself"); meanwhile the chain is controlled as it is and probed again
        ready = functools.partial(topo.rejoin_ready, now)  # (probed) -> bool
        reason = sup.check(hwi, state, events, topo.descriptors, rejoin_ready=ready)
        if reason is not None:
            stalls = topo.stalls
            missing = [i for i, m in enumerate(hwi.missing) if m > 0]
            topo.hotplug(reason, now, verify=sup.silent, position=sup.position, rejoin=sup.rejoin)
            if topo.hwi is not hwi:
                self.usable_rate.reset()
            elif topo.stalls > stalls and missing:
                self.usable_rate.stall(hwi, topo.link, missing[0], now)
            return None
        self.motion.update(hwi, state, now)
        compute = time.perf_counter() - t0
        hwi.probe_extra = topo.probe_due(now)
        try:
            hwi.write()
        except OSError as exc:
            topo.link_lost(exc)
        except ValueError as exc:  # a setpoint the codec refuses: never send it
            log.error("setpoints refused by the codec: %s", exc)
        return compute

    def _apply_period(self, period: float) -> None:
        """Run the loop at ``period`` s (the usable rate): reply time, gap and silence limits
        follow. At the nominal rate the configured reply timeout applies again."""
        nominal = abs(period - self.period) < 1e-9
        timeout = self.reply_timeout if nominal else REPLY_SHARE * period
        self.loop.set_period(period, keep_counts=True)  # timing windows restart at the new period
        self.supervisor.period = self.motion.period = period
        self.topo.reply_timeout = timeout
        self.topo.gap_cycles = gap_cycles(period, self.cfg.watchdog)
        hwi = self.topo.hwi
        if hwi is not None:
            hwi.reply_timeout = timeout
            hwi.gap_cycles = self.topo.gap_cycles

    def _on_loop_error(self, exc: BaseException) -> None:
        log.exception("control cycle failed: %s", exc, exc_info=exc)
        self.fanout.emit_event("cycle_error", message=f"{type(exc).__name__}: {exc}")

    def _require_running(self) -> None:
        """Raise DaemonError unless controllers run on an active chain (caller holds the lock)."""
        if self.motion.cm is None:
            raise DaemonError("daemon is not running")
        topo = self.topo
        if topo.link_state != "connected" or topo.hwi is None or topo.hwi.state != ACTIVE:
            raise DaemonError(f"chain not available ({topo.link_state}: {topo.link_error})")

    # -- facade ------------------------------------------------------------------------------
    def usable_rate_hz(self) -> float:
        """The rate the loop runs at now: the configured one unless a slow link lowered it."""
        period = self.loop.period
        return self.rate_hz if abs(period - self.period) < 1e-12 else round(1.0 / period, 2)

    def status(self) -> dict[str, Any]:
        """Overall state: link, robot, segments, HWI lifecycle, active controllers, goals."""
        with self._lock:
            topo, hwi, st = self.topo, self.topo.hwi, self.motion.state
            motion = self.motion.summary()
            return {
                "state": topo.link_state,
                "error": topo.link_error,
                "port": self.port,
                "robot": topo.robot.name,
                # the rate the loop runs at: the usable one (lowered while a link is slow,
                # docs/daemon.md "Degrade, don't stall"), as in loop_stats(); the configured one
                # is nominal_rate_hz
                "rate_hz": self.usable_rate_hz(),
                "nominal_rate_hz": self.rate_hz,
                "segments": list(hwi.names) if hwi else [],
                "hwi": hwi.state if hwi else "unconfigured",
                "active_controllers": motion["active_controllers"],
                "running_goals": motion["running_goals"],
                "manual_control": motion["manual_control"],
                "topology_changes": topo.topology_changes,
                "stalls": topo.stalls,
                "rejoins": topo.rejoin_counts(),
                "link_health": self.health.snapshot(),
                "uptime_s": time.monotonic() - self._t_started if self._t_started else 0.0,
                "joint_states": {
                    n: {"kappa": st.kappa[i], "phi": st.phi[i], "valid": st.valid[i]}
                    for i, n in enumerate(st.names)
                },
                # segments in FAULT (held until cleared: clear_fault / `ucr clear-fault`)
                "faults": {n: dict(f) for n, f in self.supervisor.faults.items()},
            }

    def clear_fault(self, segment: str | None = None) -> dict[str, Any]:
        """Send CLEAR_FAULT to ``segment`` (identity checked by its uid) or to every segment.

        A cleared segment goes from FAULT to HOLD; the daemon then resumes it like any held
        segment. Returns ``{"sent_to": [names], "faults": {...}}`` (faults as known now; the
        next STATE shows whether the segment left FAULT).
        """
        with self._lock:
            topo = self.topo
            if topo.link is None or topo.link_state != "connected" or topo.hwi is None:
                raise DaemonError(f"chain not available ({topo.link_state}: {topo.link_error})")
            names = list(topo.hwi.names)
            if segment is not None and segment not in names:
                raise LookupError(
                    f"unknown segment {segment!r} (segments: {', '.join(names) or 'none'})"
                )
            link = topo.link
            position = None if segment is None else names.index(segment)
            uid = None if position is None else topo.descriptors[position].get("uid")
            faults = {n: dict(f) for n, f in self.supervisor.faults.items()}
        link.clear_fault(position, uid)
        sent = names if segment is None else [segment]
        self.fanout.emit_event(
            "fault_clear_sent",
            message=f"CLEAR_FAULT sent to {', '.join(sent)}",
            segments=sent,
        )
        return {"sent_to": sent, "faults": faults}

    def topology(self) -> dict[str, Any]:
        """The chain as discovered, what is controlled, differences from the U(C)RDF, cuts; the
        sha256 and size of the U(C)RDF it drives (its text: :meth:`robot_description`)."""
        with self._lock:
            out, robot = self.topo.describe(), self.topo.full_robot
        out["description"] = robot_description(robot, text=False)
        return out

    def robot_description(self) -> dict[str, Any]:
        """The U(C)RDF it drives as the API's ``robot.description`` (host/api/schema.py)."""
        return robot_description(self.topo.full_robot)

    def loop_stats(self) -> dict[str, Any]:
        """Loop timing (µs: period, jitter, compute without I/O wait; overruns), link counters,
        hot-plug timings."""
        out = self.loop.stats.snapshot(self.loop.period)  # the usable rate (link health)
        out["nominal_rate_hz"] = self.rate_hz
        out["scheduling"] = realtime.report()  # {thread: "SCHED_FIFO 10" | "normal ..."}
        with self._lock:
            out["hotplug"] = list(self.topo.hotplug_log)
            out["subscriber_drops"] = self.fanout.dropped
            out["publisher"] = self._publisher.stats()
            link = self.topo.link
        try:
            out["link"] = link.stats if link is not None else {}
        except OSError:
            out["link"] = {}
        return out

    def controllers(self) -> list[dict[str, Any]]:
        """Every configured controller: type, state, claimed interfaces, goal."""
        return self.motion.controllers()

    def switch_controllers(
        self, start: list[str] | None = None, stop: list[str] | None = None
    ) -> dict[str, Any]:
        """Activate ``start`` and deactivate ``stop`` atomically (SwitchError on conflicts)."""
        return self.motion.switch_controllers(start or [], stop or [])

    def send_trajectory(
        self, points: list[dict], controller: str | None = None, source: Any = None
    ) -> str:
        """Start a trajectory on a cJTC (the active one by default); returns the goal id.
        ``source``: who sent it (as for :meth:`ffc_input`), its status's ``from``.

        The goal is parsed and retimed outside the daemon lock (a long one takes a while and the
        loop must go on cycling meanwhile): under the lock only the controller's desired motion
        is read, and the goal is installed only if that controller is still the active one and
        its motion did not change meanwhile (else built once more, then rejected).
        Raises ControllerError (a ValueError) with the reason when it is rejected.
        """
        return self.motion.send_trajectory(points, controller, source)

    def trajectory_status(self, goal_id: str) -> dict[str, Any]:
        """Progress and result of a goal (GoalNotFound if unknown)."""
        return self.motion.trajectory_status(goal_id)

    def cancel_trajectory(self, goal_id: str) -> dict[str, Any]:
        """Cancel a running goal (decelerates to rest); returns its status + ``canceled``."""
        return self.motion.cancel_trajectory(goal_id)

    def ffc_input(self, rates: dict[str, Any], source: Any = None) -> dict[str, Any]:
        """Stream cFFC stick input {bendable: [x, y]} (deflections in [-1, 1]).

        A deflected stick takes over from a running trajectory (arbitration); zero input to an
        inactive cFFC changes nothing (the reply says so). ``source``: who sent it (the API gives
        its connection's ``peer``, ``client`` and ``for``), the cFFC's ``input_from``."""
        return self.motion.ffc_input(rates, source)

    def hand_back(self, manual: str | None = None) -> dict[str, Any]:
        """End a manual takeover: stop the cFFC, restart the controllers it preempted."""
        return self.motion.hand_back(manual)

    def subscribe(
        self, kinds: list[str] | tuple[str, ...] | str, maxsize: int = 1000, into: Any = None
    ) -> queue.Queue:
        """A queue receiving published messages of these kinds (joint_states, transforms,
        event(s), topology). Full queues drop their oldest message. ``into``: a never-blocking
        queue-like object to fill instead (the API bridge's feed; host.publisher.Fanout)."""
        return self.fanout.subscribe(kinds, maxsize, into)

    def unsubscribe(self, q: queue.Queue) -> None:
        self.fanout.unsubscribe(q)
