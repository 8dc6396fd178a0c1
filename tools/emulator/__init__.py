"""Emulated segment chain: the real firmware on the MicroPython unix port, linked through ptys.

``EmulatedChain(n)`` is the entry point (see docs/emulator.md); ``Pipe`` is one direction of a
link (plug, throttle, latency, corruption) and can be used on its own; ``EmulatorProcess(n)``
runs ``ucr emulate`` in a process of its own (benchmarks of the host side).
"""

from tools.emulator.chain import (
    NO_CONFIG,
    EmulatedChain,
    EmulatorError,
    default_config,
    populate_segment_dir,
)
from tools.emulator.pipe import Pipe
from tools.emulator.process import EmulatorProcess

__all__ = [
    "EmulatedChain",
    "EmulatorError",
    "EmulatorProcess",
    "NO_CONFIG",
    "Pipe",
    "default_config",
    "populate_segment_dir",
]
