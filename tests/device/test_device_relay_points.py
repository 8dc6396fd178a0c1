"""Forwarding inside a tick (docs/firmware.md, "Forwarding inside a tick"): bytes that arrive
while a segment computes its control tick are passed on between the tick's phases, not after it,
and a frame completed there is handled only after the tick, by the next poll.

On a board a tick takes milliseconds (docs/firmware.md, "Memory": the ESP32 timing model), so a
SYNC that waited for the tick's end waited that long at every hop."""

from __future__ import annotations

from protocol import messages as M
from protocol.constants import FLAG_BCAST, FLAG_UP
from protocol.frame import encode_frame
from tests.device.conftest import decode, frames

_SPS = [(0.1, 0.0), (1.5, -2.0), (0.4, 0.0)]


def _sync(seq, cycle, hop=0):
    return encode_frame(FLAG_BCAST, hop, 0x02, seq, M.sync_payload(cycle, _SPS))


def test_a_sync_arriving_during_a_tick_is_relayed_before_the_servos_are_commanded(vm):
    sync = _sync(77, 9, hop=1)
    warm = [_sync(i, i, hop=1).hex() for i in range(4)]
    r = vm(
        f"""
hal, seg = vmkit.make()
held = lambda: list(getattr(seg, 'held', b''))  # (absent before relay points existed)
for h in {warm}:                           # booted and moving under SYNCs
    hal.up.feed(bytes.fromhex(h))
    vmkit.run(hal, seg, 5)
R['moving'] = seg.moving
hal.up.take(); hal.down.take()
bus = seg.bus
seen = []
real_command = bus.command
def command(targets, now):
    seen.append(hal.down.ow)               # bytes relayed downstream when the servos are commanded
    return real_command(targets, now)
bus.command = command
hal.up.feed(bytes.fromhex('{sync.hex()}'))  # arrives while the segment is in its tick: no poll
hal.t += 5
seg.tick(hal.ticks_ms())
R['during'] = [vmkit.hexs(hal.down.take()), vmkit.hexs(hal.up.take()), seen, held()]
R['position_before_poll'] = seg.position
seg.poll()                                 # the frame is handled after the tick
R['after'] = [vmkit.hexs(hal.up.take()), vmkit.hexs(hal.down.take()), held(),
              seg.position]
"""
    )
    assert r["moving"]
    down, up, seen, held = r["during"]
    fwd = frames(down)
    assert len(fwd) == 1 and (fwd[0].flags, fwd[0].hop, fwd[0].seq) == (FLAG_BCAST, 2, 77)
    assert seen and seen[0] == len(bytes.fromhex(down))  # relayed before the command went out
    assert held == [1, 0]  # complete, and held for the poll
    assert [m for m in decode(up) if m["type"] == "STATE"] == []  # not handled in the tick
    assert r["position_before_poll"] == 1  # (from the earlier SYNCs)
    up, down, held, position = r["after"]
    states = [m for m in decode(up) if m["type"] == "STATE"]
    assert [(s["seq"], s["cycle"]) for s in states] == [(77, 9)]
    assert down == "" and held == [0, 0] and position == 1  # relayed once, handled once


def test_frames_after_a_held_one_are_kept_and_handled_in_order(vm):
    """Two SYNCs in one read and a neighbour's STATE: the first SYNC completes at a relay point
    and is held; the bytes after it wait in the receive buffer, nothing is lost or reordered."""
    a, b = _sync(1, 100), _sync(2, 101)
    state = M.encode_state(
        1, cycle=100, t_ms=5, kappa=0.0, phi=0.0, servo_angles=[0.0] * 3, status=0
    )
    r = vm(
        f"""
hal, seg = vmkit.make()
held = lambda: list(getattr(seg, 'held', b''))  # (absent before relay points existed)
vmkit.run(hal, seg, 20)
hal.up.take(); hal.down.take()
hal.up.feed(bytes.fromhex('{(a + b).hex()}'))
hal.down.feed(bytes.fromhex('{state.hex()}'))
hal.t += 5
seg.tick(hal.ticks_ms())
R['tick'] = [vmkit.hexs(hal.down.take()), vmkit.hexs(hal.up.take()), held()]
seg.poll()
R['poll'] = [vmkit.hexs(hal.down.take()), vmkit.hexs(hal.up.take()), held(),
             list(getattr(seg, 'keep', b''))]
"""
    )
    down, up, held = r["tick"]
    assert [f.seq for f in frames(down)] == [1]  # the first relayed; the second waits behind it
    # the host's frame is held; the neighbour's STATE was relayed upward in the tick (hop + 1)
    # and handled there (it changes no control state); ours waits for the poll
    assert held == [1, 0]
    assert [(m["seq"], m["hop"]) for m in decode(up) if m["type"] == "STATE"] == [(1, 1)]
    down, up, held, keep = r["poll"]
    assert [f.seq for f in frames(down)] == [2]
    got = [(m["seq"], m["hop"]) for m in decode(up) if m["type"] == "STATE"]
    assert got == [(1, 0), (2, 0)]  # ours, for SYNC 1 then SYNC 2
    assert all(f.flags & FLAG_UP for f in frames(up))
    assert held == [0, 0] and keep == [0, 0, 0, 0]


def test_the_main_loop_handles_a_frame_held_in_the_tick_before_it_waits(vm):
    """The frame's bytes were read at the relay point, so no input would end the wait early:
    the loop handles it right after the tick (else its STATE would leave up to a tick late)."""
    warm = [_sync(i, i, hop=1).hex() for i in range(4)]
    sync = _sync(77, 9, hop=1)
    r = vm(
        f"""
import main
hal, seg = vmkit.make()
held = lambda: list(getattr(seg, 'held', b''))
for h in {warm}:
    hal.up.feed(bytes.fromhex(h))
    vmkit.run(hal, seg, 5)
hal.up.take(); hal.down.take()
runner = main.Runner(hal, seg, 5)
bus = seg.bus
real_poll = bus.poll
def arriving(now):                         # the SYNC arrives while the tick reads the servos
    real_poll(now)
    if not R.get('fed'):
        R['fed'] = True
        hal.up.feed(bytes.fromhex('{sync.hex()}'))
bus.poll = arriving
hal.t += 5
runner.next_t = hal.t
wait = runner.once()
R['after_once'] = [vmkit.hexs(hal.up.take()), vmkit.hexs(hal.down.take()), held(), wait]
"""
    )
    up, down, held_now, wait = r["after_once"]
    assert [f.seq for f in frames(down)] == [77]  # relayed in the tick
    states = [(m["seq"], m["cycle"]) for m in decode(up) if m["type"] == "STATE"]
    assert states == [(77, 9)], states  # and answered before the loop waits
    assert held_now == [0, 0]
