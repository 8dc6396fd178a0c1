"""Cut-through forwarding (docs/protocol.md section 6, "Cut-through"): a segment passes a frame on
while it arrives instead of after its last byte, and the receiving end still checks the CRC.

Why it stays correct and checked: COBS maps raw byte k to wire byte k + 1 (frames < 254 bytes),
so changing the hop byte (raw 2) changes wire byte 3 only, and version 2's 0x00 pad before the CRC
makes the CRC's COBS form always the last three wire bytes. A relay therefore passes the wire bytes
on as they come, with the hop byte replaced (hop 0 -> 1 merges the first two COBS runs: both codes
are among the first four bytes, which it holds), and holds back the last three bytes it has seen.
At the delimiter the frame reader beside it (``FrameReader``, same bytes) has checked the frame:

* good: the relay sends the CRC of the frame *with the new hop* (computed over the reader's
  decoded copy), so every hop's CRC covers the hop byte;
* bad (CRC, COBS, pad, runt, oversize, or a silence inside it): the relay ends the frame so that
  it is invalid COBS (a run that points past the end), which every receiver drops as a framing
  error. No receiver executes or accepts a frame its sender's relay did not verify.

Relayed: version-2 broadcasts from upstream (``FLAG_BCAST`` without ``UP``/``LOCAL``) downstream,
and version-2 ``FLAG_UP`` frames from downstream upstream. Everything else (addressed requests,
link-local frames, other versions) is store-and-forward as before (``frame.forward_into``).
Nothing here allocates; the byte loop is viper machine code where the port has the emitter.
"""

from array import array

from protocol.constants import (
    FLAG_BCAST,
    FLAG_LOCAL,
    FLAG_UP,
    FLAGS_KNOWN,
    MAX_ENCODED,
    MIN_FRAME,
    VERSION,
)
from protocol.crc import crc16

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


_HEAD = const(0)  # collecting the first four wire bytes
_RELAY = const(1)  # passing the frame on
_SKIP = const(2)  # not relayed: wait for the delimiter


class Relay:
    """One direction of cut-through forwarding. ``upward``: relay ``FLAG_UP`` frames (from the
    downstream port); otherwise broadcasts (from the upstream port).

    ``feed(data, start, end, ok, rd, out)`` takes the bytes ``FrameReader.scan`` just consumed
    (``ok``: it completed a good frame with the last of them) and writes what to send into
    ``out`` (room for ``end - start + 8`` bytes); returns that length. After it, ``relayed`` says
    whether the frame the reader handed out was passed on (then the caller must not forward it
    again). ``busy`` is True while a frame is half sent: the port carries nothing else then.
    """

    def __init__(self, upward):
        self.upward = upward
        self.mode = _HEAD
        self.n = 0
        self.head = bytearray(4)
        self.hop = 0  # the hop byte the relayed frame carries
        self.st = array("i", [0, 0, 0, 0, 0, 0])
        self.relayed = False
        self.busy = False
        self.frames = 0  # relayed with a good CRC
        self.poisoned = 0  # relayed frames ended invalid (bad input or a silence)

    def feed(self, data, start, end, ok, rd, out):
        self.relayed = False
        o = 0
        i = start
        st = self.st
        while i < end:
            if self.mode == _RELAY:
                r = _relay(data, i, end, out, o, st)
                i = r >> 10
                o = r & 0x1FF
                if r & 0x200:
                    o = self._finish(out, o, ok and i == end, rd)
                elif st[5] > MAX_ENCODED:
                    o = self._poison(out, o)
                    self.mode = _SKIP
                continue
            b = data[i]
            i += 1
            if b == 0:
                self.mode = _HEAD
                self.n = 0
                continue
            if self.mode == _HEAD:
                self.head[self.n] = b
                self.n += 1
                if self.n == 4:
                    o = self._start(out, o)
        return o

    def _start(self, out, o):
        """Decide from the first four wire bytes whether to relay; if so, send them."""
        h = self.head
        c0 = h[0]
        self.mode = _SKIP
        if c0 < 3 or h[1] != VERSION:
            return o  # a zero in ver/flags, or another version: not relayed
        flags = h[2]
        if flags & ~FLAGS_KNOWN & 0xFF or flags & FLAG_LOCAL:
            return o
        if self.upward:
            if not flags & FLAG_UP:
                return o
        elif flags & FLAG_UP or not flags & FLAG_BCAST:
            return o
        if c0 == 3:  # hop 0: raw 2 is a zero, head[3] is the code of the run after it
            c3 = h[3]
            if c3 > 251:
                return o
            out[o] = c3 + 3  # the runs (ver, flags) and (hop, ...) merge into one
            run = c3 - 1
            self.hop = 1
        else:
            if h[3] == 255:
                return o  # the hop would wrap to 0 (no chain is that long)
            out[o] = c0
            run = c0 - 4
            self.hop = h[3] + 1
        out[o + 1] = h[1]
        out[o + 2] = flags
        out[o + 3] = self.hop
        st = self.st
        st[0] = run
        st[1] = 0
        st[5] = 4
        self.mode = _RELAY
        self.busy = True
        return o + 4

    def _finish(self, out, o, good, rd):
        """The delimiter: the CRC for the new hop if the reader accepted the frame, else poison."""
        st = self.st
        self.mode = _HEAD
        self.n = 0
        self.busy = False
        if (
            good
            and st[1] == 3
            and st[0] == 0
            and rd.raw_len >= MIN_FRAME
            and (rd.hop + 1) & 0xFF == self.hop
        ):
            raw = rd.raw
            p = rd.raw_len - 2
            raw[2] = self.hop
            c = crc16(raw, 0, p)
            raw[2] = self.hop - 1
            hi = c >> 8
            lo = c & 0xFF
            if hi and lo:
                out[o] = 3
                out[o + 1] = hi
                out[o + 2] = lo
            elif hi:
                out[o] = 2
                out[o + 1] = hi
                out[o + 2] = 1
            elif lo:
                out[o] = 1
                out[o + 1] = 2
                out[o + 2] = lo
            else:
                out[o] = 1
                out[o + 1] = 1
                out[o + 2] = 1
            out[o + 3] = 0
            self.relayed = True
            self.frames += 1
            return o + 4
        return self._end_invalid(out, o)

    def _poison(self, out, o):
        self.busy = False
        return self._end_invalid(out, o)

    def _end_invalid(self, out, o):
        """End what was sent so far as invalid COBS: inside a run the delimiter comes too early;
        at a code position a code claiming 4 more bytes is sent first."""
        if self.st[0] == 0:
            out[o] = 5
            o += 1
        out[o] = 0
        self.poisoned += 1
        return o + 1

    def abort(self, out):
        """A silence inside a relayed frame: end it invalid now; return the bytes to send."""
        if self.mode != _RELAY:
            return 0
        self.mode = _SKIP
        return self._poison(out, 0)


# Machine-code byte loop on MicroPython ports with the viper emitter (protocol/_fast.py); its
# bytecode twin (protocol/relay_py.py) is compiled only where there is no emitter (CPython too).
try:
    from protocol._fast import relay as _relay
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    from protocol.relay_py import relay as _relay
