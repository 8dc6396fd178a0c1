"""A neighbour that dies mid-frame (docs/firmware.md, "A neighbour that dies mid-frame"): the
frame it left half relayed upstream is ended within ``_RELAY_SILENCE_MS`` (3 ms), so the
segment's own STATEs are not held behind it, and an own frame is never dropped for it.

Defect (issue 14 audit): the limit was 50 ms and only one buffer of own frames could wait: after
the tip was unplugged mid-STATE, no own STATE left for 50 ms, then 7 at once, and cycles were
dropped (``events_lost``); every segment above relaying the same partial frame stalled likewise.
"""

from __future__ import annotations

from protocol import messages as M
from protocol.frame import FrameReader
from tests.device.conftest import frames

# a STATE from the downstream neighbour (position 0 below us: hop 0, UP)
_DOWN_STATE = M.encode_state(
    1, cycle=1, t_ms=1, kappa=0.5, phi=0.1, servo_angles=[0.1, -0.2, 0.3], status=0
)


def _syncs(n: int) -> list[str]:
    return [M.encode_sync(10 + i, 100 + i, [(0.5, 0.0)]).hex() for i in range(n)]


def _split(up_hex: str, offsets: list[int]) -> list[bytes]:
    up = bytes.fromhex(up_hex)
    bounds = [0, *offsets]
    return [up[a:b] for a, b in zip(bounds, bounds[1:], strict=False)]


def _states(chunk: bytes) -> list[int]:
    return [
        M.decode_message(f)["cycle"]
        for f in FrameReader().feed(chunk)
        if M.decode_message(f)["type"] == "STATE"
    ]


def test_a_neighbour_dead_mid_frame_delays_no_own_state(vm) -> None:
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.take()
hal.down.feed(bytes.fromhex('{_DOWN_STATE[:12].hex()}'))   # the tip unplugged mid-STATE
seg.poll()
R['busy'] = seg.rl_up.busy
ends = []
for h in {_syncs(20)}:                      # the host's SYNC every 5 ms, nothing from below
    hal.t += 5
    hal.up.feed(bytes.fromhex(h))
    seg.poll()
    seg.tick(hal.ticks_ms())
    ends.append(hal.up.ow)                 # where this cycle's output ends
R['ends'] = ends
R['up'] = vmkit.hexs(hal.up.take())
R['lost'] = seg.events_lost
R['poisoned'] = seg.rl_up.stats()['poisoned']
"""
    )
    assert r["busy"]  # the partial frame was being relayed
    chunks = _split(r["up"], r["ends"])
    # every cycle's STATE leaves in the cycle of its SYNC (old code: nothing for 50 ms)
    assert [_states(c) for c in chunks] == [[100 + i] for i in range(20)]
    assert r["lost"] == 0 and r["poisoned"] == 1
    rd = FrameReader()
    got = rd.feed(bytes.fromhex(r["up"]))
    # the dead frame was ended invalid, never passed on as good
    assert rd.stats()["framing_error"] == 1
    assert all(M.decode_message(f)["type"] in ("STATE", "EVENT") for f in got)
    assert not any(f.flags & 0x01 and f.hop == 1 and f.seq == 1 for f in got)


def test_own_frames_beyond_the_pending_buffer_cut_the_relayed_frame_and_lose_nothing(vm) -> None:
    """Ten SYNCs in the same millisecond while a relayed frame is half sent: 10 STATEs do not
    fit the 252-byte buffer; the relayed frame is ended instead of an own STATE being dropped,
    and when its sender turns out alive, the completed frame follows store-and-forward."""
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.take()
hal.down.feed(bytes.fromhex('{_DOWN_STATE[:12].hex()}'))
seg.poll()
for h in {_syncs(10)}:
    hal.up.feed(bytes.fromhex(h))
    seg.poll()                             # no time passes: no silence
R['up'] = vmkit.hexs(hal.up.take())
hal.down.feed(bytes.fromhex('{_DOWN_STATE[12:].hex()}'))   # the rest of the frame comes
seg.poll()
R['rest'] = vmkit.hexs(hal.up.take())
R['lost'] = seg.events_lost
"""
    )
    assert r["lost"] == 0
    assert _states(bytes.fromhex(r["up"])) == list(range(100, 110))
    fwd = frames(r["rest"])
    assert len(fwd) == 1 and fwd[0].hop == 1 and fwd[0].seq == 1  # store-and-forward, hop + 1
    assert M.decode_message(fwd[0])["cycle"] == 1


def test_a_live_sender_pausing_within_the_limit_stays_cut_through(vm) -> None:
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.take()
hal.down.feed(bytes.fromhex('{_DOWN_STATE[:12].hex()}'))
seg.poll()
hal.t += 3                                 # a relaying neighbour's longest pause, rounded up
seg.poll()
hal.down.feed(bytes.fromhex('{_DOWN_STATE[12:].hex()}'))
seg.poll()
R['up'] = vmkit.hexs(hal.up.take())
R['frames'] = seg.rl_up.stats()['frames']
R['poisoned'] = seg.rl_up.stats()['poisoned']
"""
    )
    assert (r["frames"], r["poisoned"]) == (1, 0)
    fwd = frames(r["up"])
    assert [(f.hop, f.seq) for f in fwd if f.flags & 0x01 and not f.flags & 0x04] == [(1, 1)]
