"""Helpers for the firmware tests: run code on the MicroPython VM against device/ and read JSON.

VM code runs with ``vmkit`` (loopback HAL) importable; it must leave its results in ``R``, which is
printed as JSON. Frames are built and decoded on the host with ``protocol.messages``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from protocol import messages as M
from protocol.frame import FrameReader
from tools import mpvm

HERE = Path(__file__).resolve().parent
VM_PATHS = [mpvm.REPO, mpvm.REPO / "device", HERE]


def run_vm(code: str, timeout: float = 60.0, heap: str = mpvm.ESP32_HEAP):
    """Execute ``code`` on the VM; return the JSON-decoded value of ``R``.

    The heap is ESP32-sized by default; tests that ship thousands of sample points as JSON to the
    VM pass a bigger ``heap`` (the data, not the firmware, needs it).
    """
    prog = "import json, vmkit\nR = {}\n" + code + "\nprint('@@' + json.dumps(R))\n"
    out = mpvm.run_code(prog, paths=VM_PATHS, timeout=timeout, heap=heap)
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
