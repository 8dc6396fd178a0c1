"""The host daemon: one fixed-rate loop driving the segment chain, and the thread-safe facade the
API server (and the CLI demo) use.

Loop (own thread, ``host.loop.FixedRateLoop``): read (STATEs of the last exchange → state
interfaces) → supervise (events, silent segments, unexpected HOLD) → update (active controllers
→ command interfaces) → write (one SYNC down the chain). Safety and topology supervision (ACROSET
SMCS) sit beside the control path: they act before the controllers, never through them.

Topology changes (DOWNSTREAM_UP/DOWN events, a segment silent for ``missed_cycles`` cycles, a
segment that rebooted): abort every running goal, HOLD the chain, rediscover, compare with the
U(C)RDF, cut the robot to the matching segments, rebuild HWI and controllers (they hold the
measured position) and resume — without restarting. A vanished port is reopened with back-off.

Facade methods (``status``, ``topology``, ``loop_stats``, ``controllers``, ``switch_controllers``,
``send_trajectory``, ``trajectory_status``, ``cancel_trajectory``, ``ffc_input``, ``subscribe``,
``unsubscribe``, plus ``hand_back``) take the daemon lock; the loop holds it only for the
controller update, never while waiting on the bus.
"""

from __future__ import annotations

import logging
import math
import queue
import sys
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from host.arbitration import Arbitrator
from host.config import DaemonConfig, bendable_limits
from host.controller_manager import ControllerManager, SwitchError
from host.controllers.base import ControllerContext, ControllerError, RobotState
from host.controllers.jtc import StaleGoalError
from host.hwi import ACTIVE, HardwareInterface
from host.link import ChainLink, exchange_floor_s
from host.loop import FixedRateLoop
from host.topology import Comparison, adopt, adopted_path, chain_bendables, compare, truncate
from ucrdf.parser import load

log = logging.getLogger("ucr.daemon")

KINDS = ("joint_states", "transforms", "event", "topology")
SWITCH_INTERVAL_S = 0.0005  # GIL switch interval while the daemon runs (s)
_DESCRIPTOR_BYTES = 200  # a DESCRIPTOR frame on the wire, bytes (upper estimate)
_TOPOLOGY_EVENTS = {"DOWNSTREAM_UP", "DOWNSTREAM_DOWN", "BOOT"}


class DaemonError(RuntimeError):
    """The daemon cannot start or go on (message says why, one line)."""


class TopologyError(DaemonError):
    """The discovered chain does not match the description (and ``--adopt`` was not given)."""

    def __init__(self, comparison: Comparison, message: str):
        self.comparison = comparison
        super().__init__(message)


class GoalNotFound(LookupError):
    """No goal with this id."""


class PublisherThread:
    """Runs work handed over by the control cycle (e.g. cRSP's FK) in its own thread, so that work
    never lengthens a cycle. Bounded: when it falls behind, new work is dropped and counted."""

    def __init__(self, maxsize: int = 8):
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._thread: threading.Thread | None = None
        self.done = 0
        self.dropped = 0
        self.busy_s = 0.0

    def start(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._run, name="ucr-publisher", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        if self._thread is not None:
            try:
                self._q.put(None, timeout=timeout)
            except queue.Full:
                pass
            self._thread.join(timeout)
            self._thread = None

    def submit(self, fn: Callable[[], None]) -> None:
        if self._thread is None:
            fn()  # not started (e.g. timed by a benchmark): run inline
            return
        try:
            self._q.put_nowait(fn)
        except queue.Full:
            self.dropped += 1

    def stats(self) -> dict[str, Any]:
        mean = self.busy_s / self.done * 1e6 if self.done else 0.0
        return {"done": self.done, "dropped": self.dropped, "mean_us": mean}

    def _run(self) -> None:
        while True:
            fn = self._q.get()
            if fn is None:
                return
            t0 = time.perf_counter()
            try:
                fn()
            except Exception:  # noqa: BLE001 - a failing publisher must not stop the others
                log.exception("publisher task failed")
            self.busy_s += time.perf_counter() - t0
            self.done += 1


class Daemon:
    """Drives one chain described by ``robot`` (a :class:`ucrdf.model.Robot` or a file path).

    ``port``/``rate_hz`` override the config; ``adopt`` composes the robot from the descriptors
    when the chain differs and writes it to ``adopt_path`` (default ``<file>.adopted.ucrdf``).
    ``link_factory(url, baudrate)`` opens the chain (default :class:`host.link.ChainLink`).
    """

    def __init__(
        self,
        robot: Any,
        config: DaemonConfig | None = None,
        *,
        port: str | None = None,
        rate_hz: float | None = None,
        adopt: bool = False,
        adopt_path: str | Path | None = None,
        link_factory: Callable[[str, int], Any] | None = None,
    ):
        if isinstance(robot, str | Path):
            robot = load(robot)
        self.file_robot = robot
        self.full_robot = robot  # the description hot-plug compares against (adopted one if so)
        self.cfg = config or DaemonConfig()
        self.port = port or self.cfg.port
        if not self.port:
            raise DaemonError("no chain port given (--port URL or 'port:' in the config)")
        self.rate_hz = float(rate_hz or self.cfg.rate_hz)
        if not 1.0 <= self.rate_hz <= 2000.0:
            raise DaemonError(f"loop rate {self.rate_hz} Hz outside 1..2000 Hz")
        self.period = 1.0 / self.rate_hz
        self.adopt = adopt
        self.adopt_path = Path(adopt_path) if adopt_path else adopted_path(robot.source, robot.name)
        if link_factory is None:
            link_factory = ChainLink
        self._link_factory = link_factory
        wd = self.cfg.watchdog
        self.reply_timeout = min(wd.reply_timeout_s, 0.8 * self.period)
        self._lock = threading.RLock()
        self._subs: dict[queue.Queue, set[str]] = {}
        self._dropped = 0
        self.link: Any = None
        self.link_state = "stopped"
        self.link_error = ""
        self.robot = robot
        self.hwi: HardwareInterface | None = None
        self.cm: ControllerManager | None = None
        self.arb = Arbitrator()
        # goal id -> (Goal, controller name); kept across rebuilds, which recreate controllers
        self._goals: OrderedDict[str, tuple[Any, str]] = OrderedDict()
        self.descriptors: list[dict] = []
        self.comparison: Comparison | None = None
        self.cut: dict[str, Any] | None = None
        self.topology_changes = 0
        self.stalls = 0
        self._silent = False
        self.hotplug_log: deque[dict] = deque(maxlen=20)
        self.recent_events: deque[dict] = deque(maxlen=50)
        self._state = RobotState.zeros([])
        self._t_last = time.monotonic()
        self._t_started = 0.0
        self._reconnect_at = 0.0
        self._backoff = wd.reconnect_min_s
        self._stopping = False
        self.loop = FixedRateLoop(self.period, self._step, self._on_loop_error, name="ucr-daemon")
        self._publisher = PublisherThread()

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Daemon:
        """Open the port, discover, compare, build, start the loop. Raises DaemonError."""
        self._stopping = False
        # The loop thread shares the GIL with the link reader (and, in the demo, the emulator):
        # a shorter switch interval bounds how long it waits for it (default 5 ms).
        if sys.getswitchinterval() > SWITCH_INTERVAL_S:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            self.link = self._link_factory(self.port, self.cfg.baudrate)
        except OSError as exc:
            raise DaemonError(str(exc)) from None
        try:
            descs = self._discover()
        except OSError as exc:
            self._close_link()
            raise DaemonError(f"discovery on {self.port} failed: {exc}") from None
        if not descs:
            self._close_link()
            raise DaemonError(f"no segment answered DISCOVER on {self.port}")
        cmp = compare(self.full_robot, descs)
        if not cmp.ok:
            if not self.adopt:
                self._close_link()
                src = self.file_robot.source or self.file_robot.name
                raise TopologyError(
                    cmp,
                    f"chain differs from {src}: {cmp.text()} (start with --adopt to use the "
                    "chain as found)",
                )
            self._adopt(descs, cmp)
            cmp = compare(self.full_robot, descs)
        try:
            self._build(descs, cmp, "startup")
        except (OSError, ValueError) as exc:  # link failure, bad interface limits in the file
            self._close_link()
            raise DaemonError(f"cannot start on {self.port}: {exc}") from None
        except DaemonError:
            self._close_link()
            raise
        self.link_state = "connected"
        self._t_started = time.monotonic()
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
        self._stopping = True
        self.loop.stop()
        self._publisher.stop()
        with self._lock:
            self._abort_goals("daemon stopping")
        if hold and self.link is not None:
            try:
                self.link.hold()
            except OSError as exc:
                log.warning("HOLD on stop failed: %s", exc)
        self._close_link()
        self.link_state = "stopped"
        log.info("daemon stopped%s", " (segments told to HOLD)" if hold else "")

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- building ----------------------------------------------------------------------------
    def _discover(self, quick: bool = False) -> list[dict]:
        """DISCOVER. ``quick`` (after a hot-plug) bounds the wait by what the line needs: the new
        tip may still believe its lost neighbour is present for 150 ms, so the link would
        otherwise wait the whole configured timeout for an answer that will never come."""
        timeout = self.cfg.watchdog.discover_timeout_s
        if quick:
            n = max(len(self.descriptors), 1) + 1
            line_s = 2 * n * _DESCRIPTOR_BYTES * 10 / self.cfg.baudrate
            timeout = min(timeout, max(0.08, line_s + 0.04))
        return self.link.discover(timeout=timeout)

    def _adopt(self, descs: list[dict], cmp: Comparison) -> None:
        try:
            robot = adopt(descs, self.file_robot.name, self.adopt_path)
        except Exception as exc:  # noqa: BLE001 - composition failure is a user-facing error
            raise DaemonError(f"--adopt: cannot compose a robot from the chain: {exc}") from None
        log.warning(
            "chain differs from the description (%s); adopted the chain as found and wrote %s",
            cmp.text(),
            self.adopt_path,
        )
        self.full_robot = robot
        self._emit_event(
            "adopted",
            message=f"robot composed from the chain written to {self.adopt_path}",
            path=str(self.adopt_path),
            differences=[d.as_dict() for d in cmp.differences],
        )

    def _build(self, descs: list[dict], cmp: Comparison, reason: str) -> None:
        """New HWI and controllers for the first ``cmp.matched`` segments of ``descs``."""
        keep = cmp.matched
        robot = truncate(self.full_robot, keep)
        order = chain_bendables(robot)
        lim_all = bendable_limits(robot)
        limits = {n: lim_all[n] for n in order}
        # the last STATE of each bendable from the HWI being replaced: a segment that misses the
        # first heartbeat is then held where it was last seen, not at zero
        known = {}
        if self.hwi is not None:
            known = {
                n: st for n, st in zip(self.hwi.names, self.hwi.last_states, strict=True) if st
            }
        hwi = HardwareInterface(limits, self.link, self.reply_timeout, known=known)
        hwi.configure()
        hwi.activate()
        state = self._robot_state_from(hwi, time.monotonic())
        ctx = ControllerContext(limits, robot, self._publish, self._publisher.submit)
        with self._lock:
            self.robot, self.hwi, self.descriptors, self.comparison = robot, hwi, descs, cmp
            self._state = state
            if self.cm is None:
                cm = ControllerManager(self.cfg.controllers, ctx)
                try:
                    cm.switch(self.cfg.active, [], state, reason)
                except SwitchError as exc:
                    raise DaemonError(f"{self.cfg.source}: active: {exc}") from None
                self.cm = cm  # only once it runs: a retried start() builds it afresh
            else:
                self.cm.rebuild(ctx, state, reason)
                self.arb.prune(self.cm)  # a manual takeover outlives a rebuild
            expected = chain_bendables(self.full_robot)
            if keep < len(expected):
                lost = expected[keep:]
                self.cut = {
                    "after_position": keep - 1,
                    "after": expected[keep - 1] if keep else None,
                    "lost": lost,
                }
            else:
                self.cut = None
        self._warn_if_rate_exceeds_the_chain(len(order))
        self._publish(
            {"kind": "topology", "t": time.monotonic(), "reason": reason, **self._topology_locked()}
        )

    def _warn_if_rate_exceeds_the_chain(self, n: int) -> None:
        """Say so when a real UART chain of ``n`` segments cannot answer within a loop period."""
        floor = exchange_floor_s(n, self.cfg.baudrate)
        if floor <= self.reply_timeout:
            return
        max_rate = math.floor(0.8 / floor)
        if floor > self.cfg.watchdog.reply_timeout_s:
            advice = (
                f"raise watchdog.reply_timeout_s above {floor:.3f} s and use rate_hz <= "
                f"{max_rate}, or a higher baudrate"
            )
        else:
            advice = f"use rate_hz <= {max_rate} or a higher baudrate"
        log.warning(
            "%d segment(s) at %d baud need at least %.1f ms per exchange on a real UART chain "
            "(store-and-forward), more than the %.1f ms a %.0f Hz loop waits for their states: "
            "states would arrive late or be missed; %s",
            n,
            self.cfg.baudrate,
            floor * 1e3,
            self.reply_timeout * 1e3,
            self.rate_hz,
            advice,
        )

    # -- loop --------------------------------------------------------------------------------
    def _step(self) -> float | None:
        if self.link is None or self.hwi is None or self.link_state != "connected":
            self._recover()
            return None
        t0 = time.perf_counter()
        now = time.monotonic()
        hwi = self.hwi
        try:
            hwi.read()
            events = self.link.events()
        except OSError as exc:
            self._link_lost(exc)
            return None
        state = self._robot_state_from(hwi, now)
        reason = self._supervise(hwi, state, events)
        if reason is not None:
            self._hotplug(reason, now, verify=self._silent)
            return None
        with self._lock:
            dt = now - self._t_last if self._t_last else self.period
            self._t_last = now
            self._state = state
            if hwi.first_measured:
                for c in self.cm.controllers.values():
                    if c.active:
                        c.adopt_measured(hwi.first_measured, state)
            cmds = self.cm.update(state, dt)
            for name, (kx, ky) in cmds.items():
                if name in hwi.limits:
                    hwi.set_curvature(name, kx, ky)
        compute = time.perf_counter() - t0
        try:
            hwi.write()
        except OSError as exc:
            self._link_lost(exc)
        except ValueError as exc:  # a setpoint the codec refuses: never send it
            log.error("setpoints refused by the codec: %s", exc)
        return compute

    def _supervise(
        self, hwi: HardwareInterface, state: RobotState, events: list[dict]
    ) -> str | None:
        """SMCS: return a reason when the topology changed; handle unexpected HOLDs."""
        reason = None
        self._silent = False
        for ev in events:
            name = ev.get("name", "")
            self._emit_event(
                name.lower(),
                message=self._describe_event(ev),
                position=ev.get("position"),
                detail=ev.get("detail"),
                segment_t_ms=ev.get("t_ms"),
                source="segment",
            )
            if reason is None and self._is_news(name, ev.get("position")):
                reason = f"{name} from position {ev.get('position')}"
        if reason is None:
            wd = self.cfg.watchdog
            limit = max(wd.missed_cycles, math.ceil(wd.silence_s / self.period))
            silent = [i for i, m in enumerate(hwi.missing) if m >= limit]
            if silent:
                names = ", ".join(f"{hwi.names[i]} (position {i})" for i in silent)
                reason = f"no STATE from {names} for {limit} cycles"
                self._silent = True
        if reason is None and hwi.raw_states and self.descriptors:
            tip = hwi.raw_states[-1]
            known_tip = self.descriptors[len(hwi.names) - 1]
            if (
                tip is not None
                and "DOWNSTREAM" in tip["status"]
                and known_tip.get("downstream_present") is False
            ):
                reason = f"a segment answers downstream of {hwi.names[-1]}"
        if reason is None:
            held = [
                hwi.names[i]
                for i, st in enumerate(hwi.raw_states)
                if st is not None and "HOLD" in st["status"]
            ]
            if held and not hwi.resume_pending:
                msg = f"segment(s) {', '.join(held)} holding (watchdog or HOLD)"
                with self._lock:
                    self._abort_goals(msg)
                    self.cm.rebuild(self.cm.ctx, state, msg)  # controllers hold the measured state
                hwi.resume_pending = True
                self._emit_event(
                    "segments_held", message=msg + "; controllers re-held, resuming", segments=held
                )
        return reason

    def _describe_event(self, ev: dict) -> str:
        """One readable line for a segment EVENT (which segment, what happened)."""
        pos, name, detail = ev.get("position"), ev.get("name", ""), ev.get("detail")
        who = f"position {pos}"
        if isinstance(pos, int) and pos < len(self.descriptors):
            who = f"{self.descriptors[pos].get('name') or '?'} (position {pos})"
        if name == "LIMIT_CLAMPED" and isinstance(detail, int):
            bits = [b for i, b in enumerate(("kappa", "rate", "servo range")) if detail >> i & 1]
            what = f"setpoint clamped by the segment ({', '.join(bits) or detail})"
        else:
            what = {
                "DOWNSTREAM_UP": "a segment appeared on its downstream port",
                "DOWNSTREAM_DOWN": "its downstream neighbour went silent",
                "WATCHDOG_TRIPPED": f"watchdog tripped (detail {detail}): holding",
                "WATCHDOG_CLEARED": "watchdog cleared",
                "SERVO_FAULT": f"servo {detail} reports a fault",
                "BOOT": "booted",
            }.get(name, f"{name} (detail {detail})")
        return f"{who}: {what}"

    def _is_news(self, event: str, position: Any) -> bool:
        """Whether a segment event contradicts the topology we know (duplicates are not)."""
        if event not in _TOPOLOGY_EVENTS:
            return False
        if event == "BOOT" or not isinstance(position, int):
            return True
        last = len(self.descriptors) - 1
        if event == "DOWNSTREAM_DOWN":
            return position < last  # we believed a segment was behind it
        return position >= last  # DOWNSTREAM_UP: we believed it was the tip

    def _hotplug(self, reason: str, t_detect: float, verify: bool = False) -> None:
        """Hold, rediscover, abort, rebuild — in the loop thread, without restarting.

        ``verify`` (silent segments, no event): if discovery finds the very same chain, the
        silence was a stall (late replies, a loaded host): resume without aborting anything.
        """
        aborted: list[str] = []
        if not verify:
            log.warning("topology change: %s", reason)
            with self._lock:
                aborted = self._abort_goals(f"topology changed: {reason}")
        try:
            self.link.hold()
            descs = self._discover(quick=True)
        except OSError as exc:
            self._link_lost(exc)
            return
        if verify and self.hwi is not None:
            same = [d.get("uid") for d in descs] == [d.get("uid") for d in self.descriptors]
            if same and descs:
                self.hwi.missing = [0] * len(self.hwi.names)
                self.hwi.resume_pending = True
                self.stalls += 1
                self._emit_event(
                    "link_stall",
                    message=f"{reason}, but the chain is unchanged: resumed",
                    reason=reason,
                    stall_s=round(time.monotonic() - t_detect, 4),
                )
                log.warning("stall: %s; chain unchanged, resumed", reason)
                return
            log.warning("topology change: %s", reason)
            with self._lock:
                aborted = self._abort_goals(f"topology changed: {reason}")
        self.topology_changes += 1
        if not descs:
            self._lost_chain(f"{reason}; no segment answers DISCOVER")
            return
        cmp = compare(self.full_robot, descs)
        if not cmp.ok and self.adopt and cmp.matched < len(descs):
            try:
                self._adopt(descs, cmp)
                cmp = compare(self.full_robot, descs)
            except DaemonError as exc:
                log.error("%s", exc)
        if cmp.matched == 0:
            self._lost_chain(f"{reason}; {cmp.text()}")
            return
        t_disc = time.monotonic()
        try:
            self._build(descs, cmp, reason)
        except OSError as exc:
            self._link_lost(exc)
            return
        t_ready = time.monotonic()
        entry = {
            "t": t_detect,
            "reason": reason,
            "segments": list(self.hwi.names),
            "aborted_goals": aborted,
            "discover_s": t_disc - t_detect,
            "rebuild_s": t_ready - t_detect,
            "cut": self.cut,
            "differences": [d.as_dict() for d in cmp.differences],
        }
        self.hotplug_log.append(entry)
        msg = f"now {len(self.hwi.names)} segment(s): {', '.join(self.hwi.names)}"
        if self.cut:
            msg += (
                f"; chain cut after {self.cut['after']} (position "
                f"{self.cut['after_position']}): {', '.join(self.cut['lost'])} unreachable"
            )
        extra = [d.message for d in cmp.differences if d.blocking and d.kind != "count"]
        if extra:
            msg += "; " + "; ".join(extra)
        self._emit_event(
            "topology_changed",
            message=f"{reason}: {msg}",
            reason=reason,
            segments=list(self.hwi.names),
            cut=self.cut,
            aborted_goals=aborted,
            rebuild_s=round(t_ready - t_detect, 4),
        )
        log.warning("rebuilt in %.0f ms: %s", (t_ready - t_detect) * 1e3, msg)

    def _lost_chain(self, why: str) -> None:
        """No usable segment: keep the port, retry discovery with back-off."""
        log.error("chain lost: %s", why)
        self.link_state = "waiting"
        self.link_error = why
        self._reconnect_at = time.monotonic() + self._backoff
        with self._lock:
            self.hwi = None
        self._emit_event("chain_lost", message=why)

    def _link_lost(self, exc: BaseException) -> None:
        log.error("link lost: %s", exc)
        with self._lock:
            self._abort_goals(f"link lost: {exc}")
            self.hwi = None
        self._close_link()
        self.link_state = "reconnecting"
        self.link_error = str(exc)
        self._reconnect_at = time.monotonic() + self._backoff
        self._emit_event("link_lost", message=str(exc))

    def _recover(self) -> None:
        """Called by the loop while disconnected: reopen/rediscover when the back-off allows."""
        if self._stopping:
            return
        now = time.monotonic()
        if now < self._reconnect_at:
            return
        wd = self.cfg.watchdog
        try:
            if self.link is None:
                self.link = self._link_factory(self.port, self.cfg.baudrate)
            descs = self._discover()
        except OSError as exc:
            if self.link is not None:
                self._close_link()  # reopen from scratch next time
            self.link_error = str(exc)
            self._backoff = min(self._backoff * 2, wd.reconnect_max_s)
            self._reconnect_at = now + self._backoff
            return
        cmp = compare(self.full_robot, descs) if descs else None
        if not descs or cmp.matched == 0:
            self.link_error = "no matching segment answers" if descs else "no segment answers"
            self._backoff = min(self._backoff * 2, wd.reconnect_max_s)
            self._reconnect_at = now + self._backoff
            return
        try:
            self._build(descs, cmp, "reconnected")
        except OSError as exc:
            self._link_lost(exc)
            return
        self.link_state = "connected"
        self.link_error = ""
        self._backoff = wd.reconnect_min_s
        self._emit_event(
            "link_restored",
            message=f"{len(self.hwi.names)} segment(s) back on {self.port}",
            segments=list(self.hwi.names),
        )

    def _close_link(self) -> None:
        link, self.link = self.link, None
        if link is not None:
            try:
                link.close()
            except OSError:
                pass

    def _on_loop_error(self, exc: BaseException) -> None:
        log.exception("control cycle failed: %s", exc, exc_info=exc)
        self._emit_event("cycle_error", message=f"{type(exc).__name__}: {exc}")

    @staticmethod
    def _robot_state_from(hwi: HardwareInterface, t: float) -> RobotState:
        n = len(hwi.names)
        st = RobotState.zeros(hwi.names, t)
        for i in range(n):
            s = hwi.raw_states[i]
            fresh = s is not None
            if s is None:
                s = hwi.last_states[i]  # missed this cycle: the last known values, not fresh
                if s is None:
                    continue  # never measured: zeros, known=False (the HWI sends hold entries)
            kappa, phi = s["kappa"] or 0.0, s["phi"] or 0.0
            kx = s["kx"] if s["kx"] is not None else kappa * math.cos(phi)
            ky = s["ky"] if s["ky"] is not None else kappa * math.sin(phi)
            st.kx[i], st.ky[i], st.kappa[i], st.phi[i] = kx, ky, kappa, phi
            st.valid[i], st.known[i] = fresh, True
            st.t_ms[i] = s.get("t_ms")
        return st

    # -- publishing --------------------------------------------------------------------------
    def _publish(self, msg: dict) -> None:
        kind = msg.get("kind")
        with self._lock:
            subs = [q for q, kinds in self._subs.items() if kind in kinds]
        for q in subs:
            try:
                q.put_nowait(msg)
            except queue.Full:
                try:  # drop the oldest: a slow subscriber never blocks the loop
                    q.get_nowait()
                    q.put_nowait(msg)
                except (queue.Empty, queue.Full):
                    pass
                self._dropped += 1

    def _emit_event(self, event: str, message: str = "", **fields: Any) -> None:
        msg = {"kind": "event", "t": time.monotonic(), "event": event, "message": message, **fields}
        self.recent_events.append(msg)
        self._publish(msg)

    def _abort_goals(self, reason: str) -> list[str]:
        out = []
        if self.cm is None:
            return out
        for c in self.cm.controllers.values():
            abort = getattr(c, "abort_active", None)
            if c.active and abort is not None:
                gid = abort(reason)
                if gid:
                    out.append(gid)
        return out

    # -- facade ------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """Overall state: link, robot, segments, HWI lifecycle, active controllers, goals."""
        with self._lock:
            hwi = self.hwi
            active = self.cm.active_names() if self.cm else []
            goals = []
            if self.cm:
                for c in self.cm.controllers.values():
                    g = getattr(c, "current_goal", None)
                    if g is not None:
                        goals.append(g.id)
            st = self._state
            return {
                "state": self.link_state,
                "error": self.link_error,
                "port": self.port,
                "robot": self.robot.name,
                "rate_hz": self.rate_hz,
                "segments": list(hwi.names) if hwi else [],
                "hwi": hwi.state if hwi else "unconfigured",
                "active_controllers": active,
                "running_goals": goals,
                "manual_control": sorted(self.arb.takeovers),
                "topology_changes": self.topology_changes,
                "stalls": self.stalls,
                "uptime_s": time.monotonic() - self._t_started if self._t_started else 0.0,
                "joint_states": {
                    n: {"kappa": st.kappa[i], "phi": st.phi[i], "valid": st.valid[i]}
                    for i, n in enumerate(st.names)
                },
            }

    def _topology_locked(self) -> dict[str, Any]:
        cmp = self.comparison
        controlled = set(self.hwi.names) if self.hwi else set()
        names = chain_bendables(self.full_robot)
        segs = []
        for d in self.descriptors:
            pos = d.get("position", len(segs))
            segs.append(
                {
                    "position": pos,
                    "bendable": names[pos] if pos < len(names) else None,
                    "name": d.get("name"),
                    "uid": d.get("uid"),
                    "model": d.get("model"),
                    "length": d.get("length"),
                    "kappa_max": d.get("kappa_max"),
                    "kappa_rate_max": d.get("kappa_rate_max"),
                    "fw_version": d.get("fw_version"),
                    "watchdog_ms": d.get("watchdog_ms"),
                    "controlled": pos < len(names) and names[pos] in controlled,
                }
            )
        return {
            "robot": self.robot.name,
            "file": self.full_robot.source or None,
            "expected": names,
            "segments": segs,
            "controlled": list(self.hwi.names) if self.hwi else [],
            "matched": cmp.matched if cmp else 0,
            "ok": bool(cmp and cmp.ok),
            "differences": [d.as_dict() for d in cmp.differences] if cmp else [],
            "cut": self.cut,
        }

    def topology(self) -> dict[str, Any]:
        """The chain as discovered, what is controlled, differences from the U(C)RDF, cuts."""
        with self._lock:
            return self._topology_locked()

    def loop_stats(self) -> dict[str, Any]:
        """Loop timing (µs: period, jitter, compute without I/O wait; overruns), link counters,
        hot-plug timings."""
        out = self.loop.stats.snapshot(self.period)
        with self._lock:
            out["hotplug"] = list(self.hotplug_log)
            out["subscriber_drops"] = self._dropped
            out["publisher"] = self._publisher.stats()
            link = self.link
        try:
            out["link"] = link.stats if link is not None else {}
        except OSError:
            out["link"] = {}
        return out

    def controllers(self) -> list[dict[str, Any]]:
        """Every configured controller: type, state, claimed interfaces, goal."""
        with self._lock:
            return self.cm.describe() if self.cm else []

    def switch_controllers(
        self, start: list[str] | None = None, stop: list[str] | None = None
    ) -> dict[str, Any]:
        """Activate ``start`` and deactivate ``stop`` atomically (SwitchError on conflicts)."""
        with self._lock:
            self._require_running()
            res = self.cm.switch(start or [], stop or [], self._state)
            self.arb.note_switch(res["started"], res["stopped"])
        self._emit_event(
            "controllers_switched",
            message=f"started {res['started']}, stopped {res['stopped']}",
            **res,
        )
        return res

    def send_trajectory(self, points: list[dict], controller: str | None = None) -> str:
        """Start a trajectory on a cJTC (the active one by default); returns the goal id.

        The goal is parsed and retimed outside the daemon lock (a long one takes a while and the
        loop must go on cycling meanwhile): under the lock only the controller's desired motion
        is read, and the goal is installed only if that controller is still the active one and
        its motion did not change meanwhile (else built once more, then rejected).
        Raises ControllerError (a ValueError) with the reason when it is rejected.
        """
        lead = 0.05 + 2e-4 * (len(points) if isinstance(points, list | tuple) else 0)
        for attempt in range(2):
            with self._lock:
                self._require_running()
                ctrl = self._jtc(controller)
                if not ctrl.active:
                    manual = self.arb.blocking_manual(self.cm, ctrl.name)
                    if manual:
                        raise ControllerError(
                            f"manual control by {manual!r} is active; hand back first "
                            f"(switch_controllers(start=[{ctrl.name!r}], stop=[{manual!r}]))"
                        )
                    raise ControllerError(f"controller {ctrl.name!r} is not active")
                t_build = time.monotonic()
                start = ctrl.goal_snapshot(t_build + lead)
            goal, traj = ctrl.build_goal(points, start)  # the slow part, lock not held
            built_s = time.monotonic() - t_build
            with self._lock:
                self._require_running()
                current = self.cm.controllers.get(ctrl.name)
                if current is not ctrl or not ctrl.active:
                    why = f"controller {ctrl.name!r} was switched or rebuilt while it was built"
                else:
                    try:
                        ctrl.install_goal(goal, traj, start, time.monotonic())
                    except StaleGoalError as exc:
                        why = str(exc)
                    else:
                        self._goals[goal.id] = (goal, ctrl.name)
                        while len(self._goals) > 500:
                            self._goals.popitem(last=False)
                        return goal.id
            log.info("trajectory goal built again (attempt %d): %s", attempt + 1, why)
            lead = 2.0 * built_s + 0.05
        raise ControllerError(f"trajectory not started: {why}; send it again")

    def _jtc(self, controller: str | None) -> Any:
        if controller is not None:
            c = self.cm.get(controller)
            if not hasattr(c, "send_goal"):
                raise ControllerError(
                    f"controller {controller!r} ({c.type_name}) does not take trajectories"
                )
            return c
        cands = [c for c in self.cm.controllers.values() if hasattr(c, "send_goal")]
        if not cands:
            raise ControllerError("no trajectory controller (type jtc) is configured")
        active = [c for c in cands if c.active]
        return (active or cands)[0]

    def trajectory_status(self, goal_id: str) -> dict[str, Any]:
        """Progress and result of a goal (GoalNotFound if unknown)."""
        with self._lock:
            return self._goal(goal_id)[0].status()

    def cancel_trajectory(self, goal_id: str) -> dict[str, Any]:
        """Cancel a running goal (decelerates to rest); returns its status + ``canceled``."""
        with self._lock:
            goal, name = self._goal(goal_id)
            ctrl = self.cm.controllers.get(name)
            canceled = False
            if ctrl is not None and ctrl.has_goal(goal.id):
                canceled = ctrl.cancel(goal.id, time.monotonic())
            return {**goal.status(), "canceled": canceled}

    def _goal(self, goal_id: str) -> tuple[Any, str]:
        entry = self._goals.get(str(goal_id))
        if entry is None:
            raise GoalNotFound(f"unknown goal id {goal_id!r}")
        return entry

    def ffc_input(self, rates: dict[str, Any]) -> dict[str, Any]:
        """Stream cFFC stick input {bendable: [x, y]} (deflections in [-1, 1]).

        A deflected stick takes over from a running trajectory (arbitration); zero input to an
        inactive cFFC changes nothing (the reply says so)."""
        with self._lock:
            self._require_running()
            ffcs = self.cm.of_type("ffc")
            if not ffcs:
                raise ControllerError("no cFFC (type ffc) is configured")
            ctrl = next((c for c in ffcs if c.active), ffcs[0])
            parsed = ctrl.validate_input(rates)
            deflected = ctrl.has_deflection(parsed, ctrl.deadzone)
            takeover = self.arb.manual_input(self.cm, ctrl.name, deflected, self._state)
            if not ctrl.active:
                return {
                    "accepted": False,
                    "controller": ctrl.name,
                    "takeover": None,
                    "reason": f"{ctrl.name!r} is inactive and the input is in the deadzone",
                }
            ctrl.set_input(parsed, time.monotonic())
        if takeover:
            self._emit_event(
                "manual_takeover",
                message=f"{ctrl.name!r} took over from {takeover['preempted']}",
                **{k: v for k, v in takeover.items() if k not in ("t", "event")},
            )
        return {"accepted": True, "controller": ctrl.name, "takeover": takeover}

    def hand_back(self, manual: str | None = None) -> dict[str, Any]:
        """End a manual takeover: stop the cFFC, restart the controllers it preempted."""
        with self._lock:
            self._require_running()
            if manual is None:
                if not self.arb.takeovers:
                    raise ControllerError("no manual takeover to hand back")
                manual = next(iter(self.arb.takeovers))
            rec = self.arb.hand_back(self.cm, manual, self._state)
        self._emit_event(
            "hand_back",
            message=f"{manual!r} handed back; restarted {rec['restarted']}",
            **{k: v for k, v in rec.items() if k not in ("t", "event")},
        )
        return rec

    def subscribe(
        self, kinds: list[str] | tuple[str, ...] | str, maxsize: int = 1000
    ) -> queue.Queue:
        """A queue receiving published messages of these kinds (joint_states, transforms,
        event(s), topology). Full queues drop their oldest message."""
        if isinstance(kinds, str):
            kinds = [kinds]
        want = {"event" if k == "events" else k for k in kinds}
        bad = want - set(KINDS)
        if bad or not want:
            raise ValueError(
                f"unknown subscription kind(s) {sorted(bad)} (known: {', '.join(KINDS)})"
            )
        q: queue.Queue = queue.Queue(maxsize=maxsize)
        with self._lock:
            self._subs[q] = want
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            self._subs.pop(q, None)

    def _require_running(self) -> None:
        if self.cm is None:
            raise DaemonError("daemon is not running")
        if self.link_state != "connected" or self.hwi is None or self.hwi.state != ACTIVE:
            raise DaemonError(f"chain not available ({self.link_state}: {self.link_error})")
