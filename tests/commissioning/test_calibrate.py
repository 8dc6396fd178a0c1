"""``ucr calibrate --script`` end to end on the emulated chain: a segment built with zero offsets
and a reversed servo is calibrated, bends right afterwards, and keeps its calibration across a
restart; the robot file takes it and still passes ``ucr check``; the configuration hash follows."""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import pytest

from host.link import ChainLink, LinkError
from protocol import calibration as cal
from protocol.constants import T_CALIBRATE, T_CALIBRATION
from tools.cli import main
from tools.emulator import EmulatedChain
from tools.mpvm import REPO
from tools.segment_config import config_for
from ucrdf.parser import load

ROBOT = REPO / "robots" / "softrobot2.ucrdf"
TRUE_ZERO = [0.12, -0.08, 0.05]  # raw rad where each tendon is straight and just taut
TRUE_DIR = [1, -1, 1]  # servo 1 was mounted the other way round
SCRIPT = """# calibrate a freshly built segment
identify 0.4
check-directions 0.4
tension 0.05 0.02
persist
"""


def _config() -> dict:
    cfg = {**config_for(load(ROBOT), "segment_1"), "servo_driver": "emulated"}
    cfg["emulated_zero"] = list(TRUE_ZERO)
    cfg["emulated_direction"] = list(TRUE_DIR)
    return cfg


def _discover(link: ChainLink, timeout: float = 30.0) -> list[dict]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            d = link.discover(timeout=0.5)
            if d:
                return d
        except LinkError:
            pass
        time.sleep(0.1)
    raise AssertionError("the segment did not answer DISCOVER")


def _true_bend(cfg: dict, zeros: list[float], dirs: list[int], joints: list[float]) -> tuple:
    """(kx, ky) 1/m the emulated segment really has: raw angles from the measured joints and the
    calibration it runs, tendon pulls from the physical zero and winding sense."""
    r, d, ln = cfg["spool_radius"], cfg["tendon_radius"], cfg["length"]
    kx = ky = 0.0
    for i, sigma in enumerate(cfg["tendon_angles"]):
        raw = zeros[i] + dirs[i] * joints[i]
        shortening = TRUE_DIR[i] * (raw - TRUE_ZERO[i]) * r
        kx += 2.0 / (3.0 * ln * d) * shortening * math.cos(sigma)
        ky += 2.0 / (3.0 * ln * d) * shortening * math.sin(sigma)
    return kx, ky


def _bend(link: ChainLink, kappa: float, phi: float, seconds: float = 3.0) -> dict:
    end = time.monotonic() + seconds
    st = None
    while time.monotonic() < end:
        st = link.sync([(kappa, phi)], timeout=0.2, resume=True)[0] or st
        time.sleep(0.02)
    assert st is not None
    return st


def _read(link: ChainLink) -> dict:
    reply = link.request(0, T_CALIBRATE, cal.calibrate_payload(cal.ACTION_READ), T_CALIBRATION)
    return cal.decode_calibration(reply)


def test_calibrate_script_fixes_offsets_and_a_reversed_servo_and_survives_a_restart(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    robot = tmp_path / "robot.ucrdf"
    shutil.copy(ROBOT, robot)
    script = tmp_path / "cal.txt"
    script.write_text(SCRIPT)
    cfg = _config()
    want = (2.0, 0.6)
    with EmulatedChain(1, config_for=[cfg]) as chain:
        with ChainLink(chain.host_port) as link:
            _discover(link)
            before = _read(link)
            st = _bend(link, *want)  # uncalibrated: the reversed servo bends it wrong
            bad = _true_bend(cfg, before["zero_offsets"], before["directions"], st["servo_angles"])
            link.hold()
        rc = main(
            ["calibrate", "--port", chain.host_port, "--segment", "segment_1"]
            + ["--script", str(script), "--robot", str(robot)]
        )
        out = capsys.readouterr()
        assert rc == 0, out.err
        assert "servo 1 REVERSED" in out.out
        chain.restart(0)
        with ChainLink(chain.host_port) as link:
            desc = _discover(link)[0]
            after = _read(link)
            st = _bend(link, *want)
            good = _true_bend(cfg, after["zero_offsets"], after["directions"], st["servo_angles"])
    wx, wy = want[0] * math.cos(want[1]), want[0] * math.sin(want[1])
    assert math.hypot(bad[0] - wx, bad[1] - wy) > 0.15  # the fault was real
    assert after["stored"] and after["directions"] == TRUE_DIR
    assert math.hypot(good[0] - wx, good[1] - wy) < 0.05, (good, (wx, wy))
    # the robot file took the calibration, still passes `ucr check`, and hashes as the segment
    assert main(["check", "--quiet", str(robot)]) == 0
    flashed = {**config_for(load(robot), "segment_1"), "servo_driver": "emulated"}
    servos = flashed["servos"]
    assert [s["direction"] for s in servos] == TRUE_DIR
    assert [s["zero_offset"] for s in servos] == pytest.approx(after["zero_offsets"], abs=1e-4)
    assert desc["config_hash"] == cal.config_hash(flashed)


def test_calibrate_script_errors_name_the_line_and_move_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    script = tmp_path / "bad.txt"
    script.write_text("identify\njog 0 2.0\n")
    rc = main(
        ["calibrate", "--port", str(tmp_path / "nope"), "--segment", "x", "--script", str(script)]
    )
    assert rc == 1
    assert f"{script}:2: jog at most 0.5 rad" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("{not json", "not JSON"),
        ('{"version": 2, "servos": []}', "version must be 1"),
        ('{"version": 1, "servos": [{"zero_offset": 0.1, "direction": 1}]}', "1 servos calibrated"),
        (
            (
                '{"version": 1, "servos": [{"zero_offset": 3.0, "direction": 1}, '
                '{"zero_offset": 0, "direction": 1}, {"zero_offset": 0, "direction": 1}]}'
            ),
            "more than 1.0 rad",
        ),
    ],
)
def test_an_invalid_stored_calibration_is_refused_at_boot_and_nothing_moves(
    text: str, why: str
) -> None:
    cfg = _config()
    with EmulatedChain(1, config_for=[cfg]) as chain:
        (chain.segment_dir(0) / "calibration.json").write_text(text)
        chain.restart(0)
        with ChainLink(chain.host_port) as link:
            desc = _discover(link)[0]
            full = link.param_get(0, 16)  # config_error, full text
            before = _bend(link, 0.0, 0.0, 0.3)["servo_angles"]
            st = _bend(link, 2.0, 0.6, 1.0)
    assert desc["config_error"].startswith("calibration.json rejected")
    assert why in full
    assert {"HOLD", "UNCONFIGURED"} <= set(st["status"])
    assert st["servo_angles"] == pytest.approx(before, abs=1e-3)  # never moves on it


def test_calibration_changes_only_in_hold_and_forget_deletes_the_stored_one() -> None:
    with EmulatedChain(1, config_for=[_config()]) as chain:
        with ChainLink(chain.host_port) as link:
            _discover(link)
            _bend(link, 1.0, 0.0, 1.0)  # moving
            payload = cal.calibrate_payload(cal.ACTION_APPLY, [0.1, 0.0, 0.0], [1, 1, 1])
            with pytest.raises(LinkError, match="send HOLD first"):
                link.request(0, T_CALIBRATE, payload, T_CALIBRATION)
            link.hold()
            time.sleep(0.1)
            payload = cal.calibrate_payload(cal.ACTION_PERSIST, [0.1, 0.0, 0.0], [1, 1, 1])
            got = cal.decode_calibration(link.request(0, T_CALIBRATE, payload, T_CALIBRATION))
            assert got["stored"] and (chain.segment_dir(0) / "calibration.json").exists()
            assert not (chain.segment_dir(0) / "calibration.tmp").exists()  # renamed, not left
            forget = cal.calibrate_payload(cal.ACTION_FORGET)
            got = cal.decode_calibration(link.request(0, T_CALIBRATE, forget, T_CALIBRATION))
    assert not got["stored"] and not (chain.segment_dir(0) / "calibration.json").exists()


def test_a_replace_interrupted_after_the_remove_is_completed_at_boot() -> None:
    """FAT cannot rename over a file: persist removes the old one, then renames the complete
    temp file. A power cut in between leaves only the temp file; the next boot takes it."""
    with EmulatedChain(1, config_for=[_config()]) as chain:
        (chain.segment_dir(0) / "calibration.tmp").write_text(
            '{"version": 1, "servos": [{"zero_offset": 0.1, "direction": 1}, '
            '{"zero_offset": -0.05, "direction": -1}, {"zero_offset": 0.0, "direction": 1}]}'
        )
        chain.restart(0)
        with ChainLink(chain.host_port) as link:
            desc = _discover(link)[0]
            got = _read(link)
    assert desc["config_error"] == ""
    assert got["stored"] and got["directions"] == [1, -1, 1]
    assert got["zero_offsets"] == pytest.approx([0.1, -0.05, 0.0])
