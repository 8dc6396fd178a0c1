"""The floors a chain exchange is measured against (docs/protocol.md "Floors"), defined once.

One SYNC down and one STATE per segment up. 10 bits per byte (8N1), processing time excluded.

* line-rate floor: the bytes the exchange puts on link 0 (the SYNC plus every STATE) at the line
  rate. No chain can beat it; a cut-through chain with negligible per-hop latency reaches it.
* store-and-forward floor: every segment receives a whole frame (and checks its CRC) before it
  passes it on, so the SYNC crosses the n links one after the other and so does the farthest
  segment's STATE: n x (t_sync + t_state). What a store-and-forward chain cannot beat.
* cut-through floor: the protocol-v2 relay (protocol/relay.py) passes a frame on as it arrives and
  ends it RELAY_HOP_BYTES after its last byte arrived; the farthest STATE is complete at the host
  after SYNC + STATE + 2 (n - 1) hops of that, and never before the line-rate floor. What the
  current firmware can approach with zero processing time.

Benchmarks pass the frame sizes they measured; without sizes the largest frames the encoders
produce are used (what the daemon's rate warning needs: a bound for every value). Host-only:
it lives in host/ so that `ucr flash` does not put it on a board.
"""

from __future__ import annotations

from protocol import constants as C
from protocol import messages as M

BITS_PER_BYTE = 10  # UART 8N1: start + 8 data + stop
#: bytes a cut-through hop adds at a frame's end: the 3-byte hold-back and the delimiter
RELAY_HOP_BYTES = 4


def max_sync_bytes(n: int) -> int:
    """Wire bytes of the largest SYNC for ``n`` segments (COBS, CRC and delimiter included):
    the largest cycle number and the resume key (sent once when a HOLD ends)."""
    sps = [(C.SP_KAPPA_MAX / C.KAPPA_SCALE, -3.0)] * n
    return len(M.encode_sync(255, C.TIME_WRAP - 1, sps, resume=True))


def max_state_bytes(servos: int = 3) -> int:
    """Wire bytes of the largest STATE one segment with ``servos`` servos sends (COBS adds no
    byte to a frame under 254 bytes, so every STATE of that segment has this size)."""
    return len(
        M.encode_state(
            255,
            cycle=C.TIME_WRAP - 1,
            t_ms=C.TIME_WRAP - 1,
            kappa=3.0,
            phi=-3.0,
            servo_angles=[-3.0] * servos,
            status=0x3F,
        )
    )


def _sizes(n: int, sync_bytes: float | None, state_bytes: float | None) -> tuple[float, float]:
    sync = max_sync_bytes(n) if sync_bytes is None else sync_bytes
    state = max_state_bytes() if state_bytes is None else state_bytes
    return sync, state


def line_rate_floor_s(
    n: int, baudrate: int, sync_bytes: float | None = None, state_bytes: float | None = None
) -> float:
    """(SYNC + n x STATE) bytes x 10 / baud: the exchange's bytes on link 0 (s)."""
    if n <= 0:
        return 0.0
    sync, state = _sizes(n, sync_bytes, state_bytes)
    return (sync + n * state) * BITS_PER_BYTE / baudrate


def store_and_forward_floor_s(
    n: int, baudrate: int, sync_bytes: float | None = None, state_bytes: float | None = None
) -> float:
    """n x (SYNC + STATE) bytes x 10 / baud: whole frames forwarded hop by hop (s)."""
    if n <= 0:
        return 0.0
    sync, state = _sizes(n, sync_bytes, state_bytes)
    return n * (sync + state) * BITS_PER_BYTE / baudrate


def cut_through_floor_s(
    n: int, baudrate: int, sync_bytes: float | None = None, state_bytes: float | None = None
) -> float:
    """max(line-rate floor, (SYNC + STATE + 2 (n - 1) x RELAY_HOP_BYTES) x 10 / baud) (s)."""
    if n <= 0:
        return 0.0
    sync, state = _sizes(n, sync_bytes, state_bytes)
    hops = (sync + state + 2 * (n - 1) * RELAY_HOP_BYTES) * BITS_PER_BYTE / baudrate
    return max(line_rate_floor_s(n, baudrate, sync, state), hops)


def pipelined_rate_hz(
    n: int, baudrate: int, sync_bytes: float | None = None, state_bytes: float | None = None
) -> float:
    """Cycle-rate bound when cycles overlap: the busiest direction of link 0 decides (Hz)."""
    sync, state = _sizes(n, sync_bytes, state_bytes)
    return baudrate / BITS_PER_BYTE / max(sync, n * state)
