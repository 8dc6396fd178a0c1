"""Segment link protocol: COBS + CRC-16 frames carrying CBOR messages (docs/protocol.md).

The same files run on the segments (MicroPython) and on the host (CPython). Import the
submodules you need; this package file stays empty so a segment loads only what it uses:
``constants``, ``crc``, ``cobs``, ``cbor``, ``frame``, ``device`` (zero-allocation cyclic
helpers), ``messages`` (SI builders/parsers), ``errors``.
"""
