"""Topology follower: the chain as it is now — the link, discovery, comparison with the U(C)RDF,
``--adopt``, the hardware interface built for the matching segments, and what happens when the
chain changes (hot-plug) or the port vanishes (reopen with back-off).

A change (reported by :class:`host.supervision.Supervisor`): HOLD the segments it concerns,
rediscover (HEARTBEATs between the tries keep the other segments' watchdogs fed), compare, abort
the goals that move a segment it concerns, cut the robot to the matching segments, build a new
HWI and have :class:`host.motion.Motion` rebuild the controllers (they hold the measured
position; the other goals are carried over) — in the loop thread, without restarting. A segment
that answers beyond the tip rejoins with hysteresis: one that keeps dropping out must answer
steadily first (bounded, docs/daemon.md "Rejoin by itself"). Talks to the rest through:
``motion.build`` / ``motion.abort_goals``, ``fanout.publish`` / ``fanout.emit_event``,
``submit`` (publisher thread).
Why a change aborts goals (segment, cause) is decided in :mod:`host.motion_abort`.

One piece: it is one state machine over one link (connected, waiting, reconnecting, stopped),
and discovery, rebuild and reopen each move it between those states; split apart, the
transitions and the back-off they share would be scattered over several modules.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from host.chain_report import describe_chain, rate_warning, rebuild_message
from host.config import DaemonConfig
from host.controllers.base import ControllerContext
from host.errors import DaemonError, TopologyError
from host.hwi import HardwareInterface, robot_state_from
from host.limits import bendable_limits
from host.motion import Motion
from host.motion_abort import hotplug_abort
from host.positions import label
from host.publisher import Fanout
from host.topology import (
    Comparison,
    adopt_capped,
    chain_bendables,
    compare,
    envelope_from,
    truncate,
)

log = logging.getLogger("ucr.daemon")

_DESCRIPTOR_BYTES = 200  # a DESCRIPTOR frame on the wire, bytes (upper estimate)
PROBE_INTERVAL_S = 0.1  # while the chain is shorter than its description: one probe per 0.1 s
REJOIN_RETRY_S = 0.2  # longest wait between discoveries while the port is fine but no segment
# answers (the port's own reopen back-off goes up to watchdog.reconnect_max_s)
_DISCOVER_TRIES = 3  # an incomplete or unanswered discovery is retried this often at once
# Rejoin hysteresis (docs/daemon.md "Rejoin by itself"): a segment lost (or a rejoin that found
# nothing new) more than once within FLAP_MEMORY_S must answer every probe beyond the tip for a
# while before it is taken back: 0.05 s after its second flap, doubling per flap up to
# REJOIN_SPAN_MAX_S (probes then go out every cycle). A first loss rejoins at the first answer.
FLAP_MEMORY_S = 10.0
REJOIN_SPAN_MIN_S = 0.05
REJOIN_SPAN_MAX_S = 0.2
FEED_SHARE = 0.6  # a rediscovery's tries are bounded to this share of the shortest watchdog
# After a silence that no segment answers, the goals' abort waits this long for the chain to
# come back: a segment that restarted reports BOOT (cause topology_change, as when its BOOT
# comes first), else the cause is link_loss.
BOOT_WAIT_S = 1.0


class TopologyFollower:
    """Keeps ``link``, ``hwi`` and ``robot`` matching the chain; ``link_state`` is one of
    stopped, connected, waiting (no usable segment), reconnecting (port lost)."""

    def __init__(
        self,
        cfg: DaemonConfig,
        file_robot: Any,
        *,
        port: str,
        rate_hz: float,
        reply_timeout: float,
        adopt: bool,
        adopt_path: Path,
        link_factory: Callable[[str, int], Any],
        lock: threading.RLock,
        motion: Motion,
        fanout: Fanout,
        submit: Callable[[Callable[[], None]], None],
    ):
        self.cfg = cfg
        self.file_robot = file_robot
        self.full_robot = file_robot  # the description hot-plug compares against (adopted if so)
        self.robot = file_robot
        self.port = port
        self.rate_hz = rate_hz
        self.reply_timeout = reply_timeout
        self.adopt = adopt
        self.adopt_path = adopt_path
        self._link_factory = link_factory
        self._lock = lock
        self._motion = motion
        self._fanout = fanout
        self._submit = submit
        self.link: Any = None
        self.link_state = "stopped"
        self.link_error = ""
        self.hwi: HardwareInterface | None = None
        self.descriptors: list[dict] = []
        self.comparison: Comparison | None = None
        self.cut: dict[str, Any] | None = None
        self.topology_changes = 0
        self.stalls = 0
        self.hotplug_log: deque[dict] = deque(maxlen=20)
        self._reconnect_at = 0.0
        self._backoff = cfg.watchdog.reconnect_min_s
        self.stopping = False
        self.gap_cycles = 2  # set by the daemon from its (usable) period
        self.rejoins = 0  # segments probed back beyond a cut
        self._next_probe = 0.0
        self._streak = 0  # consecutive probes beyond the tip that were answered
        self._streak_t0 = 0.0
        self._flaps = 0  # losses / failed rejoins within FLAP_MEMORY_S of each other
        self._flap_at = -FLAP_MEMORY_S
        self.rejoins_deferred = 0  # cycles a probe answered but the rejoin waited (hysteresis)
        self.rejoin_failures = 0  # rejoins whose rediscovery found no new segment (nothing done)
        # ((text, cause, segment), 0-based position, deadline) of goals whose abort waits for
        # a BOOT; events read meanwhile, handed to supervision by take_events()
        self._deferred_abort: tuple[tuple[str, str, str | None], int, float] | None = None
        self._events: list[dict] = []
        self._refused: str | None = None  # the last segment_refused message (reported once)

    def rejoin_counts(self) -> dict[str, int]:
        """Segments probed back beyond the tip: taken back (``done``), cycles whose answer was
        not steady enough yet (``deferred``, the hysteresis), rediscoveries that found none."""
        return {
            "done": self.rejoins,
            "deferred": self.rejoins_deferred,
            "failed": self.rejoin_failures,
        }

    @property
    def connected(self) -> bool:
        return self.link is not None and self.hwi is not None and self.link_state == "connected"

    # -- startup -----------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, discover, compare (adopt if allowed), build. Raises DaemonError."""
        try:
            self.link = self._link_factory(self.port, self.cfg.baudrate)
        except OSError as exc:
            raise DaemonError(str(exc)) from None
        try:
            descs = self.discover()
        except OSError as exc:
            self.close_link()
            raise DaemonError(f"discovery on {self.port} failed: {exc}") from None
        if not descs:
            self.close_link()
            raise DaemonError(f"no segment answered DISCOVER on {self.port}")
        cmp = compare(self.full_robot, descs)
        if not cmp.ok:
            if not self.adopt:
                self.close_link()
                src = self.file_robot.source or self.file_robot.name
                raise TopologyError(
                    cmp,
                    f"chain differs from {src}: {cmp.text()} (start with --adopt to use the "
                    "chain as found)",
                )
            self._adopt(descs, cmp)
            cmp = compare(self.full_robot, descs)
        try:
            self.build(descs, cmp, "startup")
        except (OSError, ValueError) as exc:  # link failure, bad interface limits in the file
            self.close_link()
            raise DaemonError(f"cannot start on {self.port}: {exc}") from None
        except DaemonError:
            self.close_link()
            raise
        self.link_state = "connected"

    def discover(
        self, quick: bool = False, *, running: bool = False, cap: float | None = None
    ) -> list[dict]:
        """DISCOVER. ``quick`` (after a hot-plug) bounds the wait by what the line needs: the new
        tip may still believe its lost neighbour is present for 150 ms, so the link would
        otherwise wait the whole configured timeout for an answer that will never come.

        ``running`` (a hot-plug or reconnect, not the start): a segment speaking another
        protocol version ends the chain there, the segments before it stay under control, and
        an event ``segment_refused`` says to reflash it (once per segment and version); at the
        start the daemon refuses to run (docs/protocol.md section 10)."""
        timeout = self.cfg.watchdog.discover_timeout_s
        if quick:
            timeout = min(timeout, self.reply_window())
        if cap is not None:
            timeout = min(timeout, cap)
        # a line measured slower than its baud rate: as long as the descriptors need there (the
        # link never waits longer than asked; on such a line a try may outlast a watchdog)
        need = getattr(self.link, "discover_need_s", None)
        timeout = max(timeout, need() if need is not None else 0.0)
        if not running:
            return self.link.discover(timeout=timeout)
        descs = self.link.discover(timeout=timeout, upto_other_version=True)
        refusal = getattr(self.link, "version_refusal", None)
        text = None if refusal is None else str(refusal)
        if text is not None and text != self._refused:
            log.error("%s; the chain before it stays under control", text)
            self._fanout.emit_event(
                "segment_refused",
                message=text,
                position=refusal.position + 1,  # 1-based, like every position a user sees
            )
        self._refused = text
        return descs

    def reply_window(self) -> float:
        """What one quick discovery must wait for with the line and the link's current reply
        timing: the descriptors on the line, and at a lowered (usable) rate, where the link is
        slow, two reply times."""
        n = max(len(self.descriptors), 1) + 1
        line_s = 2 * n * _DESCRIPTOR_BYTES * 10 / self.cfg.baudrate
        return max(0.08, line_s + 0.04, 2.0 * self.reply_timeout)

    def port_ok(self) -> bool:
        """The port works (a lost reply or a silent chain leave it working)."""
        return self.link is not None and bool(getattr(self.link, "port_ok", True))

    def discover_retrying(self, quick: bool = False) -> list[dict]:
        """:meth:`discover` of a running daemon, retried at once when a reply was lost on a
        working port (a glitch or corrupted bytes) — and, after a hot-plug (``quick``), when no
        segment answered at all on a working port (a restarting neighbour, a burst of
        corruption): the last try then waits the full ``discover_timeout_s``. Raises OSError
        when the port failed or every try was incomplete; [] when every try went unanswered.

        While a chain runs (a hot-plug), every try is bounded by :meth:`feed_cap` and a
        HEARTBEAT goes out between tries (:meth:`feed`): the segments that still answer keep
        their watchdogs fed during the whole rediscovery. The last try after a hot-plug is not
        bounded: it waits the full ``discover_timeout_s`` (longer than a watchdog, the segments
        that answer may hold themselves meanwhile; the rebuilt HWI resumes them)."""
        descs: list[dict] = []
        cap = self.feed_cap()
        for attempt in range(_DISCOVER_TRIES):
            full = quick and attempt and attempt == _DISCOVER_TRIES - 1  # the last try: in full
            last = attempt == _DISCOVER_TRIES - 1
            if attempt:
                self.feed()
            try:
                descs = self.discover(
                    quick=quick and not full, running=True, cap=None if full else cap
                )
            except OSError:
                if last or not self.port_ok():
                    raise
                continue
            if descs or not quick or not self.port_ok():
                return descs
        return descs

    def feed_cap(self) -> float | None:
        """How long one discovery may wait while a chain runs: ``FEED_SHARE`` of the shortest
        watchdog of the segments known, less one reply time — never less than the link's
        current reply timing needs (:meth:`reply_window`; on a link slowed that far a try may
        outlast a watchdog) (None: no chain runs)."""
        if self.hwi is None:
            return None
        wds = [d.get("watchdog_ms") for d in self.descriptors]
        wds = [w for w in wds if isinstance(w, int | float) and w > 0]
        shortest = min(wds) / 1000.0 if wds else 0.2
        return max(self.reply_window(), FEED_SHARE * shortest - self.reply_timeout)

    def feed(self) -> None:
        """One HEARTBEAT between discovery tries (feeds the watchdogs; STATEs are not used). A
        failed port is left to the discovery that follows."""
        try:
            self.link.heartbeat(timeout=self.reply_timeout)
        except OSError:
            pass

    # -- rejoin hysteresis -------------------------------------------------------------------
    def note_probe(self, answered: bool, now: float) -> None:
        """The outcome of a probe beyond the tip (called by the loop after its read)."""
        if not answered:
            self._streak = 0
            return
        if self._streak == 0:
            self._streak_t0 = now
        self._streak += 1

    def rejoin_span(self, now: float) -> float:
        """How long the probes beyond the tip must all be answered before a rejoin."""
        if now - self._flap_at > FLAP_MEMORY_S:
            self._flaps = 0
        if self._flaps <= 1:
            return 0.0
        return min(REJOIN_SPAN_MIN_S * 2 ** (self._flaps - 2), REJOIN_SPAN_MAX_S)

    def rejoin_ready(self, now: float, probed: bool = True) -> bool:
        """A segment beyond the tip answered long enough to be taken back (else the loop keeps
        controlling the chain it has and probes again next cycle). ``probed``: the evidence is
        an answered probe; else a report (DOWNSTREAM_UP from the tip, a BOOT beyond it), taken
        at once unless the segment flapped: then only steady probe answers count."""
        span = self.rejoin_span(now)
        if span == 0.0:
            return True
        ready = probed and self._streak > 0 and now - self._streak_t0 >= span - 1e-9
        if not ready:
            self.rejoins_deferred += 1
        return ready

    def _note_flap(self, now: float) -> None:
        if now - self._flap_at > FLAP_MEMORY_S:
            self._flaps = 0
        self._flaps += 1
        self._flap_at = now
        self._streak = 0

    def probe_due(self, now: float) -> int:
        """Positions beyond the tip the next SYNC should wait for: while the chain is shorter
        than its description, once per ``PROBE_INTERVAL_S`` (a cut that healed by itself, a
        segment that missed the rediscovery), else 0."""
        hwi = self.hwi
        if hwi is None:
            return 0
        missing = len(self.full_robot.bendables) - len(hwi.names)  # (a checked tree holds all)
        if missing <= 0 or len(self.descriptors) > len(hwi.names):
            return 0  # (a segment found beyond the tip that does not match: reported, held)
        if now < self._next_probe and self._streak == 0:
            return 0  # (answers coming in: probe every cycle until the rejoin is decided)
        self._next_probe = now + PROBE_INTERVAL_S
        return missing

    def _adopt(self, descs: list[dict], cmp: Comparison) -> None:
        try:
            robot, capped = adopt_capped(
                descs,
                self.file_robot.name,
                self.adopt_path,
                envelope_from(self.file_robot),
                original=self.file_robot,
            )
        except Exception as exc:  # noqa: BLE001 - composition failure is a user-facing error
            raise DaemonError(f"--adopt: cannot compose a robot from the chain: {exc}") from None
        for line in capped:
            log.warning("--adopt: %s (envelope of %s)", line, self.file_robot.source or "the file")
        log.warning(
            "chain differs from the description (%s); adopted the chain as found and wrote %s",
            cmp.text(),
            self.adopt_path,
        )
        self.full_robot = robot
        self._fanout.emit_event(
            "adopted",
            message=f"robot composed from the chain written to {self.adopt_path}",
            path=str(self.adopt_path),
            differences=[d.as_dict() for d in cmp.differences],
            capped=capped,
        )

    def build(
        self,
        descs: list[dict],
        cmp: Comparison,
        reason: str,
        *,
        abort: tuple[str, str, str | None] | None = None,
        affected: set[str] | None = None,
    ) -> list[str]:
        """New HWI and controllers for the first ``cmp.matched`` segments of ``descs``.

        ``abort``: ``(text, cause, segment)`` for the goals the rebuild ends (default: the
        reason, cause ``stopped``); ``affected``: the segments the change concerns — a goal
        that moves none of them runs on (None: every goal ends). Returns the ids aborted."""
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
        hwi = HardwareInterface(
            limits,
            self.link,
            self.reply_timeout,
            known=known,
            gap_cycles=self.gap_cycles,
            pipeline=self.cfg.pipeline,
        )
        hwi.configure()
        hwi.activate()
        state = robot_state_from(hwi, time.monotonic())
        ctx = ControllerContext(limits, robot, self._fanout.publish, self._submit)
        text, cause, segment = abort or (reason, "stopped", None)
        with self._lock:
            self.robot, self.hwi, self.descriptors, self.comparison = robot, hwi, descs, cmp
            aborted = self._motion.build(
                ctx, state, text, cause=cause, segment=segment, affected=affected
            )
            expected = chain_bendables(self.full_robot)
            if keep < len(expected):
                lost = expected[keep:]
                self.cut = {
                    # 1-based, like every position a user sees: the last segment kept
                    "after_position": keep,
                    "after": expected[keep - 1] if keep else None,
                    "lost": lost,
                }
            else:
                self.cut = None
        self._warn_if_rate_exceeds_the_chain(len(order))
        self._fanout.publish(
            {"kind": "topology", "t": time.monotonic(), "reason": reason, **self.describe()}
        )
        return aborted

    def _warn_if_rate_exceeds_the_chain(self, n: int) -> None:
        """Say so when a real UART chain of ``n`` segments cannot answer within a loop period."""
        warning = rate_warning(
            n,
            self.cfg.baudrate,
            self.reply_timeout,
            self.cfg.watchdog.reply_timeout_s,
            self.rate_hz,
            self.cfg.pipeline,
        )
        if warning is not None:
            log.warning("%s", warning)

    # -- changes (loop thread) ---------------------------------------------------------------
    def hotplug(
        self,
        reason: str,
        t_detect: float,
        verify: bool = False,
        position: int | None = None,
        rejoin: bool = False,
    ) -> None:
        """Hold, rediscover, abort, rebuild — in the loop thread, without restarting.

        ``verify`` (silent segments, no event): if discovery finds the very same chain, the
        silence was a stall (late replies, a loaded host): resume without aborting anything.
        ``position``: the 0-based index the reason concerns (named in the abort reason).
        ``rejoin``: a segment answered beyond the tip; nothing is held, and a rediscovery that
        finds no new segment changes nothing (a failed rejoin: the next one waits longer).
        Only the goals that move a segment the change concerns are aborted; the others run on
        through the rebuild.
        """
        if not verify and not rejoin:
            log.warning("topology change: %s", reason)
        before = list(self.hwi.names) if self.hwi is not None else []
        before_uids = [d.get("uid") for d in self.descriptors]
        try:
            self._hold_concerned(position, rejoin, len(before))
            descs = self.discover_retrying(quick=True)
        except OSError as exc:
            if self.port_ok():  # replies lost on a working port: rediscover shortly
                if rejoin:
                    self._rejoin_failed(reason, f"discovery incomplete: {exc}")
                    return
                if verify:
                    log.warning("topology change: %s", reason)
                self._abort(reason, verify, None, position)
                self.topology_changes += 1
                self._lost_chain(f"{reason}; discovery incomplete: {exc}")
                return
            self.link_lost(exc)
            return
        found = [d.get("uid") for d in descs]
        if rejoin and found == before_uids[: len(found)] and len(found) <= len(before_uids):
            self._rejoin_failed(reason, f"{len(found)} segment(s) answer DISCOVER")
            return
        if verify and self.hwi is not None and 0 < len(descs) < len(self.descriptors):
            # silence, no event, and fewer answers: a loaded host or a slow link loses replies
            # as well as a cut does; ask again (fed tries, up to the full discovery time)
            # before cutting
            if found == before_uids[: len(descs)]:
                again = self._discover_fed(len(descs))
                if len(again) > len(descs):
                    descs = again
        if verify and self.hwi is not None:
            same = [d.get("uid") for d in descs] == before_uids
            if same and descs:
                self.hwi.missing = [0] * len(self.hwi.names)
                self.hwi.resume_pending = True
                self.stalls += 1
                self._fanout.emit_event(
                    "link_stall",
                    message=f"{reason}, but the chain is unchanged: resumed",
                    reason=reason,
                    stall_s=round(time.monotonic() - t_detect, 4),
                )
                log.warning("stall: %s; chain unchanged, resumed", reason)
                return
            log.warning("topology change: %s", reason)
        elif rejoin:
            log.warning("topology change: %s", reason)
        cmp = compare(self.full_robot, descs) if descs else None
        if cmp is not None and not cmp.ok and self.adopt and cmp.matched < len(descs):
            try:
                self._adopt(descs, cmp)
                cmp = compare(self.full_robot, descs)
            except DaemonError as exc:
                log.error("%s", exc)
        affected = None
        if cmp is not None and cmp.matched:
            affected = self._affected(before, before_uids, descs, cmp.matched, position, rejoin)
        abort = self._abort_reason(reason, verify, descs, position)
        if cmp is None and verify and position is not None:
            # silence, then no answer at all: a cut, or the segment restarting — its BOOT
            # (when it comes back within BOOT_WAIT_S) decides the cause (recover())
            self._deferred_abort = (abort, position, time.monotonic() + BOOT_WAIT_S)
            aborted = []
        else:
            aborted = self._motion.abort_goals(*abort, only=affected)
        self.topology_changes += 1
        if cmp is None:
            self._lost_chain(f"{reason}; no segment answers DISCOVER")
            return
        if cmp.matched == 0:
            self._lost_chain(f"{reason}; {cmp.text()}")
            return
        t_disc = time.monotonic()
        try:
            aborted += self.build(descs, cmp, reason, abort=abort, affected=affected)
        except OSError as exc:
            self.link_lost(exc)
            return
        t_ready = time.monotonic()
        if len(self.hwi.names) < len(before):
            self._note_flap(t_ready)  # a segment lost: taken back only once it answers steadily
        elif rejoin and len(self.hwi.names) > len(before):
            self.rejoins += 1
        self.hotplug_log.append(
            {
                "t": t_detect,
                "reason": reason,
                "segments": list(self.hwi.names),
                "aborted_goals": aborted,
                "discover_s": t_disc - t_detect,
                "rebuild_s": t_ready - t_detect,
                "cut": self.cut,
                "differences": [d.as_dict() for d in cmp.differences],
            }
        )
        msg = rebuild_message(list(self.hwi.names), self.cut, cmp)
        self._fanout.emit_event(
            "topology_changed",
            message=f"{reason}: {msg}",
            reason=reason,
            segments=list(self.hwi.names),
            cut=self.cut,
            aborted_goals=aborted,
            rebuild_s=round(t_ready - t_detect, 4),
        )
        log.warning("rebuilt in %.0f ms: %s", (t_ready - t_detect) * 1e3, msg)

    def _hold_concerned(self, position: int | None, rejoin: bool, n: int) -> None:
        """HOLD the segments the change concerns: from ``position`` to the tip (addressed);
        the whole chain when the position is unknown or the first. The segments before it keep
        their last setpoint (and their watchdog) during the rediscovery. A rejoin holds none."""
        if rejoin:
            return
        if position is None or position <= 0:
            self.link.hold()
            return
        for p in range(position, max(n, position + 1)):
            self.link.hold(p)

    def _discover_fed(self, have: int) -> list[dict]:
        """Rediscover once more, up to ``discover_timeout_s`` in tries bounded by
        :meth:`feed_cap` with a HEARTBEAT before each; the first answer from more than
        ``have`` segments ends it. [] if none did (or the port failed)."""
        end = time.monotonic() + self.cfg.watchdog.discover_timeout_s
        best: list[dict] = []
        while True:
            self.feed()
            try:
                descs = self.discover(running=True, cap=self.feed_cap())
            except OSError:
                if not self.port_ok():
                    return best
                descs = []
            if len(descs) > len(best):
                best = descs
            if len(best) > have or time.monotonic() >= end:
                return best

    def _rejoin_failed(self, reason: str, why: str) -> None:
        """A rejoin whose rediscovery found no new segment: nothing changes (no goal aborted,
        no rebuild); the next rejoin of that segment waits for steadier answers."""
        self.rejoin_failures += 1
        self._note_flap(time.monotonic())
        log.info("%s: not taken back (%s); the chain stays as it is", reason, why)

    def _affected(
        self,
        before: list[str],
        before_uids: list[Any],
        descs: list[dict],
        keep: int,
        position: int | None,
        rejoin: bool,
    ) -> set[str]:
        """The segments of the chain known before that a change concerns: lost, found with
        another identity or name, or at or behind the position the reason concerns (a booted,
        silent or misaddressed segment and those behind it). A rejoin concerns none of them."""
        names = chain_bendables(self.full_robot)[:keep]
        uids = [d.get("uid") for d in descs[:keep]]
        out = set()
        for i, n in enumerate(before):
            if (
                i >= keep
                or names[i] != n
                or i >= len(before_uids)
                or uids[i] != before_uids[i]
                or (not rejoin and position is not None and i >= position)
            ):
                out.add(n)
        return out

    def _abort_reason(
        self, reason: str, silent: bool, descs: list[dict] | None, position: int | None
    ) -> tuple[str, str, str | None]:
        """``(text, cause, segment)`` of the goals a change aborts (host/motion_abort.py)."""
        return hotplug_abort(
            reason,
            silent=silent,
            before=[d.get("uid") for d in self.descriptors],
            found=None if descs is None else [d.get("uid") for d in descs],
            expected=chain_bendables(self.full_robot),
            position=position,
        )

    def _abort(
        self, reason: str, silent: bool, descs: list[dict] | None, position: int | None
    ) -> list[str]:
        """Abort every running goal naming the segment and the cause (host/motion_abort.py)."""
        return self._motion.abort_goals(*self._abort_reason(reason, silent, descs, position))

    def _lost_chain(self, why: str) -> None:
        """No usable segment: keep the port, retry discovery with back-off."""
        log.error("chain lost: %s", why)
        self.link_state = "waiting"
        self.link_error = why
        self._backoff = min(self._backoff, REJOIN_RETRY_S)
        self._reconnect_at = time.monotonic() + self._backoff
        with self._lock:
            self.hwi = None
        self._fanout.emit_event("chain_lost", message=why)

    def link_lost(self, exc: BaseException) -> None:
        """The port failed: abort goals, drop the HWI, close; :meth:`recover` reopens it."""
        log.error("link lost: %s", exc)
        self._deferred_abort = None  # every goal ends here
        with self._lock:
            first = self.hwi.names[0] if self.hwi is not None and self.hwi.names else None
            self._motion.abort_goals(f"link lost: {exc}", "link_loss", first)  # the host's port
            self.hwi = None
        self.close_link()
        self.link_state = "reconnecting"
        self.link_error = str(exc)
        self._reconnect_at = time.monotonic() + self._backoff
        self._fanout.emit_event("link_lost", message=str(exc))

    def recover(self) -> None:
        """Called by the loop while disconnected: reopen/rediscover when the back-off allows."""
        if self.stopping:
            return
        now = time.monotonic()
        self._settle_abort(now, found=False)
        if now < self._reconnect_at:
            return
        wd = self.cfg.watchdog
        try:
            if self.link is None:
                self.link = self._link_factory(self.port, self.cfg.baudrate)
            descs = self.discover_retrying()
        except OSError as exc:
            cap = wd.reconnect_max_s
            if self.port_ok():
                cap = min(cap, REJOIN_RETRY_S)  # a lost reply: the port is fine, retry soon
            elif self.link is not None:
                self.close_link()  # reopen from scratch next time
            self.link_error = str(exc)
            self._backoff = min(self._backoff * 2, cap)
            self._reconnect_at = now + self._backoff
            return
        cmp = compare(self.full_robot, descs) if descs else None
        if not descs or cmp.matched == 0:
            self.link_error = "no matching segment answers" if descs else "no segment answers"
            self._backoff = min(self._backoff * 2, wd.reconnect_max_s, REJOIN_RETRY_S)
            self._reconnect_at = now + self._backoff
            return
        self._settle_abort(now, found=True)
        try:
            self.build(descs, cmp, "reconnected", abort=("link restored", "link_loss", None))
        except OSError as exc:
            self.link_lost(exc)
            return
        self.link_state = "connected"
        self.link_error = ""
        self._backoff = wd.reconnect_min_s
        # the journal says the chain is back as loudly as it said it was lost
        log.warning("chain restored: %d segment(s) back on %s", len(self.hwi.names), self.port)
        self._fanout.emit_event(
            "link_restored",
            message=f"{len(self.hwi.names)} segment(s) back on {self.port}",
            segments=list(self.hwi.names),
        )

    def _settle_abort(self, now: float, found: bool) -> None:
        """Abort the goals whose abort waited for a BOOT: when the chain answers again
        (``found``), with cause topology_change if the silent segment reported BOOT meanwhile;
        else, once ``BOOT_WAIT_S`` passed, with the link_loss reason of the silence."""
        if self._deferred_abort is None:
            return
        abort, position, deadline = self._deferred_abort
        if found:
            events = self.link.events() if self.link is not None else []
            self._events.extend(events)
            if any(e.get("name") == "BOOT" and e.get("position") == position for e in events):
                abort = self._abort_reason(f"BOOT from {label(position)}", False, None, position)
        elif now < deadline:
            return
        self._deferred_abort = None
        self._motion.abort_goals(*abort)

    def take_events(self) -> list[dict]:
        """Segment events read while the chain was being recovered (for supervision)."""
        out, self._events = self._events, []
        return out

    def close_link(self) -> None:
        link, self.link = self.link, None
        if link is not None:
            try:
                link.close()
            except OSError:
                pass

    # -- read by the facade ------------------------------------------------------------------
    def describe(self) -> dict[str, Any]:
        """The chain as discovered, what is controlled, differences, cuts (caller holds lock)."""
        controlled = list(self.hwi.names) if self.hwi else []
        out = describe_chain(
            self.robot, self.full_robot, self.descriptors, controlled, self.comparison, self.cut
        )
        out["refused"] = self._refused  # a segment of another protocol version ends the chain
        return out
