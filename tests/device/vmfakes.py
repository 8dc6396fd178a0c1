"""VM-side test doubles for the ESP32 servo drivers (kept out of vmkit to save test heap)."""

from vmkit import LoopHal, LoopPwm


class FakeFeetech:
    """A bus of Feetech servos on the other end of a UART (test double, VM side).

    Checks every packet's checksum (``bad`` counts failures), applies SYNC WRITE goal positions,
    answers READ of 8 bytes at 0x38 with position/load/voltage/temperature, echoes every written
    byte first (as a single-wire half-duplex adapter does). ``err[id]`` is the status error byte;
    ids in ``silent`` do not answer. ``big`` selects SCS byte order.
    """

    def __init__(self, ids, big=False, centre=2048):
        self.goal = {}
        self.pos = {}
        for i in ids:
            self.goal[i] = centre
            self.pos[i] = centre
        self.err = {}
        self.silent = set()
        self.big = big
        self.rx = bytearray()
        self.bad = 0
        self.reads = 0
        self.syncs = 0

    def _chk(self, pkt):
        return (~sum(pkt[2:-1])) & 0xFF

    def write(self, buf, n=-1):
        data = bytes(buf) if n < 0 else bytes(buf[:n])
        self.rx.extend(data)  # echo
        i = 0
        while i + 4 <= len(data):
            if data[i] != 0xFF or data[i + 1] != 0xFF:
                i += 1
                continue
            ln = data[i + 3]
            pkt = data[i : i + 4 + ln]
            i += 4 + ln
            if len(pkt) < 4 + ln or self._chk(pkt) != pkt[-1]:
                self.bad += 1
                continue
            sid, ins = pkt[2], pkt[4]
            if ins == 0x83 and sid == 0xFE:
                self.syncs += 1
                dlen = pkt[6]
                j = 7
                while j + 1 + dlen <= len(pkt) - 1:
                    tid = pkt[j]
                    lo, hi = (pkt[j + 2], pkt[j + 1]) if self.big else (pkt[j + 1], pkt[j + 2])
                    self.goal[tid] = lo | (hi << 8)
                    self.pos[tid] = self.goal[tid]
                    j += 1 + dlen
            elif ins == 0x02 and sid in self.pos and sid not in self.silent:
                self.reads += 1
                p = self.pos[sid]
                pb = [p >> 8, p & 0xFF] if self.big else [p & 0xFF, p >> 8]
                load = [0, 100] if self.big else [100, 0]  # 10 % load
                body = [sid, 10, self.err.get(sid, 0)] + pb + [0, 0] + load + [121, 35]
                self.rx.extend(bytes([0xFF, 0xFF] + body + [(~sum(body)) & 0xFF]))
        return len(data)

    def readinto(self, buf):
        n = min(len(buf), len(self.rx))
        if not n:
            return None
        buf[:n] = self.rx[:n]
        self.rx = self.rx[n:]
        return n


class BusHal(LoopHal):
    """LoopHal with a fake Feetech bus UART and fake PWM outputs."""

    def __init__(self, fake=None):
        LoopHal.__init__(self)
        self.fake = fake
        self.pwms = []

    def servo_uart(self, b):
        return self.fake

    def pwm(self, pin, freq):
        p = LoopPwm(pin, freq)
        self.pwms.append(p)
        return p
