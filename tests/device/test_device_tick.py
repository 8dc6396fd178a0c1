"""The control tick's period is configurable (config.json ``tick_ms``, U(C)RDF hardware param
``tick_ms``; docs/firmware.md "CPU load"): a board too slow for 200 Hz can tick slower, and the
limits stay per second whatever the tick."""

from __future__ import annotations

import subprocess

import pytest

from protocol import messages as M
from tools import mpvm
from tools.emulator.chain import populate_segment_dir
from tools.segment_config import SegmentConfigError, config_for
from ucrdf.parser import load

ROBOT = mpvm.REPO / "robots" / "softrobot3.ucrdf"


@pytest.mark.parametrize("value", [1, 51, True, 5.0, "5"])
def test_a_tick_outside_2_to_50_whole_ms_is_refused(vm, value):
    r = vm(
        f"""
import config
try:
    config.Config({{'tick_ms': {value!r}}})
    R['err'] = None
except ValueError as e:
    R['err'] = str(e)
R['ok'] = config.Config({{'tick_ms': 10}}).tick_ms
"""
    )
    assert r["err"] and "tick_ms" in r["err"]
    assert r["ok"] == 10


def test_the_firmware_ticks_at_the_configured_period(tmp_path):
    seg = tmp_path / "seg"
    populate_segment_dir(seg, config={"tick_ms": 10, "watchdog_ms": 60000})
    out = subprocess.run(
        [mpvm.micropython_binary(), "-X", f"heapsize={mpvm.ESP32_HEAP}", "-c",
         "import main\nhal, seg = main.build()\nprint('@@', seg.tick_ms, seg.mc.tick_ms)"],
        cwd=seg, env={"MICROPYPATH": f".frozen:{seg}", "UCR_UID": "b0a4d0000001"},
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    line = next((x for x in out.stdout.splitlines() if x.startswith("@@")), None)
    assert line == "@@ 10 10", out.stdout + out.stderr


def test_the_slew_limit_is_per_second_whatever_the_tick(vm):
    """A far setpoint: after 300 ms a 5 ms and a 20 ms segment have bent equally far, at
    kappa_rate_max (the slew step per tick scales with the tick)."""
    sync = M.encode_sync(1, 1, [(3.0, 0.0)], resume=True).hex()
    r = vm(
        f"""
import gc
out = {{}}
for tick in (5, 20):
    hal, seg = vmkit.make({{'watchdog_ms': 60000, 'kappa_rate_max': 2.0}}, tick_ms=tick)
    vmkit.run(hal, seg, 40)
    for _ in range(15):                   # a SYNC every 20 ms, 300 ms
        hal.up.feed(bytes.fromhex('{sync}'))
        vmkit.run(hal, seg, 20)
        hal.up.discard()
    out[str(tick)] = seg.mc.cx
    del hal, seg
    gc.collect()
R["cx"] = out
""",
        heap="400k",  # two segments built one after the other: more than one board's heap
    )
    k5, k20 = r["cx"]["5"] / 1e4, r["cx"]["20"] / 1e4  # 1e-4 1/m
    assert 0.4 <= k5 <= 0.7 and 0.4 <= k20 <= 0.7, r  # 2 1/m/s for about 0.3 s
    assert abs(k5 - k20) <= 0.05, r


def test_ucrdf_hardware_param_tick_ms_reaches_the_segment_config():
    robot = load(ROBOT)
    assert "tick_ms" not in config_for(robot, "segment_1")  # not given: the firmware's 5 ms
    robot.ros2_control[0].hardware_params["tick_ms"] = "10"
    assert config_for(robot, "segment_1")["tick_ms"] == 10
    for bad in ("1", "7.5", "fast"):
        robot.ros2_control[0].hardware_params["tick_ms"] = bad
        with pytest.raises(SegmentConfigError, match="tick_ms"):
            config_for(robot, "segment_1")


def test_ucr_check_refuses_a_tick_the_segments_cannot_run_with_path_and_line(tmp_path):
    from tests.cli_run import run_ucr
    from tests.device.test_device_config_rules import _line_of, _robot

    old = '<param name="watchdog_ms">200</param>'
    path = _robot(tmp_path, **{old: old + '\n      <param name="tick_ms">7.5</param>'})
    line = _line_of(path, 'name="tick_ms"')
    res = run_ucr("check", str(path))
    out = res.stdout + res.stderr
    assert res.returncode != 0 and "Traceback" not in out
    assert f"{path}:{line}: " in out and "tick_ms 7.5 is not a whole number of ms" in out


def test_a_watchdog_shorter_than_two_ticks_is_refused_by_firmware_and_ucr_check(vm, tmp_path):
    r = vm(
        """
import config
try:
    config.Config({'tick_ms': 25, 'watchdog_ms': 40})
    R['err'] = None
except ValueError as e:
    R['err'] = str(e)
R['ok'] = config.Config({'tick_ms': 25, 'watchdog_ms': 50}).watchdog_ms
"""
    )
    assert r["err"] and "two ticks" in r["err"] and r["ok"] == 50
    from tests.cli_run import run_ucr
    from tests.device.test_device_config_rules import _line_of, _robot

    old = '<param name="watchdog_ms">200</param>'
    new = '<param name="watchdog_ms">40</param>\n      <param name="tick_ms">25</param>'
    path = _robot(tmp_path, **{old: new})
    res = run_ucr("check", str(path))
    out = res.stdout + res.stderr
    assert res.returncode != 0 and "Traceback" not in out
    line = _line_of(path, 'name="watchdog_ms"')
    assert f"{path}:{line}: " in out and "two ticks" in out
