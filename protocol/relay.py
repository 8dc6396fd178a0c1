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

from protocol.crc import _TABLE

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


# The relay's state: one array 'i' the byte loop (machine code or its bytecode twin) works on.
# 0..5 the hold-back (run, held, h0, h1, h2, bytes so far), then:
_MODE = const(6)  # 0 collecting the first four wire bytes, 1 passing the frame on, 2 not relayed
_HEADN = const(7)  # head bytes collected (8..11: the head)
_HOP = const(12)  # the hop byte the relayed frame carries
_UPWARD = const(13)
_FRAMES = const(14)  # relayed with a good CRC
_POISONED = const(15)  # relayed frames ended invalid (bad input or a silence)
_BUSY = const(16)
# 17, 18: the bytecode twin's scratch (relay_py.relay's position and output length)
_RELAY = const(1)
_SKIP = const(2)
_ST_LEN = const(19)


class Relay:
    """One direction of cut-through forwarding. ``upward``: relay ``FLAG_UP`` frames (from the
    downstream port); otherwise broadcasts (from the upstream port).

    ``feed(data, start, end, ok, rd, out)`` takes the bytes ``FrameReader.scan`` just consumed
    (``ok``: it completed a good frame with the last of them) and writes what to send into
    ``out`` (room for ``end - start + 8`` bytes); returns that length. After it, ``relayed`` says
    whether the frame the reader handed out was passed on (then the caller must not forward it
    again). ``busy`` is true while a frame is half sent: the port carries nothing else then.
    The whole step is one call of ``_feed`` (machine code where the port has the viper emitter).
    """

    def __init__(self, upward):
        self.st = array("i", [0] * _ST_LEN)
        self.st[_UPWARD] = 1 if upward else 0
        self.relayed = 0
        self.busy = 0

    def stats(self):
        """Counters as a dict: frames relayed with a good CRC, relayed frames ended invalid.
        (No properties on this class: see ``FrameReader.stats``.)"""
        return {"frames": self.st[_FRAMES], "poisoned": self.st[_POISONED]}

    def feed(self, data, start, end, ok, rd, out):
        if start < 0 or end > len(data) or end - start + 8 > len(out) or end - start > 0xFF00:
            raise IndexError("relay range outside the buffers (or over 65280 bytes at once)")
        st = self.st
        r = _feed(data, start, end, out, st, ok, rd.raw, rd.raw_len, _TABLE)
        self.relayed = r & 0x10000
        self.busy = st[_BUSY]
        return r & 0xFFFF

    def abort(self, out):
        """A silence inside a relayed frame: end it invalid now; return the bytes to send."""
        st = self.st
        if st[_MODE] != _RELAY:
            return 0
        st[_MODE] = _SKIP
        st[_BUSY] = 0
        self.busy = 0
        o = 0
        if st[0] == 0:  # at a code position: a code claiming 4 more bytes first
            out[0] = 5
            o = 1
        out[o] = 0  # inside a run: the delimiter comes too early
        st[_POISONED] += 1
        return o + 1


# The step in machine code on MicroPython ports with the viper emitter (protocol/_fast.py); its
# bytecode twin (protocol/relay_py.py) is compiled only where there is no emitter (CPython too).
try:
    from protocol._fast import relay_feed as _feed
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    from protocol.relay_py import feed as _feed
