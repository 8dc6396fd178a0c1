"""Feetech STS / SCS serial bus servos (half-duplex TTL bus), non-blocking.

Packet: ``FF FF id len instr params... chk`` with len = len(params) + 2 and
chk = ~(id + len + instr + sum(params)) & 0xFF; a reply is ``FF FF id len error params... chk``.
Each cycle: one SYNC WRITE (instr 0x83, broadcast id 0xFE) of the goal positions (register 0x2A)
of all servos (``command``), then one READ (instr 0x02) of 8 bytes from 0x38 (present position,
speed, load, voltage, temperature) of one servo, round robin (``request``, also during the boot
hold); its reply is parsed in the next cycle, so the loop never waits on the bus.
Faults: no valid reply for ``misses`` consecutive polls ->
FAULT_NO_REPLY; error byte bit 5 (overload) or bit 3 (overcurrent) -> FAULT_OVERLOAD; any other
error bit (voltage, sensor, temperature) -> FAULT_ERROR. STS is little-endian, 4096 steps per turn,
centre 2048; SCS is big-endian, 1024 steps over 300 deg, centre 512. The bus UART and its pins
(``uart``, ``tx``, ``rx``) come from config ``bus``, which config.py fills from the board's profile
in protocol/boards.py (the one source: ``esp32s3-usbrepl`` UART0 TX 43 RX 44; a stock ESP32 has no
UART left for a bus) and which may override them and ``baud`` (default 1000000),
``steps_per_rev``, ``centre``, ``max_step``, ``misses`` (default 3).
Echoed own bytes (single-wire adapters) are skipped: only a status packet of the polled id and
the expected length is accepted.
"""

from array import array

import fxp

from servos import FAULT_ERROR, FAULT_NO_REPLY, FAULT_NONE, FAULT_OVERLOAD, ServoBus

_SYNC_WRITE = 0x83
_READ = 0x02
_WRITE = 0x03
_REG_TORQUE = 0x28
_REG_GOAL = 0x2A
_REG_PRESENT = 0x38
_READ_LEN = 8
_REPLY_LEN = _READ_LEN + 6  # FF FF id len err 8*data chk


def checksum(buf, start, end):
    """Feetech checksum of buf[start:end] (id .. last param)."""
    s = 0
    for i in range(start, end):
        s += buf[i]
    return (~s) & 0xFF


class FeetechBus(ServoBus):
    name = "feetech"

    def __init__(self, cfg, hal, scs=False):
        ServoBus.__init__(self, cfg.n)
        b = {"baud": 1000000, "misses": 3}  # UART and pins: the board's (protocol/boards.py)
        if scs:
            b.update({"steps_per_rev": 1228.8, "centre": 512, "max_step": 1023})
        else:
            b.update({"steps_per_rev": 4096, "centre": 2048, "max_step": 4095})
        if cfg.si.get("bus"):
            b.update(cfg.si["bus"])
        if "uart" not in b or "tx" not in b or "rx" not in b:
            raise ValueError("no servo bus UART/pins in the configuration (board profile's bus)")
        self.big_endian = scs
        self.ids = bytearray(cfg.servo_ids)
        self.centre = int(b["centre"])
        self.max_step = int(b["max_step"])
        self.misses_max = int(b["misses"])
        spe4 = b["steps_per_rev"] / (2 * 3.141592653589793 * 10000.0)  # steps per 1e-4 rad
        self.q_f = fxp.q_for([spe4])
        self.k_f = fxp.to_q(spe4, self.q_f)
        # back: 1e-4 rad per step in 1/256 (|steps - centre| < 2**16 keeps the product < 2**30)
        self.k_b = int(256.0 / spe4 + 0.5)
        if self.k_b >= 1 << 14:
            raise ValueError("bus.steps_per_rev too small")
        self.uart = hal.servo_uart(b)
        n = cfg.n
        self.tx = bytearray(8 + 3 * n)  # sync write
        self.rq = bytearray(8)  # read request
        self.rx = bytearray(64)
        self.rx_len = 0
        self.polled = -1  # index of the servo whose reply is pending
        self.next_poll = 0
        self.miss = bytearray(n)
        self.load = array("h", [0] * n)  # 0.1 % of max torque, signed
        self.voltage = bytearray(n)  # 0.1 V
        self.temperature = bytearray(n)  # deg C
        self.err = bytearray(n)  # last error byte
        for i in range(n):
            self.pos[i] = cfg.zero[i]  # placeholder: nothing is commanded before every read
        self.seen = bytearray(n)  # 1 once a present position was read from servo i
        self.limp = False
        t = self.tx
        t[0] = 0xFF
        t[1] = 0xFF
        t[2] = 0xFE
        t[3] = 3 * n + 4
        t[4] = _SYNC_WRITE
        t[5] = _REG_GOAL
        t[6] = 2
        r = self.rq
        r[0] = 0xFF
        r[1] = 0xFF
        r[3] = 4
        r[4] = _READ
        r[5] = _REG_PRESENT
        r[6] = _READ_LEN

    def torque(self, on):
        """Enable or disable torque on every servo (slow path: allocates)."""
        for sid in self.ids:
            p = bytearray([0xFF, 0xFF, sid, 4, _WRITE, _REG_TORQUE, 1 if on else 0, 0])
            p[7] = checksum(p, 2, 7)
            self.uart.write(p)

    def _send(self, targets, now_ms):
        if self.limp:  # after a release: torque back on first (slow path, once)
            self.torque(True)
            self.limp = False
        t = self.tx
        j = 7
        sat = False
        for i in range(self.n):
            s = self.centre + fxp.mulq(targets[i], self.k_f, self.q_f)
            if s < 0:
                s = 0
                sat = True
            elif s > self.max_step:
                s = self.max_step
                sat = True
            t[j] = self.ids[i]
            if self.big_endian:
                t[j + 1] = s >> 8
                t[j + 2] = s & 0xFF
            else:
                t[j + 1] = s & 0xFF
                t[j + 2] = s >> 8
            j += 3
        t[j] = checksum(t, 2, j)
        self.uart.write(t)
        self.saturated = sat

    def _release(self):
        self.torque(False)
        self.limp = True

    def request(self, now_ms):
        """Ask one servo (round robin) for its state; the reply is parsed by the next poll."""
        k = self.next_poll
        self.next_poll = (k + 1) % self.n
        r = self.rq
        r[2] = self.ids[k]
        r[7] = checksum(r, 2, 7)
        self.uart.readinto(self.rx)  # drop stale bytes (e.g. echo of earlier packets)
        self.uart.write(r)
        self.polled = k

    def _refresh(self, now_ms):
        k = self.polled
        if k < 0:
            return
        self.polled = -1
        n = self.uart.readinto(self.rx)
        self.rx_len = n if n else 0
        if self.parse(k):
            self.miss[k] = 0
        else:
            m = self.miss[k] + 1
            if m >= self.misses_max:
                m = self.misses_max
                self.fault[k] = FAULT_NO_REPLY
            self.miss[k] = m

    def telemetry(self, i):
        """Last (voltage V, temperature deg C, load fraction) read from servo i; None before the
        first reply."""
        if not self.seen[i]:
            return None
        return (self.voltage[i] / 10.0, float(self.temperature[i]), self.load[i] / 1000.0)

    def parse(self, k):
        """Find servo k's status packet in the receive buffer; store its values. True if found."""
        buf = self.rx
        sid = self.ids[k]
        end = self.rx_len - _REPLY_LEN
        i = 0
        while i <= end:
            if (
                buf[i] == 0xFF
                and buf[i + 1] == 0xFF
                and buf[i + 2] == sid
                and buf[i + 3] == _READ_LEN + 2
                and checksum(buf, i + 2, i + _REPLY_LEN - 1) == buf[i + _REPLY_LEN - 1]
            ):
                err = buf[i + 4]
                d = i + 5
                if self.big_endian:
                    steps = (buf[d] << 8) | buf[d + 1]
                    ld = (buf[d + 4] << 8) | buf[d + 5]
                else:
                    steps = buf[d] | (buf[d + 1] << 8)
                    ld = buf[d + 4] | (buf[d + 5] << 8)
                if steps & 0x8000:  # sign-magnitude (multi-turn modes)
                    steps = -(steps & 0x7FFF)
                self.pos[k] = ((steps - self.centre) * self.k_b + 128) >> 8
                self.load[k] = -(ld & 0x3FF) if ld & 0x400 else ld & 0x3FF
                self.voltage[k] = buf[d + 6]
                self.temperature[k] = buf[d + 7]
                self.err[k] = err
                if not self.seen[k]:
                    self.seen[k] = 1
                    known = True
                    for j in range(self.n):
                        if not self.seen[j]:
                            known = False
                    self.known = known
                if err & 0x28:
                    self.fault[k] = FAULT_OVERLOAD
                elif err:
                    self.fault[k] = FAULT_ERROR
                else:
                    self.fault[k] = FAULT_NONE
                return True
            i += 1
        return False
