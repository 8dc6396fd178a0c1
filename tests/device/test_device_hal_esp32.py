"""ESP32 HAL pin selection (pure logic, run on CPython with a stand-in ``machine`` module): the
classic ESP32 defaults, and a clear refusal on chips whose defaults would be their USB pins."""

from __future__ import annotations

import sys
import types
from pathlib import Path

import pytest

DEVICE = Path(__file__).resolve().parents[2] / "device"


@pytest.fixture()
def hal(monkeypatch):
    monkeypatch.setitem(sys.modules, "machine", types.ModuleType("machine"))
    monkeypatch.syspath_prepend(str(DEVICE))
    monkeypatch.delitem(sys.modules, "hal_esp32", raising=False)
    import hal_esp32

    return hal_esp32


def test_classic_esp32_uses_uart1_and_uart2_on_the_documented_pins(hal):
    p = hal.chain_pins("ESP32", None)
    assert (p["up_uart"], p["up_tx"], p["up_rx"]) == (1, 19, 18)
    assert (p["down_uart"], p["down_tx"], p["down_rx"], p["baud"]) == (2, 17, 16, 921600)


@pytest.mark.parametrize("chip", ["ESP32S3", "ESP32C3"])
def test_other_chips_must_name_their_chain_pins(hal, chip):
    with pytest.raises(ValueError, match=f"{chip}.*up_tx, up_rx, down_tx, down_rx"):
        hal.chain_pins(chip, None)
    with pytest.raises(ValueError, match="down_rx"):
        hal.chain_pins(chip, {"up_tx": 4, "up_rx": 5, "down_tx": 6})
    pins = {"up_uart": 1, "up_tx": 4, "up_rx": 5, "down_uart": 0, "down_tx": 6, "down_rx": 7}
    assert hal.chain_pins(chip, pins)["down_uart"] == 0


def test_chip_name_is_read_from_the_board_description(hal, monkeypatch):
    board = types.SimpleNamespace(machine="Generic ESP32S3 module with ESP32S3")
    monkeypatch.setattr(hal.os, "uname", lambda: board)
    assert hal.chip() == "ESP32S3"


def test_a_configuration_for_another_board_is_refused_on_this_chip(hal):
    pins = {
        "board": "esp32s3",
        "up_uart": 1,
        "up_tx": 17,
        "up_rx": 18,
        "down_uart": 2,
        "down_tx": 15,
        "down_rx": 16,
        "baud": 921600,
    }
    with pytest.raises(ValueError, match="names board 'esp32s3' .* this chip is an ESP32"):
        hal.chain_pins("ESP32", pins)
    assert hal.chain_pins("ESP32S3", pins)["down_tx"] == 15


def test_chain_uarts_deliver_bytes_as_they_arrive_for_cut_through(hal, monkeypatch):
    """Cut-through needs each byte readable when it arrives: timeout_char=0 makes the ESP32 port
    set the RX FIFO threshold to 1 (ports/esp32/machine_uart.c); the driver's default threshold
    would hold a short frame until its end plus an idle time."""
    opened = []

    class UART:
        IRQ_RX = 1

        def __init__(self, uid, **kw):
            opened.append((uid, kw))

        def irq(self, handler=None, trigger=0):
            pass

    class Poll:
        def register(self, obj, mask):
            pass

    monkeypatch.setattr(hal.machine, "UART", UART, raising=False)
    monkeypatch.setattr(hal.select, "poll", Poll)
    monkeypatch.setattr(hal, "chip", lambda: "ESP32")
    monkeypatch.setattr(hal.time, "ticks_ms", lambda: 0, raising=False)
    monkeypatch.setattr(hal.machine, "freq", _Freq(), raising=False)
    assert hal.Hal(None).mhz == 240
    assert [uid for uid, _ in opened] == [1, 2]
    for _, kw in opened:
        assert kw["timeout_char"] == 0 and kw["timeout"] == 0 and kw["rxbuf"] >= 253


class _Freq:
    """machine.freq of a stock build: starts at ESP-IDF's default 160 MHz."""

    def __init__(self, hz=160000000):
        self.hz = hz
        self.calls = []

    def __call__(self, hz=None):
        if hz is None:
            return self.hz
        self.calls.append(hz)
        self.hz = hz
        return None


@pytest.mark.parametrize(
    ("chip", "board", "mhz"),
    [("ESP32", None, 240), ("ESP32", "esp32", 240), ("ESP32S3", "esp32s3", 240),
     ("ESP32C3", "esp32c3-usbrepl", 160), ("ESP32S3", None, 0)],
)  # fmt: skip
def test_the_cpu_runs_at_the_board_profiles_clock(hal, monkeypatch, chip, board, mhz):
    """A stock ESP32 build boots at 160 MHz; the firmware's cycle budget (and the emulator's CPU
    factor, protocol/boards.py) assumes the profile's clock, so the HAL sets it at boot."""
    freq = _Freq()
    monkeypatch.setattr(hal.machine, "freq", freq, raising=False)
    assert hal.set_clock(chip, board) == mhz
    if mhz == 160 or not mhz:
        assert freq.calls == []  # already there, or unknown chip: left alone
    else:
        assert freq.calls == [mhz * 1000000]
    # the profile's score is the one at that clock (pystone 1.2, docs/emulator.md)
    from protocol import boards

    if board:
        assert boards.profile(board)["mhz"] == mhz


# -- a configuration this chip cannot run (review of issue 11: "never substitute defaults") -------
def _boot(hal, monkeypatch, tmp_path, chip, config):
    """main.build on an ESP32 of ``chip`` with ``config`` as config.json: (UARTs opened as
    (id, tx, rx), PWM pins driven, the segment)."""
    import json

    opened = []
    pwm = []

    class UART:
        IRQ_RX = 1

        def __init__(self, uid, **kw):
            opened.append((uid, kw["tx"], kw["rx"]))

        def irq(self, handler=None, trigger=0):
            pass

        def any(self):
            return 0

        def readinto(self, buf, n=None):
            return None

        def write(self, buf, n=None):
            return n

    class Poll:
        def register(self, obj, mask):
            pass

    m = hal.machine
    monkeypatch.setattr(m, "UART", UART, raising=False)
    monkeypatch.setattr(m, "Pin", lambda n, *a, **k: n, raising=False)
    monkeypatch.setattr(m, "PWM", lambda pin, **k: pwm.append(pin), raising=False)
    monkeypatch.setattr(m, "freq", _Freq(), raising=False)
    monkeypatch.setattr(m, "unique_id", lambda: b"\x01\x02\x03\x04\x05\x06", raising=False)
    monkeypatch.setattr(hal.select, "poll", Poll)
    monkeypatch.setattr(hal, "chip", lambda: chip)
    for name in ("ticks_ms", "ticks_us"):
        monkeypatch.setattr(hal.time, name, lambda: 0, raising=False)
    monkeypatch.setattr(hal.time, "ticks_diff", lambda a, b: a - b, raising=False)
    (tmp_path / "config.json").write_text(json.dumps(config))
    monkeypatch.chdir(tmp_path)
    import main

    monkeypatch.setattr(main, "_hal_module", lambda: hal)
    _, seg = main.build()
    return opened, pwm, seg


_SERVOS = [{"id": i, "min_angle": -1.0, "max_angle": 1.0} for i in (1, 2, 3)]


def test_a_rejected_config_keeps_its_board_and_chain_pins_and_holds(hal, monkeypatch, tmp_path):
    """A C3 whose config.json is refused (kappa_max 0) rebuilt the plan for board 'esp32' and
    died at boot ("names board 'esp32' ... this chip is an ESP32C3"): nothing reached the host."""
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32c3-usbrepl", "kappa_max": 0}
    cfg.update(servos=_SERVOS, pins={"up_tx": 1, "up_rx": 3})
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32C3", cfg)
    assert opened == [(1, 1, 3), (0, 21, 20)]  # the configured chain, not esp32's defaults
    assert pwm == []  # a refused configuration drives no servo pin
    assert seg.cfg.error.startswith("config.json rejected: kappa_max")
    assert seg.status() & 0x21 == 0x21  # HOLD + UNCONFIGURED


def test_a_rejected_config_on_a_classic_esp32_opens_the_configured_pins(hal, monkeypatch, tmp_path):
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32", "kappa_max": -1.0}
    cfg.update(servos=_SERVOS, pins={"down_tx": 23, "down_rx": 22})
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32", cfg)
    assert opened == [(1, 19, 18), (2, 23, 22)]  # not the default 17/16
    assert pwm == [] and "kappa_max" in seg.cfg.error


def test_a_plan_this_chip_cannot_run_falls_back_to_the_chips_own_board_and_says_why(
    hal, monkeypatch, tmp_path
):
    # a valid configuration made for a classic ESP32, flashed on a C3
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32", "servos": _SERVOS}
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32C3", cfg)
    assert opened == [(1, 5, 4)]  # the C3's own upstream; a stock C3 has no UART left downstream
    assert pwm == []
    assert "names board 'esp32'" in seg.cfg.error and "ESP32C3" in seg.cfg.error
    assert seg.status() & 0x01  # HOLD
    # a refused configuration whose plan is unusable (a stock C3 cannot chain): the chip's own
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32c3", "servos": _SERVOS}
    (tmp_path / "b").mkdir()
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path / "b", "ESP32C3", cfg)
    assert opened == [(1, 5, 4)] and pwm == []
    assert seg.cfg.error.startswith("config.json rejected: board esp32c3")


def test_a_refused_config_never_opens_a_chain_uart_on_one_of_its_servo_pins(
    hal, monkeypatch, tmp_path
):
    """Defect (review): a refused config kept its chain after checking it alone, so a downstream
    TX on GPIO25, the first PWM servo's default pin, was opened: UART bytes on a servo's signal
    wire. Now the kept chain must avoid the config's servo pins, else the board's own is used."""
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32", "servos": _SERVOS}
    cfg["pins"] = {"down_tx": 25}
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32", cfg)
    assert opened == [(1, 19, 18), (2, 17, 16)] and pwm == []
    assert seg.cfg.error.startswith("config.json rejected")


def test_a_refused_config_whose_servos_sit_on_the_chain_pins_opens_no_uart_on_them(
    hal, monkeypatch, tmp_path
):
    """PWM servos wired to the default chain pins (19, 17): no upstream is possible without
    driving one, so the segment opens none and stays silent (saying why on its console)."""
    cfg = {"name": "s", "servo_driver": "pwm", "board": "esp32", "servos": _SERVOS}
    cfg["pwm"] = {"pins": [19, 26, 27]}
    with pytest.raises(ValueError, match="servo pins"):
        _boot(hal, monkeypatch, tmp_path, "ESP32", cfg)
    cfg["pwm"] = {"pins": [17, 26, 27]}  # only the downstream's: the segment is the tip
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32", cfg)
    assert opened == [(1, 19, 18)] and pwm == []


def test_a_calibration_beside_a_config_json_that_is_not_an_object_is_refused_not_a_crash(
    hal, monkeypatch, tmp_path
):
    """Defect (review): with calibration.json present, a config.json holding a JSON list made
    the merge raise AttributeError, which escaped main.build: the chain was dead, no reason."""
    import json

    (tmp_path / "calibration.json").write_text(
        json.dumps({"version": 1, "servos": [{"zero_offset": 0.0, "direction": 1}] * 3})
    )
    opened, pwm, seg = _boot(hal, monkeypatch, tmp_path, "ESP32", [1, 2])
    assert opened == [(1, 19, 18), (2, 17, 16)] and pwm == []
    assert seg.cfg.error.startswith("config.json rejected")
