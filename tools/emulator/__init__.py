"""Emulated segment chain: the real firmware on the MicroPython unix port, linked through ptys.

``EmulatedChain(n)`` is the entry point (see docs/emulator.md); ``Pipe`` is one direction of a
link (plug, throttle, latency, corruption) and can be used on its own.
"""

from tools.emulator.chain import EmulatedChain, EmulatorError, populate_segment_dir
from tools.emulator.pipe import Pipe

__all__ = ["EmulatedChain", "EmulatorError", "Pipe", "populate_segment_dir"]
