"""Fault lifecycle on the MicroPython VM (issue 11, finding 3): an exception inside the loop puts
the segment in FAULT through the real ``main.Runner``: servos hold (or are released), the host gets
an EVENT FAULT with code and reason and the FAULT status bit, counters count; only CLEAR_FAULT
leaves it (for HOLD), and the optional hardware watchdog resets a hung segment, whose next boot
reports WDT_RESET."""

from __future__ import annotations

import os
import pty
import subprocess
import time
import tty
from pathlib import Path

import pytest

from protocol import messages as M
from protocol.constants import (
    ERR_BAD_VALUE,
    FAULT_TICK,
    FAULT_WDT_RESET,
    ST_FAULT,
    ST_HOLD,
)
from protocol.frame import FrameReader
from tests.device.conftest import decode
from tools import mpvm
from tools.emulator.chain import populate_segment_dir

SYNC = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
RESUME = M.encode_sync(3, 3, [(3.0, 0.3)], resume=True).hex()
RAISE = M.encode_param_set(2, 0, 5, "0:raise").hex()
NONE = M.encode_param_set(4, 0, 5, "none").hex()
CLEAR = M.encode_clear_fault(5).hex()
GET_COUNT = M.encode_param_get(6, 0, 21).hex()
GET_FAULT = M.encode_param_get(7, 0, 20).hex()

# the real main loop (main.Runner) on the loopback HAL, 5 ms per pass
RUNNER = """
from main import Runner
def loop(hal, r, ms):
    end = hal.t + ms
    while hal.t < end:
        hal.t += 5
        r.once()
"""


def _events(msgs, name):
    return [m for m in msgs if m["type"] == "EVENT" and m["name"] == name]


def test_tick_exception_enters_fault_holds_reports_and_only_clear_fault_leaves_it(vm):
    r = vm(
        RUNNER
        + f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
r = Runner(hal, seg, 5)
hal.up.feed(bytes.fromhex('{SYNC}'))
loop(hal, r, 100)
hal.up.discard()
hal.up.feed(bytes.fromhex('{RAISE}'))
loop(hal, r, 200)
pos = list(seg.bus.true_pos)
hal.up.feed(bytes.fromhex('{SYNC}'))
loop(hal, r, 20)
hal.up.feed(bytes.fromhex('{GET_COUNT}'))
hal.up.feed(bytes.fromhex('{GET_FAULT}'))
loop(hal, r, 20)
R['fault'] = [seg.status(), pos, list(seg.bus.true_pos), vmkit.hexs(hal.up.take())]
hal.up.feed(bytes.fromhex('{NONE}'))   # the cause is gone ...
loop(hal, r, 50)
for _ in range(4):                    # ... but a resume does not leave FAULT
    hal.up.feed(bytes.fromhex('{RESUME}'))
    loop(hal, r, 50)
R['still'] = [seg.status(), list(seg.bus.true_pos), vmkit.hexs(hal.up.take())]
hal.up.feed(bytes.fromhex('{CLEAR}'))
loop(hal, r, 60)
R['cleared'] = [seg.status(), vmkit.hexs(hal.up.take())]
for _ in range(30):
    hal.up.feed(bytes.fromhex('{RESUME}'))
    loop(hal, r, 50)
    hal.up.discard()
R['moving'] = [seg.status(), seg.mc.kappa]
"""
    )
    status, pos, later, out = r["fault"]
    msgs = decode(out)
    faults = _events(msgs, "FAULT")
    assert len(faults) == 1 and faults[0]["detail"] == FAULT_TICK
    assert "tick: RuntimeError" in faults[0]["text"] and "injected" in faults[0]["text"]
    assert status & (ST_FAULT | ST_HOLD) == ST_FAULT | ST_HOLD
    assert pos == later  # servos held
    states = [m for m in msgs if m["type"] == "STATE"]
    assert states and "FAULT" in states[-1]["status"] and "HOLD" in states[-1]["status"]
    values = {m["param_id"]: m["value"] for m in msgs if m["type"] == "PARAM_VALUE"}
    assert values[21] >= 20  # every failing tick counted (40 ticks)
    assert values[20].startswith("TICK_EXCEPTION: tick: RuntimeError")
    status, still_pos, out = r["still"]
    assert status & ST_FAULT and still_pos == pos
    assert not _events(decode(out), "FAULT_CLEARED")
    status, out = r["cleared"]
    msgs = decode(out)
    assert [e["detail"] for e in _events(msgs, "FAULT_CLEARED")] == [FAULT_TICK]
    assert status & ST_FAULT == 0 and status & ST_HOLD  # FAULT -> HOLD
    status, kappa = r["moving"]
    assert status & (ST_FAULT | ST_HOLD) == 0 and abs(kappa - 30000) <= 40


def test_frame_exception_enters_fault_too(vm):
    r = vm(
        RUNNER
        + f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
r = Runner(hal, seg, 5)
def boom(rd):
    raise ValueError('injected frame handler failure')
seg._on_up = boom
hal.up.feed(bytes.fromhex('{SYNC}'))
loop(hal, r, 60)
R['s'] = [seg.status(), seg.fault_code, vmkit.hexs(hal.up.take())]
"""
    )
    status, code, out = r["s"]
    ev = _events(decode(out), "FAULT")
    assert status & ST_FAULT and code == 2 and ev and ev[0]["text"].startswith("frame: ValueError")


def test_fault_action_release_stops_driving_the_servos(vm):
    r = vm(
        RUNNER
        + f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000, 'fault_action': 'release'}})
r = Runner(hal, seg, 5)
hal.up.feed(bytes.fromhex('{SYNC}'))
loop(hal, r, 100)
R['before'] = seg.bus.enabled
hal.up.feed(bytes.fromhex('{RAISE}'))
loop(hal, r, 50)
R['after'] = [seg.bus.enabled, seg.status()]
"""
    )
    assert r["before"] is True
    enabled, status = r["after"]
    assert enabled is False and status & ST_FAULT


def test_clear_fault_checks_identity_and_malformed_requests(vm):
    wrong = M.encode_clear_fault(8, 0, uid="ffffffffffff").hex()
    r = vm(
        RUNNER
        + f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
r = Runner(hal, seg, 5)
seg.enter_fault(1, 'test')
hal.up.feed(bytes.fromhex('{wrong}'))
loop(hal, r, 20)
R['s'] = [seg.fault_code, vmkit.hexs(hal.up.take())]
"""
    )
    code, out = r["s"]
    errs = [m for m in decode(out) if m["type"] == "ERROR"]
    assert code == 1 and errs and errs[0]["name"] == "IDENTITY_MISMATCH"
    assert ERR_BAD_VALUE != errs[0]["code"]


# ---- hardware watchdog, on the real firmware process (unix port, emulated machine.WDT) ----------
def _read(fd: int, seconds: float) -> bytes:
    import select

    out = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], 0.02)
        if ready:
            try:
                out += os.read(fd, 4096)
            except OSError:
                break
    return out


def _start(seg: Path, up_slave: str):
    env = dict(os.environ, UCR_UP_PORT=up_slave, UCR_UID="C0FFEE0000AA")
    env["MICROPYPATH"] = f".frozen:{seg}"
    return subprocess.Popen(
        [mpvm.micropython_binary(), "-X", "heapsize=160k", "main.py"],
        cwd=seg,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )


def _until(fd: int, pred, seconds: float) -> list[dict]:
    msgs: list[dict] = []
    reader = FrameReader()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        msgs += [M.decode_message(f) for f in reader.feed(_read(fd, 0.1))]
        if pred(msgs):
            break
    return msgs


def test_hardware_watchdog_resets_a_hung_segment_and_the_next_boot_reports_wdt_reset(tmp_path):
    try:
        mpvm.micropython_binary()
    except FileNotFoundError as e:
        pytest.skip(str(e))
    seg = tmp_path / "seg"
    # the segment's flash as `ucr flash` writes it (precompiled modules): a boot from source
    # files is bounded by the compiler's peak on the 160 KB heap, not by the firmware
    populate_segment_dir(seg, config={"hw_watchdog_ms": 300, "watchdog_ms": 60000})
    m, s = pty.openpty()
    tty.setraw(m)
    procs = []
    try:
        proc = _start(seg, os.ttyname(s))
        procs.append(proc)
        hb = M.encode_heartbeat(1, 1)
        msgs = _until(
            m, lambda ms: any(x["type"] == "STATE" for x in ms) or not os.write(m, hb), 20
        )
        assert any(x["type"] == "STATE" for x in msgs), "segment did not answer"
        # a healthy loop keeps feeding the watchdog: still alive well past its timeout
        time.sleep(1.0)
        assert proc.poll() is None
        os.write(m, M.encode_param_set(2, 0, 5, "0:hang"))  # the next tick hangs for good
        proc.wait(timeout=30)  # the watchdog resets (kills) it
        assert (seg / "wdt_reset").exists()
        # the board boots again (the emulator restarts it): FAULT WDT_RESET, servos held
        proc = _start(seg, os.ttyname(s))
        procs.append(proc)

        def seen(ms):
            os.write(m, hb)
            return any(x["type"] == "EVENT" and x["name"] == "FAULT" for x in ms) and any(
                x["type"] == "STATE" for x in ms
            )

        msgs = _until(m, seen, 20)
        ev = [x for x in msgs if x["type"] == "EVENT" and x["name"] == "FAULT"]
        assert ev and ev[0]["detail"] == FAULT_WDT_RESET and "watchdog" in ev[0]["text"]
        st = [x for x in msgs if x["type"] == "STATE"]
        assert st and {"FAULT", "HOLD"} <= st[-1]["status"]
        assert not (seg / "wdt_reset").exists()  # the reset cause is read once
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait(timeout=5)
        os.close(m)
        os.close(s)


def test_the_hardware_watchdog_is_fed_only_by_clean_ticks(vm):
    """A pass that only handled frames fed the watchdog, so a tick raising every time (frames
    arriving between ticks, as from a 200 Hz host) fed it 199 times in 200 ticks and the chip
    never reset. Healthy = the pass ran the tick to its end and raised nothing."""
    sync = M.encode_sync(1, 1, [(0.0, 0.0)]).hex()
    r = vm(
        f"""
import main
class Dog:
    def __init__(self):
        self.n = 0
    def feed(self):
        self.n += 1
def drive(faults):
    hal, seg = vmkit.make({{'watchdog_ms': 60000}})
    dog = Dog()
    run = main.Runner(hal, seg, 5, dog)
    if faults:
        seg.bus.set_faults(faults)
    for k in range(100):
        hal.t += 5
        run.once()                  # the tick
        hal.up.feed(bytes.fromhex('{sync}'))
        run.once()                  # a frame before the next tick is due
        hal.up.discard()
    return [dog.n, seg.fault_count]
R['ok'] = drive(None)
R['raising'] = drive('0:raise')
import config
try:
    config.Config({{'hw_watchdog_ms': 100, 'tick_ms': 50, 'watchdog_ms': 200}})
    R['slow'] = None
except ValueError as e:
    R['slow'] = str(e)
""",
        heap="4m",  # two segments in one VM
    )
    feeds, faults = r["ok"]
    # once per clean tick (100, and the first pass's catch-up tick), not once per pass (200)
    assert faults == 0 and feeds in (100, 101), feeds
    feeds, faults = r["raising"]
    assert faults >= 100 and feeds == 0
    # fed once per tick, so the timeout must span a few ticks: config.json refuses less
    assert r["slow"] and "shorter than four ticks" in r["slow"]


def test_main_uses_the_protocol_fault_codes():
    """main.py keeps plain ints (a lighter boot); they must be the wire's FAULT codes."""
    import ast

    from protocol import constants as C

    tree = ast.parse((mpvm.REPO / "device" / "main.py").read_text())
    found = {
        t.id: node.value.value
        for node in tree.body
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant)
        for t in node.targets
        if isinstance(t, ast.Name) and t.id.startswith("FAULT_")
    }
    assert found == {
        "FAULT_TICK": C.FAULT_TICK,
        "FAULT_FRAME": C.FAULT_FRAME,
        "FAULT_WDT_RESET": C.FAULT_WDT_RESET,
    }
