"""The segment coordinator: chain forwarding, message handling, safety, and the control tick.

Two entry points, both allocation-free in steady state (proved by tests/device with heap_lock):

* ``poll()``: read both UARTs, feed the frame readers, forward / process every complete frame
  (chain rules of docs/architecture.md "Link protocol");
* ``tick(now_ms)``: one control cycle: read servos, detect faults, measure (kappa, phi), run the
  watchdog, step MC -> SC -> servos, downstream presence, ALIVE, queued EVENTs.

Safety states (docs/firmware.md): boot hold (no motion before the first SYNC), HOLD (message or
servo fault; left only by a SYNC with ``2: 1``), watchdog (no SYNC/HEARTBEAT for watchdog_ms:
hold; cleared by the next SYNC), FAULT (an exception in the loop, ``enter_fault``; left only by
CLEAR_FAULT, then HOLD). Whenever motion stops, the targets become the measured servo positions,
and when it starts again the curvature is slew-limited from the measured one. Motion starts only
where ``_first_motion_ok`` allows it: every servo's position known and inside its range.
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


import gc
from array import array

# Each module is compiled on its own after a collection: the compiler's peak, not the firmware's
# size, bounds the boot on an ESP32-sized heap (main.build does the same between its imports).
gc.collect()
import params  # noqa: E402

gc.collect()
import sc as scmod  # noqa: E402
from mechanism import CLAMP_SERVO, RANGE_TOL, Mechanism  # noqa: E402
from servos import FAULT_NONE, FAULT_RANGE, FAULT_STALL  # noqa: E402

gc.collect()
from protocol import device as pd  # noqa: E402
from protocol.constants import (  # noqa: E402
    ALIVE_SILENCE_MS,
    DOWNSTREAM_TIMEOUT_MS,
    ERR_BAD_VALUE,
    ERR_MALFORMED,
    ERR_UNSUPPORTED_VERSION,
    EV_BOOT,
    EV_DOWNSTREAM_DOWN,
    EV_DOWNSTREAM_UP,
    EV_FAULT,
    EV_LIMIT_CLAMPED,
    EV_SERVO_FAULT,
    EV_WATCHDOG_CLEARED,
    EV_WATCHDOG_TRIPPED,
    EVENT_MIN_INTERVAL_MS,
    FLAG_BCAST,
    FLAG_LOCAL,
    FLAG_UP,
    FLAGS_KNOWN,
    HEADER_LEN,
    MAX_ENCODED,
    MAX_FRAME,
    ST_CLAMPED,
    ST_DOWNSTREAM,
    ST_FAULT,
    ST_HOLD,
    ST_SERVO_FAULT,
    ST_UNCONFIGURED,
    ST_WATCHDOG,
    T_ALIVE,
    T_ERROR,
    T_HEARTBEAT,
    T_HOLD,
    T_SYNC,
    VERSION_MAX,
    VERSION_MIN,
)
from protocol.crc import _TABLE as _CRC_TABLE  # noqa: E402
from protocol.frame import FrameReader, forward_into  # noqa: E402

gc.collect()
from protocol.relay import Relay  # noqa: E402

try:  # the receive step in one call (rx is _RXBUF bytes, rout _RXBUF + 8: within its limits)
    from protocol._fast import scan_relay as _scan_relay
except Exception:  # no viper emitter: FrameReader.scan and Relay.feed
    _scan_relay = None

try:  # the usual SYNC in one call (protocol.device.decode_sync's machine-code step)
    from protocol._fast import sync_entry as _sync_entry
except Exception:  # no viper emitter: pd.decode_sync alone
    _sync_entry = None

try:
    from protocol._fast import move as _move
except Exception:  # no viper emitter: the same copy in bytecode

    def _move(src, s0, dst, d0, n):
        for k in range(n):
            dst[d0 + k] = src[s0 + k]


_TMASK = const(0x3FFFFFFF)
_CLAMP_EVENT_MS = const(100)  # LIMIT_CLAMPED at most once per 100 ms
_STALL_TOL = const(500)  # 0.05 rad: a servo this far from its command ...
_STALL_MOVE = const(50)  # ... that moved less than 0.005 rad ...
_STALL_MS = const(250)  # ... for 250 ms is stalled (feedback drivers only)
_EVQ = const(16)  # event queue length
_FAULT_TEXT = const(48)  # bytes of a FAULT's reason kept and sent (EVENT key 3)
_RXBUF = const(256)
_PEND = const(252)  # own upstream frames held while a relayed frame is half sent
# A relayed frame silent for more than this is ended (invalid COBS): a sender that died mid-frame
# must not hold the port (docs/firmware.md, "A neighbour that dies mid-frame"). On the wire a
# frame's bytes come back to back (10.9 us each at 921600 baud); a live relaying neighbour pauses
# inside one at most for its relay path plus a SYNC it handles (0.59 + 1.25 ms on the esp32 model),
# and ticks_ms stamps add < 1 ms. A live sender that pauses longer (a slow-path reply) loses no
# frame: the reader never gives up on it, and once complete and good it goes on
# store-and-forward. The emulator runs this same limit.
_RELAY_SILENCE_MS = const(3)
_LOAD_WINDOW_MS = const(1000)  # CPU load measured over windows this long
_T_CALIBRATE = const(0x09)  # protocol.constants T_CALIBRATE (device/calib.py handles it)


# Elapsed time: ``(a - b) & _TMASK`` is the ms from the past stamp ``b`` to ``a`` (stamps wrap at
# 2**30), in [0, 2**30); written out where it is used (a call per use cost the cycle more than
# the subtraction). Unsigned on purpose: every use asks "how long since", and a signed difference
# would turn negative (hold events back, never time out) after 2**29 ms (6.2 days) without a
# refresh of the stamp. A stamp exactly k * 2**30 ms (12.4 days) old reads as new: at worst one
# interval late.


class Segment:
    """One segment: ``hal`` (uarts, clock), ``cfg`` (config.Config), ``bus`` (servo driver)."""

    def __init__(self, hal, cfg, bus, tick_ms=5):
        self.hal = hal
        self.cfg = cfg
        self.bus = bus
        self.tick_ms = tick_ms
        self.n = cfg.n
        self.uid = (cfg.uid_override or hal.uid()).lower()
        # frame handlers bound once: fetching a bound method in the loop would allocate
        self._on_up = self._from_up
        self._on_down = self._from_down  # requests' uids are compared lowered
        self.mc = Mechanism(cfg, tick_ms)
        si = cfg.si
        self.sc = scmod.SimpleControllers(cfg.n, cfg.sc, si["sc_gain"], si["servo_speed"], tick_ms)
        self.watchdog_ms = cfg.watchdog_ms
        self.kappa_max_si = float(si["kappa_max"])
        self.rate_max_si = float(si["kappa_rate_max"])
        # receive side
        self.rxu = bytearray(_RXBUF)
        self.rxd = bytearray(_RXBUF)
        self.rd_up = FrameReader()
        self.rd_dn = FrameReader()
        # cut-through (protocol/relay.py): broadcasts pass downstream and upstream frames pass
        # upstream while they arrive; own frames wait in ``pend`` while one is half sent
        self.rl_dn = Relay(False)
        self.rl_up = Relay(True)
        self.rout = bytearray(_RXBUF + 8)
        self.pend = bytearray(_PEND)
        self.pend_len = 0
        self.t_rx_up = 0
        self.t_rx_dn = 0
        # relay points inside a tick: a frame completed there waits (held) for the next poll,
        # with the unscanned rest of its read kept in rx (keep: up pos, up len, down pos, len)
        self.held = bytearray(2)
        self.keep = array("H", [0, 0, 0, 0])
        # transmit side: scratch raw frame + one wire buffer, written with write(buf, n)
        # (stream write with a length: no slice object, which would be a heap allocation)
        self.raw = bytearray(MAX_FRAME)
        self.wire = bytearray(MAX_ENCODED + 8)
        self.sync_out = [0, 0, 0, 0]
        # pd.state_frame's machine-code builder where the port has it (pd checked it against
        # the bytecode encoder at import) and the buffers hold a STATE of n servos
        sw = pd._state_wire
        if sw is None or 26 + 2 * cfg.n > MAX_FRAME or 28 + 2 * cfg.n > MAX_ENCODED + 8:
            sw = None
        self._state_wire = sw
        # counters
        self.dropped = 0  # good CRC but not acceptable (direction, flags, version, malformed)
        self.events_lost = 0
        self.overruns = 0
        self.cycle_us = 0
        self.cycle_us_max = 0
        # CPU load: % of the last window (>= 1 s) not spent in hal.wait, and its peak
        self.cpu_load = 0
        self.cpu_load_peak = 0
        self.load_us = hal.ticks_us()
        self.load_ms = hal.ticks_ms()
        hal.idle_us = 0
        # safety state
        self.armed = False  # boot hold until the first SYNC
        self.hold = False
        self.wd_armed = False
        self.wd_tripped = False
        self.moving = False
        self.fault_bits = 0  # latched servo faults (bit per servo)
        self.clamped = 0  # clamp bits of the last cycle (CLAMPED status bit)
        self.sp_clamp = 0  # clamp bits of the last setpoint (kappa_max)
        self.clamp_pending = 0
        self.clamp_queued = False  # a LIMIT_CLAMPED is in the event queue
        self.fault_code = 0  # FAULT state: the code (protocol FAULT_*), 0 = no fault
        self.fault_count = 0  # exceptions caught by the loop since boot
        self.fault_msg = bytearray(_FAULT_TEXT)
        self.fault_len = 0
        # a servo measured outside [zero + min - tol, zero + max + tol] is faulty (FAULT_RANGE)
        self.range_lo = array(
            "i", [cfg.zero[i] + cfg.min_angle[i] - RANGE_TOL for i in range(cfg.n)]
        )
        self.range_hi = array(
            "i", [cfg.zero[i] + cfg.max_angle[i] + RANGE_TOL for i in range(cfg.n)]
        )
        self.position = 0
        now = hal.ticks_ms()
        self.now = now
        self.last_feed = now
        self.last_clamp_ev = now - _CLAMP_EVENT_MS
        self.last_sp = now  # arrival time of the last accepted SYNC setpoint (rate check)
        self.last_up_tx = now
        self.last_down_rx = now
        self.down_present = False
        self.last_event = now - EVENT_MIN_INTERVAL_MS
        self.stall_ref = array("i", [0] * cfg.n)
        self.stall_t = array("i", [now] * cfg.n)
        self.prev_fault = bytearray(cfg.n)  # current fault code per servo (driver or stall)
        # event queue (ring of code, detail)
        self.evq = array("i", [0] * (2 * _EVQ))
        self.ev_head = 0
        self.ev_len = 0
        # start in a safe hold at the measured position
        bus.poll(now)
        self.mc.hold_here(bus.pos)
        self.sc.reset(bus.pos)
        for i in range(cfg.n):
            self.stall_ref[i] = bus.pos[i]
        if cfg.error:
            print("[segment]", cfg.error)
        self.event(EV_BOOT, 0)
        # sent now, before any frame is handled: on the wire the BOOT precedes every reply of
        # this life (a DISCOVER already waiting would be answered first at the first poll, and
        # the host would take a BOOT after its discovery for a restart)
        self.service(now)

    # ---- output helpers --------------------------------------------------------------------
    def _up(self, end):
        if self.rl_up.busy:  # a relayed frame is half sent upstream: ours goes after it
            p = self.pend_len
            if p + end <= _PEND:
                _move(self.wire, 0, self.pend, p, end)
                self.pend_len = p + end
                return
            # no room left: end the relayed frame (invalid) rather than lose an own frame; a
            # live sender's frame still follows, store-and-forward, once it is complete
            self._cut_up()
        self.hal.up.write(self.wire, end)
        self.last_up_tx = self.now

    def _cut_up(self):
        """End the frame half relayed upstream as invalid COBS, then send the own frames that
        waited behind it."""
        m = self.rl_up.abort(self.rout)
        if m:
            self.hal.up.write(self.rout, m)
        self._flush_pending()

    def _flush_pending(self):
        if self.pend_len and not self.rl_up.busy:
            self.hal.up.write(self.pend, self.pend_len)
            self.pend_len = 0
            self.last_up_tx = self.now

    def event(self, code, detail):
        """Queue an EVENT (sent from ``tick``, at most one per EVENT_MIN_INTERVAL_MS); False if
        the queue was full (counted in ``events_lost``)."""
        if self.ev_len >= _EVQ:
            self.events_lost += 1
            return False
        j = ((self.ev_head + self.ev_len) % _EVQ) * 2
        self.evq[j] = code
        self.evq[j + 1] = detail
        self.ev_len += 1
        return True

    def _reply(self, mtype, seq, obj):
        """Slow path: ``obj`` CBOR-encoded into an UP frame and sent (params.reply)."""
        params.reply(self, mtype, seq, obj)

    def _error(self, seq, code, mtype, text):
        self._reply(T_ERROR, seq, {0: code, 1: mtype, 2: text})

    def status(self):
        s = self.clamped and ST_CLAMPED
        if self.hold or not self.armed or self.cfg.error or not self.bus.known:
            s |= ST_HOLD
        if self.fault_code:
            s |= ST_FAULT
        if self.wd_tripped:
            s |= ST_WATCHDOG
        if self.fault_bits:
            s |= ST_SERVO_FAULT
        if self.down_present:
            s |= ST_DOWNSTREAM
        if self.cfg.unconfigured or self.cfg.error:
            s |= ST_UNCONFIGURED
        return s

    def _send_state(self, cycle, seq):
        mc = self.mc
        if self._state_wire is not None:  # pd.state_frame's machine-code call, made here
            self._up(
                self._state_wire(
                    self.raw,
                    self.wire,
                    seq,
                    cycle,
                    self.now,
                    mc.kappa,
                    mc.phi,
                    self.status() | self.position << 8,
                    mc.joint,
                    self.n,
                    _CRC_TABLE,
                )
            )
            return
        end = pd.state_frame(
            self.raw,
            self.wire,
            seq,
            cycle,
            self.now,
            mc.kappa,
            mc.phi,
            mc.joint,
            self.n,
            self.status(),
            self.position,  # whose SYNC entry we apply (the host checks it)
        )
        self._up(end)

    # ---- receiving -------------------------------------------------------------------------
    def poll(self):
        """Handle everything waiting on both ports; return the number of bytes read."""
        now = self.hal.ticks_ms()
        self.now = now
        total = self._pump(now, False, self.hal.rx_any())
        # (the silence clocks t_rx_up/t_rx_dn are now when bytes came just now)
        if self.rl_dn.busy and ((now - self.t_rx_up) & _TMASK) > _RELAY_SILENCE_MS:
            m = self.rl_dn.abort(self.rout)  # the frame stopped mid-way: end it invalid
            if m:
                self.hal.down.write(self.rout, m)
        if self.rl_up.busy and ((now - self.t_rx_dn) & _TMASK) > _RELAY_SILENCE_MS:
            self._cut_up()
        return total

    def relay_point(self):
        """Pass on what arrived meanwhile, between two phases of a tick (docs/firmware.md,
        "Forwarding inside a tick"): bytes are relayed (cut-through) at once, but a frame from
        upstream that completes here is only held (``held``) and handled by the next ``poll``,
        right after the tick, so no phase of a tick sees a setpoint, HOLD or parameter change
        under it."""
        mask = self.hal.rx_any()
        if mask:
            self._pump(self.hal.ticks_ms(), True, mask)

    def _pump(self, now, defer, mask):
        """Drain the ports ``mask`` names (``hal.rx_any``: 1 upstream, 2 downstream) and those
        holding a frame; a quiet port costs no call."""
        hal = self.hal
        held = self.held
        n = 0
        k = 0
        if mask & 1 or held[0]:
            n = self._drain(
                hal.up, self.rxu, self.rd_up, self._on_up, self.rl_dn, hal.down, 0, defer
            )
            if n:
                self.t_rx_up = now
        if mask & 2 or held[1]:
            # frames from downstream change no control state (neighbour presence, events,
            # forwarding): handled at once even at a relay point, so a STATE behind another
            # one never waits for the tick to end
            k = self._drain(
                hal.down, self.rxd, self.rd_dn, self._on_down, self.rl_up, hal.up, 1, False
            )
            if k:
                self.t_rx_dn = now
        return n + k

    def _drain(self, uart, rx, rd, handle, relay, dst, side, defer):
        """Read ``uart`` into ``rx`` until empty; relay what passes through to ``dst`` as it comes
        and hand every complete frame to ``handle``. ``defer``: stop at a complete frame instead
        (``held[side]``), keeping the bytes after it (``keep``) for the next call; a held frame
        blocks further reading on that side until a call without ``defer`` handles it."""
        held = self.held
        if held[side]:
            if defer:
                return 0
            held[side] = 0
            handle(rd)
            if self.pend_len:
                self._flush_pending()
        total = 0
        rout = self.rout
        keep = self.keep
        j = side + side
        pos = keep[j]
        n = keep[j + 1]
        fresh = False
        if pos >= n:
            pos = 0
            n = uart.readinto(rx)
            fresh = True
        while n:
            if fresh:
                total += n
            while pos < n:
                if _scan_relay is not None:  # the two calls below in one machine-code call
                    r = _scan_relay(rd, relay, rx, pos, n, rout, _CRC_TABLE)
                    nxt = r & 0xFFF
                    m = (r >> 12) & 0xFFF
                    ok = r >> 24
                else:
                    nxt = rd.scan(rx, pos, n)
                    ok = rd.ready
                    m = relay.feed(rx, pos, nxt, ok, rd, rout)
                if m:
                    dst.write(rout, m)
                pos = nxt
                if ok:
                    if defer:
                        held[side] = 1
                        keep[j] = pos
                        keep[j + 1] = n
                        return total
                    handle(rd)
                if self.pend_len:
                    self._flush_pending()
            n = uart.readinto(rx) if n == _RXBUF or not fresh else 0
            pos = 0
            fresh = True
        keep[j] = 0
        keep[j + 1] = 0
        return total

    def _from_up(self, r):
        flags = r.flags
        if flags & FLAG_UP:
            self.dropped += 1  # travels towards the host but came from the host side
            return
        if flags & ~FLAGS_KNOWN & 0xFF:
            self.dropped += 1
            self._error(r.seq, ERR_MALFORMED, r.mtype, "unknown flag bits 0x%02x" % flags)
            return
        if not VERSION_MIN <= r.ver <= VERSION_MAX:  # pd.version_supported, without a call
            self.dropped += 1
            self._reply(
                T_ERROR,
                r.seq,
                {
                    0: ERR_UNSUPPORTED_VERSION,
                    1: r.mtype,
                    2: "supported protocol versions %d..%d" % (VERSION_MIN, VERSION_MAX),
                    3: [VERSION_MIN, VERSION_MAX],
                },
            )
            return
        hop = r.hop
        # pd.route and pd.next_hop written out (FLAG_UP is excluded above): a link-local frame
        # is ours only; a broadcast is ours and goes on with hop + 1; an addressed frame is ours
        # at hop 0, else it goes on with hop - 1
        if flags & FLAG_LOCAL:
            self._process(r, flags, hop)
            return
        bc = flags & FLAG_BCAST
        if (bc or hop) and not self.rl_dn.relayed:
            # store-and-forward what was not relayed (addressed frames); payload bytes intact
            end = forward_into(r.raw, r.raw_len, (hop + 1) & 0xFF if bc else hop - 1, self.wire)
            self.hal.down.write(self.wire, end)
            r.raw[2] = hop  # restore our view of the header (CRC no longer needed)
        if bc or not hop:
            self._process(r, flags, hop)

    def _from_down(self, r):
        self.last_down_rx = self.now
        if not self.down_present:
            self.down_present = True
            self.event(EV_DOWNSTREAM_UP, 0)
        flags = r.flags
        if flags & FLAG_LOCAL:
            return  # ALIVE (or any link-local frame) from the neighbour: consumed
        if flags & FLAG_UP:
            if not self.rl_up.relayed:  # (other versions: store-and-forward)
                end = forward_into(r.raw, r.raw_len, r.hop + 1, self.wire)
                self._up(end)
            return
        self.dropped += 1  # a host-bound frame must carry FLAG_UP

    # ---- processing ------------------------------------------------------------------------
    def _process(self, r, flags, hop):
        t = r.mtype
        raw = r.raw
        pe = r.payload_end
        seq = r.seq
        if t == T_SYNC:
            if flags & FLAG_BCAST:
                self.position = hop
            out = self.sync_out
            # the usual encoding in one machine-code call (pd.decode_sync's first step, called
            # here directly: HEADER_LEN <= pe <= len(raw) holds for every frame the reader
            # completes); anything else, or no emitter: the general decoder
            pos = self.position
            res = -1 if _sync_entry is None else _sync_entry(raw, HEADER_LEN, pe, pos, out)
            if res < 0:
                res = pd.decode_sync(raw, HEADER_LEN, pe, pos, out)
            if res < 0:
                self.dropped += 1
                self._error(seq, ERR_MALFORMED, t, "malformed SYNC")
                return
            self._on_sync(res, out, seq)
        elif t == T_HEARTBEAT:
            if flags & FLAG_BCAST:
                self.position = hop
            c = pd.decode_cycle(raw, HEADER_LEN, pe)
            if c < 0:
                self.dropped += 1
                self._error(seq, ERR_MALFORMED, t, "malformed HEARTBEAT")
                return
            self.last_feed = self.now
            self.wd_armed = True
            self._send_state(c, seq)
        elif t == T_HOLD:
            if pd.decode_empty(raw, HEADER_LEN, pe) < 0:
                self.dropped += 1
                self._error(seq, ERR_MALFORMED, t, "malformed HOLD")
                return
            self.enter_hold()
        elif t == T_ALIVE:
            # link-local keep-alive from the host side: nothing to do, but its payload is
            # checked like any other (docs/protocol.md: an empty map; invalid -> MALFORMED)
            if pd.decode_empty(raw, HEADER_LEN, pe) < 0:
                self.dropped += 1
                self._error(seq, ERR_MALFORMED, t, "malformed ALIVE")
        elif t == _T_CALIBRATE:
            import gc

            gc.collect()
            try:
                import calib  # slow path, loaded on demand (device/calib.py)
            except MemoryError:
                self._error(seq, ERR_BAD_VALUE, t, "no heap for calibration: reboot, retry")
                return
            calib.request(self, flags, raw, pe, seq)
        else:  # DISCOVER, PARAM_*, CLEAR_FAULT, unknown: the slow path
            params.request(self, t, flags, hop, raw, pe, seq)

    def _on_sync(self, res, out, seq):
        self.last_feed = self.now
        self.wd_armed = True
        if self.wd_tripped:
            self.wd_tripped = False
            self.event(EV_WATCHDOG_CLEARED, 0)
        if out[3] and self.hold:
            self._try_resume()
        self.armed = True
        if self._may_move() and (self.moving or self._first_motion_ok()):
            if not self.moving:
                self._start_moving()
            if res == pd.OK:
                c = self.mc.set_target(out[1], out[2], (self.now - self.last_sp) & _TMASK)
                self.last_sp = self.now
                self.sp_clamp = c
                self.clamped |= c
                self.clamp_pending |= c
        self._send_state(out[0], seq)

    def _try_resume(self):
        if self.fault_code:
            return False  # FAULT is left only by CLEAR_FAULT
        bus = self.bus
        pos = bus.pos
        for i in range(self.n):
            f = bus.fault[i]
            if f != FAULT_NONE and f != FAULT_STALL:
                return False  # the driver still reports the fault: stay in hold
            if bus.known and (pos[i] < self.range_lo[i] or pos[i] > self.range_hi[i]):
                return False  # still out of range: accepted only once it is back inside
        self.fault_bits = 0
        for i in range(self.n):
            self.prev_fault[i] = 0
        self.hold = False
        return True

    def _may_move(self):
        # a config.json that was rejected or absent (main.NO_CONFIG) leaves the calibration
        # unknown: never move on guessed zero offsets
        return (
            self.armed
            and not self.hold
            and not self.wd_tripped
            and not self.cfg.error
            and not self.fault_code
        )

    def _first_motion_ok(self):
        """The first-motion rule, decided here only (docs/firmware.md, "First motion"): motion
        starts when every servo's position is known (bus servos: read from each; open loop: the
        configured rest pose) and inside its range. From there the SC moves at most servo_speed
        per tick and the MC keeps every target inside [min, max], whatever the setpoint asks."""
        bus = self.bus
        if not bus.known:
            return False
        pos = bus.pos
        for i in range(self.n):
            if pos[i] < self.range_lo[i] or pos[i] > self.range_hi[i]:
                return False  # reported as SERVO_FAULT out_of_range by _faults
        return True

    def _start_moving(self):
        self.moving = True
        pos = self.bus.pos
        self.mc.hold_here(pos)
        self.sc.reset(self.mc.servo_target)
        for i in range(self.n):
            self.stall_ref[i] = pos[i]
            self.stall_t[i] = self.now

    def _stop_moving(self):
        self.moving = False
        bus = self.bus
        self.mc.hold_here(bus.pos)
        self.sc.reset(self.mc.servo_target)
        if bus.enabled:
            bus.command(self.mc.servo_target, self.now)  # stop now, not at the next tick

    def enter_hold(self):
        """HOLD message or fault: stop where we are; only a SYNC with resume leaves it."""
        self.hold = True
        if self.moving:
            self._stop_moving()

    def stop_for_repl(self):
        """The loop ends (Ctrl-C: the REPL takes over, nothing drives the servos any more): their
        safe state, as in FAULT: held at the measured positions, or (``fault_action``
        "release") no longer driven (PWM pulses off, Feetech torque off)."""
        self.enter_hold()
        if self.cfg.fault_action == "release":
            self.moving = False
            self.bus.release()

    def enter_fault(self, code, text):
        """An exception escaped the loop (``main.Runner``): enter FAULT, the one place
        (params.enter_fault, the slow path)."""
        params.enter_fault(self, code, text)

    def clear_fault(self):
        """CLEAR_FAULT: leave FAULT for HOLD (a SYNC with resume moves again); False if none."""
        return params.clear_fault(self)

    # ---- control tick ----------------------------------------------------------------------
    def tick(self, now):
        """One control cycle at time ``now`` (ms since boot)."""
        t0 = self.hal.ticks_us()
        self.now = now
        bus = self.bus
        mc = self.mc
        # relay points (docs/firmware.md "Forwarding inside a tick") between phases of about
        # equal length: servo read + fault checks, measure, MC update, SC step + command
        hal = self.hal
        # each relay point is ``relay_point()`` written out (a call per point cost the tick more)
        bus.poll(now)
        self._faults(now)
        m = hal.rx_any()
        if m:
            self._pump(hal.ticks_ms(), True, m)
        mc.measure(bus.pos)
        m = hal.rx_any()
        if m:
            self._pump(hal.ticks_ms(), True, m)
        if self.wd_armed and not self.wd_tripped:
            if ((now - self.last_feed) & _TMASK) > self.watchdog_ms:
                self.wd_tripped = True
                self.event(EV_WATCHDOG_TRIPPED, (now - self.last_feed) & _TMASK)
        if self.moving and not self._may_move():
            self._stop_moving()
        if self.moving:
            f = mc.update()
            m = hal.rx_any()
            if m:
                self._pump(hal.ticks_ms(), True, m)
            bus.command(self.sc.step(mc.servo_target), now)
            if bus.saturated:
                f |= CLAMP_SERVO  # output clipped (PWM pulse range): pos holds the achieved angle
            self.clamped = self.sp_clamp | f
            self.clamp_pending |= f
        elif bus.enabled:
            bus.command(mc.servo_target, now)  # keep holding the measured position
        m = hal.rx_any()
        if m:
            self._pump(hal.ticks_ms(), True, m)
        bus.request(now)
        self.service(now)
        us = hal.ticks_diff(hal.ticks_us(), t0)
        self.cycle_us = us
        if us > self.cycle_us_max:
            self.cycle_us_max = us
        if ((now - self.load_ms) & _TMASK) >= _LOAD_WINDOW_MS:
            self._measure_load(now)

    def _measure_load(self, now):
        """CPU load of the window that ends now: the share not spent waiting in ``hal.wait``
        (docs/firmware.md, "CPU load"). Small ints only (no allocation)."""
        hal = self.hal
        t = hal.ticks_us()
        span = hal.ticks_diff(t, self.load_us)
        idle = hal.idle_us
        hal.idle_us = 0
        self.load_us = t
        self.load_ms = now
        if span < 100:
            return
        pct = (span - idle) // (span // 100)
        if pct < 0:
            pct = 0
        elif pct > 100:
            pct = 100
        self.cpu_load = pct
        if pct > self.cpu_load_peak:
            self.cpu_load_peak = pct

    def service(self, now):
        """Chain housekeeping of a tick (downstream presence, LIMIT_CLAMPED, EVENT or ALIVE).
        ``main.Runner`` calls it on its own when the control part raised, so a segment in FAULT
        still reports and keeps its link alive."""
        if self.down_present and ((now - self.last_down_rx) & _TMASK) > DOWNSTREAM_TIMEOUT_MS:
            self.down_present = False
            self.event(EV_DOWNSTREAM_DOWN, 0)
        # LIMIT_CLAMPED: one in the queue at a time, queued >= 100 ms after the previous one was
        # *sent*, so the events on the wire are >= 100 ms apart however the queue delays them
        if (
            self.clamp_pending
            and not self.clamp_queued
            and ((now - self.last_clamp_ev) & _TMASK) >= _CLAMP_EVENT_MS
            and self.event(EV_LIMIT_CLAMPED, self.clamp_pending)
        ):
            self.clamp_pending = 0
            self.clamp_queued = True
        if self.rl_up.busy or self.pend_len:
            return  # a relayed frame is half sent upstream: events wait in their queue
        if self.ev_len and ((now - self.last_event) & _TMASK) >= EVENT_MIN_INTERVAL_MS:
            j = self.ev_head * 2
            code = self.evq[j]
            if code == EV_LIMIT_CLAMPED:
                self.last_clamp_ev = now
                self.clamp_queued = False
            tl = self.fault_len if code == EV_FAULT else 0
            end = pd.event_frame(
                self.raw, self.wire, 0, code, self.evq[j + 1], now, self.fault_msg, tl
            )
            self._up(end)
            self.ev_head = (self.ev_head + 1) % _EVQ
            self.ev_len -= 1
            self.last_event = now
        elif ((now - self.last_up_tx) & _TMASK) >= ALIVE_SILENCE_MS:
            self._up(pd.alive_frame(self.raw, self.wire, 0))

    def _faults(self, now):
        bus = self.bus
        fb = bus.feedback
        moving = self.moving
        known = bus.known
        fault = bus.fault  # arrays bound once: an attribute lookup per use cost the tick more
        pos = bus.pos
        lo = self.range_lo
        hi = self.range_hi
        prev = self.prev_fault
        for i in range(self.n):
            f = fault[i]
            if f == FAULT_NONE and known:
                p = pos[i]
                if p < lo[i] or p > hi[i]:
                    f = FAULT_RANGE  # e.g. powered up outside its range: never start there
            if fb and moving and f == FAULT_NONE:
                p = pos[i]
                e = self.sc.cmd[i] - p
                d = p - self.stall_ref[i]
                if -_STALL_TOL <= e <= _STALL_TOL or d > _STALL_MOVE or d < -_STALL_MOVE:
                    self.stall_ref[i] = p
                    self.stall_t[i] = now
                elif ((now - self.stall_t[i]) & _TMASK) > _STALL_MS:
                    f = FAULT_STALL
            if f != FAULT_NONE and prev[i] == FAULT_NONE:
                self.fault_bits |= 1 << i
                self.event(EV_SERVO_FAULT, i)
                self.enter_hold()
            prev[i] = f

    # ---- slow path (device/params.py: compiled apart, so boot needs less heap at once) --------
    def descriptor(self):
        """Descriptor dict with the contract's names (SI floats)."""
        return params.descriptor(self)

    def descriptor_payload(self):
        """DESCRIPTOR payload: int keys 0..16 of the contract, SI floats."""
        return params.descriptor_payload(self)

    def get_param(self, pid):
        return params.get_param(self, pid)

    def set_param(self, pid, v):
        """Change a run-time parameter (SI units); ValueError with the reason if refused."""
        params.set_param(self, pid, v)
