"""`ucr flash` onto a segment that runs a hardware watchdog (config ``hw_watchdog_ms``).

A ``machine.WDT`` cannot be stopped (MicroPython docs), and the emulated one (``wdt.EmulatedWdt``)
keeps watching after Ctrl-C in the same way. ``ucr flash`` stops ``main.py`` with Ctrl-C: nothing
fed the watchdog any more, the board reset in the middle of the copy, the flash failed and the
next boot reported FAULT WDT_RESET (review 2026-11-28, A). Now the firmware keeps the watchdog
fed from a ``machine.Timer`` while the REPL runs (``wdt.keep_fed``; on the emulated board the
timer of ``emu_board.BoardMachine``).
"""

from __future__ import annotations

import time

import pytest
import serial

from host.link import ChainLink
from tools.emulator import EmulatedChain, default_config
from tools.flash import flash

pytestmark = pytest.mark.timeout(240)

WDT_MS = 300  # short, so a starved watchdog would reset the segment early in the copy


def _config(name: str) -> dict:
    cfg = default_config()
    cfg.update(name=name, hw_watchdog_ms=WDT_MS, watchdog_ms=60000)
    return cfg


def _wdt_kills(chain: EmulatedChain) -> int:
    """Resets of segment 0 by its (emulated) watchdog: the process killed with SIGKILL."""
    return chain.stats()["segments"][0]["exit_codes"].count(-9)


def test_a_segment_with_a_hardware_watchdog_can_be_flashed() -> None:
    with EmulatedChain(1, config_for=[_config("before")]) as chain:
        with ChainLink(chain.host_port) as link:
            end = time.monotonic() + 30
            while not link.discover(timeout=0.3) and time.monotonic() < end:
                time.sleep(0.1)
        restarts = chain.stats()["segments"][0]["restarts"]
        lines: list[str] = []
        flash(chain.repl_port(0), _config("after"), log=lines.append)  # raises FlashError
        assert any("verified" in x for x in lines), lines
        chain.wait_restarts(0, restarts + 1, timeout=20)
        assert _wdt_kills(chain) == 0, chain.repl_output(0)[-3000:]
        assert not (chain.segment_dir(0) / "wdt_reset").exists()
        with ChainLink(chain.host_port) as link:
            end = time.monotonic() + 30
            descs: list = []
            while not descs and time.monotonic() < end:
                descs = link.discover(timeout=0.3)
            assert descs and descs[0]["name"] == "after"
            st = link.heartbeat(timeout=0.5)[0]
        assert st is not None and "FAULT" not in st["status"]  # no WDT_RESET at this boot


def test_the_repl_outlives_the_watchdog_after_ctrl_c() -> None:
    """Ctrl-C, then the REPL idles for several watchdog periods: no reset, the REPL answers."""
    with EmulatedChain(1, config_for=[_config("idle")]) as chain:
        time.sleep(1.0)  # booted, the loop feeding the watchdog
        kills = _wdt_kills(chain)
        with serial.Serial(chain.repl_port(0), 115200, timeout=0.2) as repl:
            repl.write(b"\r\x03\x03")
            time.sleep(8 * WDT_MS / 1000)
            repl.reset_input_buffer()
            repl.write(b"print(6 * 7)\r")
            out = b""
            end = time.monotonic() + 5
            while b"42" not in out and time.monotonic() < end:
                out += repl.read(256)
        assert b"42" in out, chain.repl_output(0)[-2000:]
        assert _wdt_kills(chain) == kills
        assert not (chain.segment_dir(0) / "wdt_reset").exists()
