"""Safety defects of the firmware found by the 2026-11-28 review, each on the real firmware:

* A: Ctrl-C ends the loop (the REPL takes over, ``ucr flash``): servos in their safe state and a
  hardware watchdog kept fed by a timer (the flash itself: tests/tools/test_flash_watchdog.py);
* B: PWM servos released in FAULT are assumed at their rest pose again (first-motion rule);
* C: a missing config.json is refused like an invalid one (never built-in defaults);
* D: ALIVE payloads are validated like DISCOVER's (MALFORMED, counted in ``dropped``);
* E: ``overruns`` counts ticks that started a whole tick period (or more) late.

docs/firmware.md "Fault injection" lists them.
"""

from __future__ import annotations

import sys
import time
import types
from pathlib import Path

import pytest

from protocol import messages as M
from protocol.frame import encode_frame
from tests.device.conftest import decode

DEVICE = Path(__file__).resolve().parents[2] / "device"
PWM_CFG = "{'servo_driver': 'pwm', 'fault_action': '%s', 'watchdog_ms': 60000%s}"


# -- A: Ctrl-C -----------------------------------------------------------------------------------
_RUN = """
import main, wdt
hal, seg = vmkit.make(%s)
class Dog:
    feeds = 0
    def feed(self):
        Dog.feeds += 1
class Timer:
    PERIODIC = 1
    def __init__(self, tid):
        R['timer_id'] = tid
    def init(self, mode=0, period=0, callback=None):
        R['timer'] = [mode, period]
        self.cb = callback
    def deinit(self):
        R['deinit'] = True
class Machine:
    def Timer(self, tid):
        t = Timer(tid)
        R['t'] = t
        return t
hal.machine = Machine()
main.build = lambda tick_ms=None: (hal, seg)
wdt.make = lambda ms: Dog()
wdt.reset_by_watchdog = lambda: False
SYNC = bytes.fromhex('%s')
passes = [0]
def wait(ms):
    hal.t += ms
    passes[0] += 1
    if passes[0] %% 5 == 0:
        hal.up.feed(SYNC)
    if passes[0] == 300:
        R['moving'] = seg.moving
        R['pulses'] = [p.ns for p in seg.bus.pwm]
        raise KeyboardInterrupt
hal.wait = wait
try:
    main.run()
except KeyboardInterrupt:
    R['interrupt'] = True
R['after'] = [p.ns for p in seg.bus.pwm]
R['hold'] = seg.hold
R['still_moving'] = seg.moving
R['feeds_by_loop'] = Dog.feeds
t = R.pop('t', None)
if t is not None:
    for _ in range(3):
        t.cb(t)
R['feeds_by_timer'] = Dog.feeds - R['feeds_by_loop']
"""


@pytest.mark.parametrize("action", ["hold", "release"])
def test_ctrl_c_leaves_the_servos_safe_and_keeps_the_hardware_watchdog_fed(vm, action):
    """Ctrl-C (mpremote, ``ucr flash``) ended main.run and nothing fed the machine.WDT, which
    cannot be stopped: the board reset in the REPL, mid-flash (review A). Now the servos are put
    in their fault_action state and a periodic machine.Timer feeds the watchdog."""
    sync = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
    cfg = PWM_CFG % (action, ", 'hw_watchdog_ms': 300")
    r = vm(_RUN % (cfg, sync), heap="4m")  # main.py compiled from source beside a segment
    assert r["interrupt"] and r["moving"]  # it was bending when Ctrl-C came
    assert all(p > 0 for p in r["pulses"])
    assert r["feeds_by_loop"] > 100  # the loop fed it once per clean tick
    assert r.get("timer") == [1, 100], r  # periodic, a third of the timeout
    assert r["timer_id"] == 0
    assert r["feeds_by_timer"] == 3  # ... and its callback feeds the dog
    assert r["hold"] and not r["still_moving"]
    if action == "release":
        assert r["after"] == [0, 0, 0]  # pulses off: the servos go limp, as in FAULT
    else:
        assert all(p > 0 for p in r["after"])  # held where they are


def test_a_second_ctrl_c_during_the_safe_stop_still_feeds_the_watchdog_and_stops(vm):
    """Code review: ``ucr flash`` sends two Ctrl-C and people double-tap; a second one while the
    servos were being made safe (a Feetech torque-off takes a while) escaped the handler before
    the watchdog's feeder started: the board reset in the REPL. Now the handler starts again."""
    sync = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
    cfg = PWM_CFG % ("hold", ", 'hw_watchdog_ms': 300")
    code = _RUN.replace(
        "hal.wait = wait\n",
        "hal.wait = wait\n"
        "stop = seg.stop_for_repl\n"
        "calls = [0]\n"
        "def twice():\n"
        "    calls[0] += 1\n"
        "    if calls[0] == 1:\n"
        "        raise KeyboardInterrupt  # the second Ctrl-C, mid-stop\n"
        "    stop()\n"
        "seg.stop_for_repl = twice\n",
    )
    code += "R['stop_calls'] = calls[0]\n"
    r = vm(code % (cfg, sync), heap="4m")
    assert r["interrupt"] and r["stop_calls"] == 2, r
    assert r.get("timer") == [1, 100], r  # the feeder runs
    assert r["feeds_by_timer"] == 3
    assert r["hold"] and not r["still_moving"]


def test_without_a_hardware_watchdog_ctrl_c_starts_no_timer(vm):
    sync = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
    r = vm(_RUN % (PWM_CFG % ("hold", ""), sync), heap="4m")
    assert r["interrupt"] and "timer" not in r and r["hold"]


# -- B: PWM after release ------------------------------------------------------------------------
def test_pwm_servos_released_in_fault_restart_from_the_rest_pose_under_the_slew_limit(vm):
    """After FAULT with fault_action release (pulses off, servos limp), CLEAR_FAULT and a resume
    SYNC drove the servos in one step to the pre-fault pose (the last command, taken as their
    position): a limp hobby servo may be anywhere. Now it is assumed at its rest pose again, as
    at power-on, and moves from there under the servo-speed limit (review B)."""
    bend = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
    clear = M.encode_clear_fault(5).hex()
    resume = M.encode_sync(6, 6, [None], resume=True).hex()  # resume, no setpoint
    r = vm(
        f"""
rest = [0.2, -0.1, 0.0]
servos = [{{'id': i, 'rest_angle': rest[i]}} for i in range(3)]
hal, seg = vmkit.make({{'servo_driver': 'pwm', 'fault_action': 'release', 'watchdog_ms': 60000,
                        'servos': servos}})
bus = seg.bus
for _ in range(40):
    hal.up.feed(bytes.fromhex('{bend}')); vmkit.run(hal, seg, 25)
R['bent'] = [p.ns for p in bus.pwm]
seg.enter_fault(1, 'tick: simulated')
vmkit.run(hal, seg, 50)
R['in_fault'] = [p.ns for p in bus.pwm]
hal.up.feed(bytes.fromhex('{clear}')); vmkit.run(hal, seg, 10)
rest_raw = [seg.cfg.zero[i] + seg.cfg.rest[i] for i in range(3)]
R['rest_pulses'] = [bus.centre_ns + ((rest_raw[i] * bus.k256 + 128) >> 8) for i in range(3)]
hal.up.feed(bytes.fromhex('{resume}')); vmkit.run(hal, seg, 5)
R['first'] = [p.ns for p in bus.pwm]
seq = []
for _ in range(20):
    hal.up.feed(bytes.fromhex('{bend}')); vmkit.run(hal, seg, 5)
    seq.append([p.ns for p in bus.pwm])
R['seq'] = seq
R["step_ns"] = (seg.sc.step_limit * bus.k256 + 128) >> 8
"""
    )
    assert r["in_fault"] == [0, 0, 0]
    assert r["bent"] != r["rest_pulses"]
    step = r["step_ns"] + 1
    # the rest pose, as at power-on: the first command starts there (one servo step at most,
    # towards the pose the measured curvature maps to), not at the pre-fault bend
    assert all(abs(a - b) <= step for a, b in zip(r["first"], r["rest_pulses"], strict=True)), r
    assert any(abs(a - b) > 10 * step for a, b in zip(r["bent"], r["rest_pulses"], strict=True))
    prev = r["first"]
    for pulses in r["seq"]:  # from there at most one servo-speed step per tick
        assert all(abs(a - b) <= step for a, b in zip(pulses, prev, strict=True)), (
            pulses,
            prev,
        )
        prev = pulses
    assert r["seq"][-1] != r["first"]  # and it does move towards the setpoint


# -- C: no config.json ---------------------------------------------------------------------------
def test_an_emulated_segment_without_config_json_holds_and_says_why():
    """No config.json ran the built-in defaults (PWM pins 25/26/27 on a board, zero offsets 0,
    ranges ±π) and moved on a SYNC (review C). Now it is refused like an invalid file: HOLD +
    UNCONFIGURED, config_error says why, a SYNC moves nothing. The emulator provisions a
    configuration explicitly when a test gives none (tools.emulator.default_config)."""
    from host.link import ChainLink
    from tools.emulator import NO_CONFIG, EmulatedChain, default_config

    with (
        EmulatedChain(2, config_for=[NO_CONFIG, default_config()]) as chain,
        ChainLink(chain.host_port) as link,
    ):
        end = time.monotonic() + 30
        descs: list = []
        while len(descs) < 2 and time.monotonic() < end:
            descs = link.discover(timeout=0.5)
        assert len(descs) == 2, chain.repl_output(0)[-2000:]
        assert descs[0]["config_error"].startswith("no config.json")
        assert not descs[1].get("config_error")
        assert not (chain.segment_dir(0) / "config.json").exists()
        assert (chain.segment_dir(1) / "config.json").exists()  # written out, not built in
        first = link.sync([(0.0, 0.0), (0.0, 0.0)], timeout=0.5)
        for _ in range(80):
            states = link.sync([(2.0, 0.5), (2.0, 0.5)], timeout=0.5)
            time.sleep(0.01)
    st0, st1 = states[0], states[1]
    assert {"HOLD", "UNCONFIGURED"} <= set(st0["status"])
    assert st0["servo_angles"] == pytest.approx(first[0]["servo_angles"], abs=1e-3)  # no motion
    assert "UNCONFIGURED" not in st1["status"] and st1["kappa"] > 1.0  # the provisioned one moves


@pytest.fixture()
def esp32_hal(monkeypatch):
    monkeypatch.setitem(sys.modules, "machine", types.ModuleType("machine"))
    monkeypatch.syspath_prepend(str(DEVICE))
    for m in ("hal_esp32", "main", "config"):
        monkeypatch.delitem(sys.modules, m, raising=False)
    import hal_esp32

    return hal_esp32


def test_a_board_without_config_json_drives_no_servo_and_says_why(esp32_hal, monkeypatch, tmp_path):
    """main.build on an ESP32 (stand-in machine, CPython) in a flash without config.json: the
    PWM driver on the default pins was built and moved on the first SYNC. Now: no servo driver
    that drives a pin (OfflineBus), HOLD + UNCONFIGURED, the reason in config_error."""
    from tests.device.test_device_hal_esp32 import _boot

    opened, pwm, seg = _boot(esp32_hal, monkeypatch, tmp_path, "ESP32", {})
    (tmp_path / "config.json").unlink()
    import main

    _, seg = main.build()
    assert (seg.cfg.error or "").startswith("no config.json")
    assert seg.bus.name == "offline"  # no PWM output on guessed pins
    assert seg.status() & 0x21 == 0x21  # HOLD + UNCONFIGURED
    assert not seg._may_move()


# -- D: ALIVE payload ----------------------------------------------------------------------------
def test_alive_payloads_are_validated_like_discovers(vm):
    """An ALIVE with invalid CBOR got no ERROR and was not counted in ``dropped``, while a
    DISCOVER with the same bytes was MALFORMED (review D). A valid ALIVE stays silent."""
    frames = [
        encode_frame(4, 0, 0x07, 1, b"\xff\xff\x1f"),  # LOCAL, garbage
        encode_frame(0, 0, 0x07, 2, b"\xbf\x00"),  # addressed, indefinite map
        encode_frame(4, 0, 0x07, 3, b"\xa1\x00\xa1\x01\x01\x00"),  # trailing byte
        encode_frame(4, 0, 0x07, 4, b"\xa0"),  # valid: {}
        encode_frame(4, 0, 0x07, 5, b""),  # valid: empty payload counts as {}
        encode_frame(0, 0, 0x01, 6, b"\xff\xff\x1f"),  # DISCOVER with garbage
    ]
    r = vm(
        f"""
hal, seg = vmkit.make({{}})
R['res'] = []
for f in {[f.hex() for f in frames]!r}:
    vmkit.run(hal, seg, 5)
    hal.up.take()
    d0 = seg.dropped
    hal.up.feed(bytes.fromhex(f))
    vmkit.run(hal, seg, 5)
    R['res'].append([seg.dropped - d0, vmkit.hexs(hal.up.take())])
"""
    )
    got = [
        (dropped, [m["name"] for m in decode(out) if m["type"] == "ERROR"])
        for dropped, out in r["res"]
    ]
    assert got == [
        (1, ["MALFORMED"]),
        (1, ["MALFORMED"]),
        (1, ["MALFORMED"]),
        (0, []),
        (0, []),
        (1, ["MALFORMED"]),
    ], got


# -- E: overruns ---------------------------------------------------------------------------------
@pytest.mark.parametrize("tick", [5, 20])
def test_overruns_count_ticks_that_start_a_whole_tick_late(vm, tick):
    """``overruns`` counted only ticks more than four periods late (20 ms at 5 ms) while the
    documentation said "> 20 ms" for every tick_ms (review E). Now: a tick that starts a whole
    tick period or more after its slot is an overrun, whatever tick_ms is."""
    r = vm(
        f"""
from main import Runner
tick = {tick}
hal, seg = vmkit.make({{'tick_ms': tick}}, tick_ms=tick)
r = Runner(hal, seg, tick)
counts = []
for late in (0, tick - 1, tick, 3 * tick, 5 * tick):
    r.next_t = hal.t
    hal.t += late
    o = seg.overruns
    r.once()
    counts.append(seg.overruns - o)
    hal.t = r.next_t  # back on schedule
    r.once()
R['counts'] = counts
""",
        heap="4m",
    )
    assert r["counts"] == [0, 0, 1, 1, 1], r
