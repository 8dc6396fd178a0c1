"""The last line of `ucr flash`: what was measured, and the 115200-baud floor only where the
REPL really is a 115200-baud UART (not a native-USB REPL, not an emulated segment's pty)."""

from __future__ import annotations

import os
import pty

import pytest

from tools.emulator import EmulatedChain
from tools.flash import flash, summary_line


@pytest.fixture
def uart_port(tmp_path):
    """A path that is no pty (as /dev/ttyUSB0 would be); the summary only looks at its name."""
    p = tmp_path / "ttyUSB0"
    p.write_text("")
    return str(p)


def test_a_native_usb_repl_gets_no_115200_baud_floor(uart_port) -> None:
    line = summary_line(38, 2.4, 300000, uart_port, {"board": "esp32s3-usbrepl"})
    assert "115200" not in line and "at least" not in line
    assert line.startswith("flashed 38 files in 2.4 s (300000 bytes over the REPL, 125.0 kB/s")


def test_a_serial_bus_segment_defaults_to_the_native_usb_board(uart_port) -> None:
    line = summary_line(38, 30.0, 300000, uart_port, {"servo_driver": "feetech_sts"})
    assert "115200" not in line


def test_a_uart_repl_gets_the_floor_it_really_has(uart_port) -> None:
    line = summary_line(38, 30.0, 300000, uart_port, {"board": "esp32"})
    assert "a 115200-baud UART REPL needs at least 26.0 s" in line


def test_an_emulated_pty_or_url_gets_no_floor() -> None:
    master, slave = pty.openpty()
    try:
        name = os.ttyname(slave)
        assert "115200" not in summary_line(3, 1.0, 1000, name, {"board": "esp32"})
    finally:
        os.close(master)
        os.close(slave)
    assert "115200" not in summary_line(3, 1.0, 1000, "socket://x:1", {})


def test_flashing_an_emulated_segment_says_nothing_it_did_not_measure() -> None:
    with EmulatedChain(1) as chain:
        lines: list[str] = []
        flash(chain.repl_port(0), {"name": "s", "watchdog_ms": 250}, log=lines.append)
    last = lines[-1]
    assert last.startswith("flashed ") and "bytes over the REPL" in last and "kB/s" in last
    assert "at least" not in last and "115200" not in last
