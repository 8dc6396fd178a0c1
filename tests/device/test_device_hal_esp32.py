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
