"""Helpers for the firmware tests: run code on the MicroPython VM against device/ and read JSON.

VM code runs with ``vmkit`` (loopback HAL) importable; it must leave its results in ``R``, which is
printed as JSON. Frames are built and decoded on the host with ``protocol.messages``.
"""

from __future__ import annotations

import atexit
import json
import shutil
import tempfile
from pathlib import Path

import pytest

from protocol import messages as M
from protocol.frame import FrameReader
from tools import mpvm

HERE = Path(__file__).resolve().parent
_FLASH: list[Path] = []


def vm_paths() -> list[Path]:
    """The segment's flash as ``ucr flash`` writes it and the emulator runs it (the firmware's
    modules precompiled to .mpy, tools/mpy.py), laid out once per test process, and this kit.

    A board does not compile its firmware: importing from source would bound a test by the
    compiler's peak and the fragmentation it leaves on the ESP32-sized heap, not by the firmware
    (``ucr flash --source`` is the documented fallback, docs/flashing.md)."""
    if not _FLASH:
        from tools.emulator.chain import populate_segment_dir

        flash = Path(tempfile.mkdtemp(prefix="ucr-vmflash-"))
        atexit.register(shutil.rmtree, flash, ignore_errors=True)
        populate_segment_dir(flash)
        _FLASH.append(flash)
    return [_FLASH[0], HERE]


def run_vm(code: str, timeout: float = 60.0, heap: str = mpvm.ESP32_HEAP):
    """Execute ``code`` on the VM against the precompiled firmware (``vm_paths``); return the
    JSON-decoded value of ``R``.

    The heap is ESP32-sized by default; tests that ship thousands of sample points as JSON to the
    VM pass a bigger ``heap`` (the data, not the firmware, needs it).
    """
    prog = "import json, vmkit\nR = {}\n" + code + "\nprint('@@' + json.dumps(R))\n"
    out = mpvm.run_code(prog, paths=vm_paths(), timeout=timeout, heap=heap)
    for line in out.splitlines():
        if line.startswith("@@"):
            return json.loads(line[2:])
    raise AssertionError("VM printed no result:\n" + out)


def decode(hexstr: str) -> list[dict]:
    """Wire bytes (hex) -> decoded messages (dicts from protocol.messages.decode_message)."""
    return [M.decode_message(f) for f in FrameReader().feed(bytes.fromhex(hexstr))]


def frames(hexstr: str):
    """Wire bytes (hex) -> protocol.frame.Frame list (raw header fields)."""
    return FrameReader().feed(bytes.fromhex(hexstr))


@pytest.fixture(scope="session")
def vm():
    """The VM runner (skips when no micropython binary is installed)."""
    try:
        mpvm.micropython_binary()
    except FileNotFoundError as e:
        pytest.skip(str(e))
    return run_vm
