"""The ``ucr calibrate`` terminal UI, driven by textual's test pilot on the emulated chain: keys
jog a servo and persist, and the hold key stops a running step at once (the segment holds)."""

from __future__ import annotations

import asyncio
import time

import pytest

pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")

from test_calibrate import _config, _discover  # noqa: E402

from host.calibrate import Session  # noqa: E402
from host.calibrate_tui import CalibrateApp  # noqa: E402
from host.link import ChainLink  # noqa: E402
from protocol import calibration as cal  # noqa: E402
from protocol.constants import T_CALIBRATE, T_CALIBRATION  # noqa: E402
from tools.emulator import EmulatedChain  # noqa: E402


async def _idle(app: CalibrateApp, pilot, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    await pilot.pause(0.2)
    while app.busy:
        assert time.monotonic() < end, "the step did not finish"
        await pilot.pause(0.1)


def _read(link: ChainLink) -> dict:
    reply = link.request(0, T_CALIBRATE, cal.calibrate_payload(cal.ACTION_READ), T_CALIBRATION)
    return cal.decode_calibration(reply)


def test_tui_keys_jog_a_servo_persist_it_and_hold_at_once() -> None:
    with EmulatedChain(1, config_for=[_config()]) as chain:
        with ChainLink(chain.host_port) as link:
            desc = _discover(link)[0]
            session = Session(link, 0, 1, desc, say=lambda _line: None)
            before = list(session.zeros)
            app = CalibrateApp(session)

            async def drive() -> None:
                async with app.run_test() as pilot:
                    await pilot.press("1", "plus")  # servo 1, one jog step in
                    await _idle(app, pilot)
                    await pilot.press("p")
                    await _idle(app, pilot)
                    await pilot.press("d")  # a long step ...
                    await pilot.pause(0.5)
                    assert app.busy
                    await pilot.press("space")  # ... held at once
                    await _idle(app, pilot, timeout=5.0)
                    await pilot.press("q")

            asyncio.run(drive())
            text = "\n".join(app.lines)
            after = _read(link)
            status = link.heartbeat(expected=1)[0]["status"]
    assert "jog: servo 1 by" in text and "persist: done" in text
    assert after["stored"]
    assert after["zero_offsets"][1] == pytest.approx(before[1] + 0.02 * after["directions"][1])
    assert "HOLD: the segment holds" in text and "stopped: the segment holds" in text
    assert "HOLD" in status


def test_ctrl_c_in_the_tui_holds_and_quits() -> None:
    """New-user audit: textual 8 maps Ctrl-C to a "press ctrl+q to quit" prompt, so Ctrl-C
    neither held the segment nor quit (docs/commissioning.md promises both)."""

    class Stub:
        def __init__(self) -> None:
            self.stops = 0
            self.position, self.n, self.zeros, self.dirs = 0, 3, [0.0, 0.0, 0.0], [1, 1, 1]

        def stop(self) -> None:
            self.stops += 1

        def __getattr__(self, name):
            return lambda *a, **k: None

    stub = Stub()
    app = CalibrateApp(stub)  # type: ignore[arg-type]

    async def drive() -> None:
        async with app.run_test() as pilot:
            await pilot.pause(0.2)
            await pilot.press("ctrl+c")
            await pilot.pause(0.5)

    asyncio.run(drive())
    assert stub.stops >= 1 and not app.is_running
