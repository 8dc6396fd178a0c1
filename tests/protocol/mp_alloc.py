"""Zero-allocation checks, run on the MicroPython VM only (micropython.heap_lock()).

Each check runs once unlocked (warm-up: first-call caches, attribute dicts) and then many times
with the heap locked; any allocation raises MemoryError. ``main()`` prints one line per check:
``<name> ok`` or ``<name> ALLOC <error>``.
"""

import gc

import micropython

from protocol import cobs, crc
from protocol import device as D
from protocol import frame as F

gc.collect()  # compiling messages.py next needs large blocks: start it on a tidy heap
from protocol import messages as M  # noqa: E402
from protocol.constants import FLAG_UP, HEADER_LEN, MAX_ENCODED, MAX_FRAME  # noqa: E402

# --- preallocated state, as the firmware would hold it ---------------------------------------
reader = F.FrameReader()
raw_tx = bytearray(MAX_FRAME)
wire_tx = bytearray(MAX_ENCODED)
fwd_out = bytearray(MAX_ENCODED)
sync_out = [0, 0, 0, 0]
servos = [-3500, 2100, 1400, 0]
counter = [0]

# a received byte stream: 8-segment SYNC, HEARTBEAT, upstream STATE, garbage, EVENT
_sync8 = M.encode_sync(5, 1000, [(0.5 * i, -3.0 + 0.8 * i) for i in range(8)])
_hb = M.encode_heartbeat(6, 1001)
_state = M.encode_state(
    7,
    cycle=1000,
    t_ms=5,
    kappa=2.5,
    phi=0.3,
    servo_angles=[0.1, 0.2, 0.3],
    status=16,
)
_event = M.encode_event(8, 6, 3, 77)
STREAM = bytearray(b"\x00" + _sync8 + _hb + b"\x13\x37garbage\x00" + _state + _event + _sync8)
N_STREAM = len(STREAM)


def rx_cycle():
    """(a) scan a whole stream, (b) decode SYNC/HEARTBEAT in place, (d) forward every frame."""
    pos = 0
    while pos < N_STREAM:
        pos = reader.scan(STREAM, pos, N_STREAM)
        if reader.ready:
            t = reader.mtype
            if t == 0x02:
                D.decode_sync(reader.raw, HEADER_LEN, reader.payload_end, 2, sync_out)
            elif t == 0x03:
                D.decode_cycle(reader.raw, HEADER_LEN, reader.payload_end)
            r = D.route(reader.flags, reader.hop)
            if r & 3:
                F.forward_into(
                    reader.raw, reader.raw_len, D.next_hop(reader.flags, reader.hop), fwd_out, 0
                )
            counter[0] += 1


def scan_only():
    """(a) the frame reader alone."""
    pos = 0
    while pos < N_STREAM:
        pos = reader.scan(STREAM, pos, N_STREAM)


_rx = F.FrameReader()
_rx.feed(bytes(_sync8))  # leaves the SYNC frame decoded in _rx.raw
_rx.scan(_sync8, 0, len(_sync8))
SYNC_END = _rx.payload_end


def decode_sync8():
    """(b) decode this segment's entry of an 8-segment SYNC, for every position."""
    for p in range(9):
        D.decode_sync(_rx.raw, HEADER_LEN, SYNC_END, p, sync_out)


def tx_state():
    """(c) encode a STATE report and frame it (COBS + CRC + delimiter)."""
    D.state_frame(raw_tx, wire_tx, 9, 1000, 123456, 25000, 7854, servos, 4, 0x10, 2)


def tx_state_parts():
    """(c) the same via encode_state + frame_into (what a firmware may call separately)."""
    end = D.encode_state(raw_tx, HEADER_LEN, 1000, 123456, 25000, 7854, servos, 3, 0x10, 2)
    F.frame_into(raw_tx, end, FLAG_UP, 0, 0x83, 9, wire_tx, 0)


_fwd_raw = bytearray(F.decode_frame(_state).raw())
_fwd_len = len(_fwd_raw)


def forward():
    """(d) re-frame a received upstream frame with hop + 1."""
    F.forward_into(_fwd_raw, _fwd_len, 1, fwd_out, 0)


def tx_small():
    """EVENT and ALIVE frames, and the raw CRC/COBS primitives."""
    D.event_frame(raw_tx, wire_tx, 1, 6, 3, 5000)
    D.alive_frame(raw_tx, wire_tx, 2)
    crc.crc16(raw_tx, 0, 100)
    n = cobs.encode_into(raw_tx, 0, 100, wire_tx, 0)
    cobs.decode_into(wire_tx, 0, n, fwd_out, 0)


def malformed():
    """Malformed payloads are rejected by return code, also without allocating."""
    D.decode_sync(STREAM, 0, N_STREAM, 1, sync_out)
    D.decode_cycle(STREAM, 3, 40)
    D.decode_empty(STREAM, 5, 30)


def control_allocates():
    """Negative control: a bytes slice allocates, so the harness can detect allocation."""
    return bytes(STREAM[0:10])


CHECKS = (
    ("rx_cycle", rx_cycle),
    ("scan_only", scan_only),
    ("decode_sync8", decode_sync8),
    ("tx_state", tx_state),
    ("tx_state_parts", tx_state_parts),
    ("forward", forward),
    ("tx_small", tx_small),
    ("malformed", malformed),
    ("control_allocates", control_allocates),
)


def main(repeat=20, pure=False):
    from mp_runner import fast_loops_active, use_pure_loops

    if pure:  # the pure-Python loops must not allocate either
        use_pure_loops()
    print("fast", fast_loops_active())
    for name, fn in CHECKS:
        fn()  # warm up
        err = None
        micropython.heap_lock()
        try:
            for _ in range(repeat):
                fn()
        except MemoryError as e:
            err = e
        micropython.heap_unlock()
        if err is None:
            print(name, "ok")
        else:
            print(name, "ALLOC", err)
    s = reader.stats()
    print("frames", counter[0], s["ok"], s["crc_error"], s["framing_error"])
