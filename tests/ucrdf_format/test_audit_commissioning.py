"""Commissioning audit: the PWM pulse range in the U(C)RDF, no invented servos, `ucr check`
showing each board's wiring, and <origin rpy> in degrees refused."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from tests.cli_run import run_ucr as ucr
from tools.segment_config import SegmentConfigError, config_for, configs
from ucrdf.checks import check, warnings
from ucrdf.compose import robot_from_descriptors
from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string, parse_with_lines
from ucrdf.writer import dumps

REPO = Path(__file__).resolve().parents[2]
HYBRID = REPO / "robots" / "hybrid_arm.ucrdf"
PULSE = '      <pwm_pulse min_us="500" max_us="2500" range="6.283185307179586"/>\n'


def _hybrid(tmp_path: Path, old: str = "", new: str = "") -> Path:
    text = HYBRID.read_text()
    if old:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "hybrid.ucrdf"
    path.write_text(text)
    return path


def _line_of(path: Path, needle: str) -> int:
    return next(i for i, t in enumerate(path.read_text().splitlines(), 1) if needle in t)


# -- 1. the PWM pulse range ---------------------------------------------------------------------
def test_a_pwm_servo_travel_beyond_the_default_pulse_range_is_an_error_at_its_line(tmp_path):
    path = _hybrid(tmp_path, PULSE, "")  # the auditor's file: ±3 rad, no pulse range declared
    result = ucr("check", str(path))
    assert result.returncode == 1
    line = _line_of(path, '<servo index="0" id="0"')
    assert f"{path}:{line}: bendable 'wrist'" in result.stderr
    assert "PWM pulse range" in result.stderr and "[-1.571, 1.571]" in result.stderr
    assert "<pwm_pulse" in result.stderr  # says what to declare


def test_kappa_max_reachability_is_judged_against_the_pulse_range(tmp_path):
    # travel inside the declared pulse range, but the range too small for kappa_max
    path = _hybrid(
        tmp_path,
        'range="6.283185307179586"',
        'range="4.0"',
    )
    text = path.read_text().replace('min_angle="-3.0" max_angle="3.0"', "")
    path.write_text(text)  # min/max default to the pulse range: ±2 rad
    with pytest.raises(UcrdfError) as exc:
        load(path)
    assert "cannot reach kappa_max" in str(exc.value)
    servo = load(_hybrid(tmp_path)).bendables["wrist"].actuation.servos[0]
    assert (servo.min_angle, servo.max_angle) == (-3.0, 3.0)


def test_a_pwm_servo_without_min_max_spans_its_pulse_range(tmp_path):
    path = _hybrid(tmp_path, 'min_angle="-3.0" max_angle="3.0"', "")
    path.write_text(
        path.read_text().replace(
            'zero_offset="0.0" direction="1"', 'zero_offset="0.1" direction="1"', 1
        )
    )
    servos = load(path).bendables["wrist"].actuation.servos
    assert servos[0].min_angle == pytest.approx(-math.pi - 0.1)
    assert servos[0].max_angle == pytest.approx(math.pi - 0.1)
    assert servos[1].min_angle == pytest.approx(-math.pi)


def test_the_pulse_range_round_trips_and_reaches_config_json(tmp_path):
    robot = load(HYBRID)
    pulse = robot.bendables["wrist"].actuation.pwm_pulse
    assert (pulse.min_us, pulse.max_us, pulse.range) == (500.0, 2500.0, math.tau)
    assert "<pwm_pulse" in dumps(robot)
    assert parse_string(dumps(robot)) == robot
    cfg = config_for(robot, "wrist")
    assert cfg["pwm"] == {
        "pins": [25, 26, 27, 32],
        "min_us": 500.0,
        "max_us": 2500.0,
        "range": math.tau,
    }


@pytest.mark.parametrize(
    "attrs, words",
    [
        ('min_us="2500" max_us="500"', "need 0 < min_us < max_us < 20000"),
        ('min_us="500" max_us="6000"', "more than 4000 us"),
        ('range="180"', "if 180 is degrees, write 3.14159265"),
        ('range="0"', "must be > 0"),
    ],
)
def test_an_impossible_pulse_range_is_an_error_at_its_line(tmp_path, attrs, words):
    path = _hybrid(tmp_path, PULSE, f"      <pwm_pulse {attrs}/>\n")
    with pytest.raises(UcrdfError) as exc:
        load(path)
    line = _line_of(path, "<pwm_pulse")
    assert any(d.line == line and words in d.message for d in exc.value.diagnostics), str(exc.value)


def test_two_pulse_ranges_are_an_error(tmp_path):
    path = _hybrid(tmp_path, PULSE, PULSE + PULSE)
    with pytest.raises(UcrdfError, match="two <pwm_pulse>"):
        load(path)


# -- 2. no invented servos ----------------------------------------------------------------------
def _no_servos(tmp_path: Path) -> Path:
    text = HYBRID.read_text()
    text = re.sub(r'\s*<servo index="\d" id="\d"[^>]*/>', "", text)
    path = tmp_path / "noservo.ucrdf"
    path.write_text(text)
    return path


def test_flash_refuses_a_segment_without_servos_and_says_what_to_add(tmp_path):
    path = _no_servos(tmp_path)
    with pytest.raises(SegmentConfigError) as exc:
        config_for(load(path), "wrist")
    text = str(exc.value)
    assert "declares no <servo>" in text and "add one <servo index= id=" in text
    assert text.startswith(f"{path}:")
    result = ucr("flash", "--port", "/dev/null", "--robot", str(path), "--segment", "wrist")
    assert result.returncode != 0 and "declares no <servo>" in result.stderr


def test_an_emulated_chain_still_gets_stand_in_servos(tmp_path):
    cfgs = configs(load(_no_servos(tmp_path)))
    assert [s["id"] for s in cfgs[-1]["servos"]] == [0, 1, 2, 3]


def test_check_warns_about_a_segment_without_servos_at_its_line(tmp_path):
    path = _no_servos(tmp_path)
    result = ucr("check", str(path))
    assert result.returncode == 0
    line = _line_of(path, 'driver="pwm"')
    assert f"{path}:{line}: warning: bendable 'wrist'" in result.stderr
    assert "declares no <servo>" in result.stderr
    robot, lines = parse_with_lines(path.read_bytes(), str(path))
    assert [d.line for d in warnings(robot, lines)] == [line]


def test_a_file_composed_from_descriptors_says_its_servos_are_missing(tmp_path):
    desc = {
        "name": "seg1",
        "length": 0.2,
        "tendon_angles": [0.0, 2.0943951023931953, 4.1887902047863905],
        "tendon_radius": 0.03,
        "spool_radius": 0.016,
        "kappa_max": 5.0,
        "servo_driver": "emulated",
    }
    robot = robot_from_descriptors([desc], "arm")
    text = dumps(robot)
    assert "<!-- no <servo> declared" not in text.split("<actuation")[0]
    comment = text.split("<actuation", 1)[1].split("</actuation>")[0]
    assert "no <servo> declared" in comment and "`ucr flash` refuses" in comment
    path = tmp_path / "arm.adopted.ucrdf"
    path.write_text(text)
    with pytest.raises(SegmentConfigError, match="declares no <servo>"):
        config_for(load(path), "seg1")
    assert parse_string(text) == robot  # the comment changes nothing else


# -- 5. `ucr check` shows each segment's board, pins and UARTs ----------------------------------
def test_check_prints_each_segments_board_pins_and_uarts():
    result = ucr("check", str(HYBRID))
    assert result.returncode == 0, result.stderr
    assert (
        "board esp32, upstream UART1 tx 19 rx 18, downstream UART2 tx 17 rx 16, 921600 baud, "
        "PWM pins 25, 26, 27, 32, pulse 500..2500 us = 6.283 rad"
    ) in result.stdout


def test_check_prints_a_servo_bus_uart(tmp_path):
    path = _hybrid(tmp_path, 'driver="pwm"', 'driver="feetech_sts"')
    path.write_text(path.read_text().replace(PULSE, ""))
    result = ucr("check", str(path))
    assert result.returncode == 0, result.stderr
    assert "board esp32s3-usbrepl" in result.stdout and "servo bus UART" in result.stdout


# -- 6. <origin rpy> in degrees -----------------------------------------------------------------
JOINT_ORIGIN = '<child link="shoulder"/>\n    <origin xyz="0 0 0.1" rpy="0 0 0"/>'  # shoulder_yaw
INERTIAL_ORIGIN = '<origin xyz="0 0 0.06" rpy="0 0 0"/>'  # the wrist's <inertial>
WRIST = '    <parent link="wrist_base"/>'


@pytest.mark.parametrize(
    "old, new, needle, what",
    [
        (
            JOINT_ORIGIN,
            '<child link="shoulder"/>\n    <origin xyz="0 0 0.1" rpy="0 0 90"/>',
            'rpy="0 0 90"',
            "joint 'shoulder_yaw'",
        ),
        (INERTIAL_ORIGIN, '<origin xyz="0 0 0.06" rpy="0 0 90"/>', 'rpy="0 0 90"', "<inertial>"),
        (
            WRIST,
            WRIST + '\n    <origin xyz="0 0 0" rpy="0 0 90"/>',
            'rpy="0 0 90"',
            "bendable 'wrist'",
        ),
    ],
)
def test_origin_rpy_in_degrees_is_refused_at_its_line(tmp_path, old, new, needle, what):
    path = _hybrid(tmp_path, old, new)
    line = _line_of(path, needle)
    with pytest.raises(UcrdfError) as exc:
        load(path)
    hits = [d for d in exc.value.diagnostics if "rpy yaw 90 is beyond 2*pi" in d.message]
    assert len(hits) == 1 and hits[0].line == line, str(exc.value)
    assert what in hits[0].message and "write 1.570796327" in hits[0].message


def test_origin_rpy_within_two_pi_passes():
    robot = load(HYBRID)
    assert not check(robot)
