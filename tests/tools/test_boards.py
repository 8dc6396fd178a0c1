"""Issue 11 finding 5 (board reality): each board profile's refusals, the same in ``ucr check``,
``ucr flash``, the segment's config.json at boot and the emulated board's ``machine``."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import pytest

from protocol import boards
from tests.cli_run import run_ucr
from tools import mpvm
from tools.emulator import EmulatedChain
from tools.segment_config import config_for
from ucrdf.parser import load

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"
ACT = '<actuation type="tendon" count="3" radius="0.06" spool_radius="0.025" driver="emulated">'

pytestmark = pytest.mark.timeout(120)


def _robot(tmp_path: Path, actuation: str, wiring: str = "") -> Path:
    """softrobot3 with segment_2's <actuation> start tag replaced and ``wiring`` added to it."""
    text = ROBOT.read_text()
    start = text.index('<bendable name="segment_2">')
    head, tail = text[:start], text[start:]
    tail = tail.replace(ACT, actuation + wiring, 1)
    path = tmp_path / "robot.ucrdf"
    path.write_text(head + tail)
    return path


def _line_of(path: Path, needle: str) -> int:
    start = path.read_text().index('<bendable name="segment_2">')
    lines = path.read_text().splitlines()
    offset = path.read_text()[:start].count("\n")
    for i, line in enumerate(lines[offset:], offset + 1):
        if needle in line:
            return i
    raise AssertionError(needle)


# -- the rules, board by board -------------------------------------------------------------------
def _msgs(board: str, **kw) -> list[str]:
    return [m for _, m in boards.problems(board, **kw)]


def test_every_board_accepts_its_default_plan_for_pwm_and_emulated_servos() -> None:
    for name in ("esp32", "esp32s3", "esp32s3-usbrepl", "esp32c3-usbrepl", "unix"):
        assert boards.problems(name, driver="pwm") == [], name
        assert boards.problems(name, driver="emulated") == [], name


def test_uart0_is_the_repl_on_stock_micropython_and_refused_for_the_chain() -> None:
    for name in ("esp32", "esp32s3"):
        msgs = _msgs(name, pins={"up_uart": 0}, driver="pwm")
        assert any("UART0 is the REPL's" in m for m in msgs), msgs


def test_a_c3_has_two_uarts_so_a_stock_c3_cannot_chain() -> None:
    assert any(
        "UART2 for the downstream UART does not exist" in m
        for m in _msgs("esp32c3-usbrepl", pins={"down_uart": 2})
    )
    msgs = _msgs("esp32c3", driver="pwm")
    assert any("2 UARTs and UART0 is the REPL's" in m and "downstream" in m for m in msgs)


def test_a_pin_used_twice_and_reserved_pins_are_refused() -> None:
    msgs = _msgs("esp32", pwm={"pins": [19, 26, 27]}, driver="pwm")
    assert any("GPIO19 is used twice: upstream UART TX and PWM servo 0" in m for m in msgs)
    assert any("GPIO6 is wired to the SPI flash" in m for m in _msgs("esp32", pins={"up_tx": 6}))
    assert any("GPIO34 is input-only" in m for m in _msgs("esp32", pins={"down_tx": 34}))
    assert any("GPIO19 is the native USB" in m for m in _msgs("esp32s3", pins={"up_tx": 19}))


def test_every_esp32_gpio_from_34_is_input_only_as_the_port_says() -> None:
    """ports/esp32/machine_pin.c: GPIO_FIRST_NON_OUTPUT 34 on the ESP32 (37/38 exist on some
    packages, inputs only); the S3 and C3 have no input-only GPIO (no such limit for them)."""
    for g in (34, 35, 36, 37, 38, 39):
        msgs = _msgs("esp32", pwm={"pins": [25, 26, g]}, driver="pwm")
        assert msgs == [f"PWM servo 2: GPIO{g} is input-only on esp32"], msgs
        assert _msgs("esp32", pins={"down_rx": g}) == []  # an input is fine
    assert boards.profile("esp32")["input_only"] == tuple(range(34, 40))
    for name in ("esp32s3", "esp32c3"):
        assert boards.profile(name)["input_only"] == ()


def test_ucr_check_refuses_pwm_on_gpio37_with_path_and_line(tmp_path) -> None:
    text = ROBOT.read_text()
    old = '<actuation type="tendon" count="3" radius="0.06" spool_radius="0.025" driver="emulated">'
    assert old in text
    new = (
        old.replace('driver="emulated">', 'driver="pwm" board="esp32">')
        + '\n        <pwm index="0" pin="37"/>\n        <pwm index="1" pin="38"/>'
        + '\n        <pwm index="2" pin="27"/>'
    )
    path = tmp_path / "pwm37.ucrdf"
    path.write_text(text.replace(old, new, 1))
    line = next(i for i, s in enumerate(path.read_text().splitlines(), 1) if 'pin="37"' in s)
    res = run_ucr("check", str(path))
    assert res.returncode != 0
    out = res.stdout + res.stderr
    assert f"{path}:{line}: " in out and "GPIO37 is input-only on esp32" in out, out


def test_a_serial_servo_bus_needs_a_free_uart_and_unique_ids() -> None:
    msgs = _msgs("esp32", driver="feetech_sts", servo_ids=[1, 2, 3])
    assert any("no UART left for a serial servo bus" in m for m in msgs)
    # the classic Feetech defaults (UART0, GPIO17/16) collide with the REPL and the chain
    msgs = _msgs(
        "esp32s3-usbrepl",
        bus={"uart": 2, "tx": 17, "rx": 16},
        driver="feetech_sts",
        servo_ids=[1, 2, 3],
    )
    assert any("UART2 is used twice" in m for m in msgs)
    msgs = _msgs("esp32s3-usbrepl", driver="feetech_sts", servo_ids=[1, 2, 1])
    assert msgs == ["servo 2 has the same bus id 1 as servo 0"]


# -- ucr check / ucr flash -----------------------------------------------------------------------
def test_ucr_check_refuses_the_chain_on_the_repl_uart_with_path_and_line(tmp_path) -> None:
    wiring = '\n        <uart role="upstream" id="0" tx="1" rx="3"/>'
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="pwm" board="esp32"'), wiring)
    result = run_ucr("check", str(path))
    assert result.returncode != 0 and "Traceback" not in result.stderr
    line = _line_of(path, '<uart role="upstream"')
    assert f"{path}:{line}: bendable 'segment_2': board 'esp32': UART0 is the REPL's" in (
        result.stderr
    )


def test_ucr_check_refuses_a_c3_chain_and_a_pwm_pin_twice(tmp_path) -> None:
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="pwm" board="esp32c3"'))
    result = run_ucr("check", str(path))
    assert result.returncode != 0
    assert re.search(r"robot\.ucrdf:\d+: .*esp32c3 has 2 UARTs", result.stderr), result.stderr
    wiring = '\n        <pwm index="1" pin="25"/>'
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="pwm"'), wiring)
    result = run_ucr("check", str(path))
    assert f"{path}:{_line_of(path, '<pwm index')}:" in result.stderr
    assert "GPIO25 is used twice: PWM servo 0 and PWM servo 1" in result.stderr


def test_ucr_flash_refuses_an_impossible_plan_before_touching_the_port(tmp_path) -> None:
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="feetech_sts" board="esp32"'))
    result = run_ucr("flash", "--port", "/dev/null", "--robot", str(path), "--segment", "segment_2")
    assert result.returncode == 1 and "Traceback" not in result.stderr  # the file's plan
    assert "no UART left for a serial servo bus" in result.stderr


def test_ucr_flash_refuses_a_servo_driver_override_the_board_cannot_wire() -> None:
    result = run_ucr(
        "flash",
        "--port",
        "/dev/null",
        "--robot",
        str(ROBOT),
        "--segment",
        "segment_1",
        "--servo-driver",
        "feetech_sts",
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "--servo-driver feetech_sts: board 'esp32': esp32 has no UART left" in result.stderr


def test_the_board_and_its_pins_reach_config_json(tmp_path) -> None:
    # the servos travel ±π: 360° PWM servos (the default pulse range spans only ±π/2)
    wiring = (
        '\n        <uart role="downstream" id="2" tx="4" rx="13"/>'
        f'\n        <pwm_pulse range="{2 * math.pi!r}"/>'
    )
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="pwm" board="esp32"'), wiring)
    cfg = config_for(load(path), "segment_2")
    assert cfg["board"] == "esp32"
    assert cfg["pins"]["down_tx"] == 4 and cfg["pins"]["up_tx"] == 19
    assert cfg["pwm"] == {"pins": [25, 26, 27], "min_us": 500.0, "max_us": 2500.0,
                          "range": 2 * math.pi} and cfg["bus"] is None  # fmt: skip


# -- the firmware: config.json at boot, and the emulated machine ---------------------------------
def _vm(code: str) -> str:
    return mpvm.run_code(code, paths=[REPO, REPO / "device"])


def _config_refusal(cfg: dict) -> str:
    """What config.Config says about ``cfg`` on the VM."""
    return _vm(
        "import config\ntry:\n config.Config("
        + repr(cfg)
        + ")\nexcept ValueError as e:\n print('refused:', e)\n"
    )


def test_the_segment_refuses_an_impossible_config_json_and_says_why(tmp_path) -> None:
    cfg = {"servo_driver": "pwm", "board": "esp32", "pins": {"up_uart": 0}}
    out = _config_refusal(cfg)
    assert "refused: board esp32: UART0 is the REPL's" in out
    cfg = {"servo_driver": "feetech_sts", "servos": [{"id": 4}, {"id": 4}, {"id": 5}]}
    out = _config_refusal(cfg)
    assert "servo 1 has the same bus id 4 as servo 0" in out


def test_the_emulated_machine_refuses_uarts_and_pins_the_board_lacks() -> None:
    out = _vm(
        "import emu_board, hal_unix\n"
        "from protocol import boards\n"
        "def tryit(board, f):\n"
        " m = emu_board.BoardMachine(board, boards.profile(board), {}, hal_unix._open_uart)\n"
        " try:\n  f(m)\n  print(board, 'ok')\n"
        " except ValueError as e:\n  print(board, 'refused:', e)\n"
        "tryit('esp32c3', lambda m: m.UART(2, tx=4, rx=5))\n"
        "tryit('esp32', lambda m: m.UART(0, tx=19, rx=18))\n"
        "tryit('esp32', lambda m: m.UART(1, tx=6, rx=18))\n"
        "tryit('esp32', lambda m: (m.UART(1, tx=19, rx=18), m.UART(2, tx=19, rx=16)))\n"
        "tryit('esp32', lambda m: m.UART(1, tx=34, rx=18))\n"
        "tryit('esp32s3', lambda m: m.UART(2, tx=15, rx=16))\n"
    )
    assert "esp32c3 refused: UART(2) does not exist" in out
    assert "esp32 refused: UART(0) is the REPL's on esp32" in out
    assert "GPIO6 is wired to the SPI flash on esp32" in out
    assert "GPIO19 is already UART1 TX (UART2 TX)" in out
    assert "GPIO34 is input-only on esp32" in out
    assert "esp32s3 ok" in out


def test_an_emulated_stock_c3_segment_refuses_to_start_and_says_why() -> None:
    with EmulatedChain(1, board="esp32c3") as chain:
        end = time.monotonic() + 30
        while "no UART left for the downstream port" not in chain.repl_output(0):
            assert time.monotonic() < end, chain.repl_output(0)
            time.sleep(0.1)


def test_the_emulator_gives_each_segment_its_boards_heap() -> None:
    with EmulatedChain(1, board="esp32c3-usbrepl") as chain:
        end = time.monotonic() + 30
        while chain.pid(0) is None:
            assert time.monotonic() < end
            time.sleep(0.05)
        cmdline = Path(f"/proc/{chain.pid(0)}/cmdline").read_bytes().split(b"\0")
        heap = boards.profile("esp32c3-usbrepl")["heap"] // 1024
        assert f"heapsize={heap}k".encode() in cmdline
        assert chain.board_of(0) == "esp32c3-usbrepl"


def test_ucr_emulate_refuses_an_unknown_board_in_one_line() -> None:
    result = run_ucr("emulate", "1", "--board", "esp8266", "--no-stdin")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "unknown board 'esp8266'" in result.stderr and "esp32c3" in result.stderr


def test_the_timing_model_makes_a_segment_answer_at_the_boards_speed() -> None:
    from host.link import ChainLink

    with EmulatedChain(1, timing=True, cpu_factor=100.0) as chain:
        assert chain.cpu_factor_of(0) == 100.0
        with ChainLink(chain.host_port) as link:
            end = time.monotonic() + 60
            while not link.discover(timeout=2.0):  # boot is stretched too
                assert time.monotonic() < end
            rtts = []
            for _ in range(3):
                t0 = time.monotonic()
                assert link.discover(timeout=2.0)
                rtts.append(time.monotonic() - t0)
    # a DESCRIPTOR takes the VM well over 0.15 ms to build: x100 is at least 15 ms on the board
    assert min(rtts) >= 0.015, rtts


def test_the_timing_model_does_not_stretch_the_hosts_uart_system_calls() -> None:
    """A UART call is C on the board (copies into the driver's ring buffer): the host's read and
    write system calls, slow on a loaded host, must not count as the board's compute and be
    multiplied by the CPU factor. A stand-in UART whose calls take 20 ms leaves the compute to
    stretch at what the code around them took (ms, printed)."""
    out = _vm(
        "import time, emu_board, hal_unix\n"
        "class Slow:\n"
        " f = None\n irq_set = False\n"
        " def readinto(self, b):\n  time.sleep_ms(20)\n  return 3\n"
        " def write(self, b, n=-1):\n  time.sleep_ms(20)\n  return n\n"
        "class H:\n"
        " not_compute = hal_unix.Hal.not_compute\n"
        " def stretch(self):\n  self._busy_from = time.ticks_us()\n"
        "h = H()\n"
        "u = emu_board.StretchUart(Slow(), h)\n"
        "h._busy_from = time.ticks_us()\n"
        "u.readinto(bytearray(4))\n"
        "u.write(b'abc', 3)\n"
        "print('compute', time.ticks_diff(time.ticks_us(), h._busy_from) // 1000)\n"
    )
    compute_ms = int(out.split("compute")[1].split()[0])
    assert compute_ms < 10, out  # both calls' 40 ms were left out


def test_the_timing_models_hold_sleeps_or_with_ucr_spin_hold_busy_waits() -> None:
    """1 ms of compute at CPU factor 11 holds 10 ms more, in one sleep by default; with
    UCR_SPIN_HOLD (benchmarks: the host stays hot) in a busy wait, no sleep (ms, sleeps printed)."""
    out = _vm(
        "import time as T, hal_unix\n"
        "sleeps = []\n"
        "class FT:\n"
        " ticks_us = T.ticks_us\n ticks_diff = T.ticks_diff\n ticks_add = T.ticks_add\n"
        " def sleep_us(us):\n  sleeps.append(us)\n  T.sleep_us(us)\n"
        "hal_unix.time = FT\n"
        "class H:\n"
        " stretch = hal_unix.Hal.stretch\n"
        "h = H()\n"
        "h.cpu_factor = 11.0\n"
        "for spin in (False, True):\n"
        " h.spin_hold = spin\n"
        " sleeps.clear()\n"
        " h._busy_from = T.ticks_add(T.ticks_us(), -1000)\n"
        " t0 = T.ticks_us()\n"
        " h.stretch()\n"
        " print('spin' if spin else 'sleep', T.ticks_diff(T.ticks_us(), t0) // 1000, len(sleeps))\n"
    )
    rows = {ln.split()[0]: [int(x) for x in ln.split()[1:]] for ln in out.splitlines() if ln}
    assert rows["sleep"][0] >= 10 and rows["sleep"][1] == 1, out
    assert rows["spin"][0] >= 10 and rows["spin"][1] == 0, out


def test_board_and_wiring_survive_a_write_and_parse(tmp_path) -> None:
    from ucrdf.parser import parse_string
    from ucrdf.writer import dumps

    wiring = (
        '\n        <uart role="downstream" id="2" tx="4" rx="13" baud="460800"/>'
        '\n        <pwm index="2" pin="32"/>'
        f'\n        <pwm_pulse range="{2 * math.pi!r}"/>'
    )
    path = _robot(tmp_path, ACT.replace('driver="emulated"', 'driver="pwm" board="esp32"'), wiring)
    robot = load(path)
    act = robot.bendables["segment_2"].actuation
    assert act.board == "esp32" and act.pwm_pins == {2: 32}
    assert act.uarts == {"downstream": {"id": 2, "tx": 4, "rx": 13, "baud": 460800}}
    assert parse_string(dumps(robot)) == robot
    assert config_for(robot, "segment_2")["pwm"] == {
        "pins": [25, 26, 32], "min_us": 500.0, "max_us": 2500.0, "range": 2 * math.pi
    }  # fmt: skip
