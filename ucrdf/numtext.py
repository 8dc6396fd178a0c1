"""Number text as U(C)RDF reads it: the XML Schema spellings only, and never an exception.

Python's ``float()`` and ``int()`` accept more than a C++ or ROS reader of the same file does
(``1_5``, ``infinity``, non-ASCII digits such as ``١٥``), and ``int()`` raises on more than 4300
digits. The parser, the checks and the kinematics commands read numbers through these functions
instead, so a file means the same number to every reader, or is refused. Importing this module
costs nothing (no numpy, no lxml).
"""

from __future__ import annotations

import re

__all__ = ["MAX_WHOLE_DIGITS", "number", "shown", "whole"]

#: ``xs:double`` (XML Schema 1.0): decimal or exponent notation, ``INF``, ``-INF``, ``NaN``
_DOUBLE = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|-?INF|NaN")
_INTEGER = re.compile(r"([+-]?)0*([0-9]+)")
#: XML white space, which the schema collapses around a number (not Python's wider ``strip()``)
_XML_SPACE = " \t\r\n"

#: Digits a whole number (a count, an index, a servo id, a pin, a baud rate) may have: more than
#: any of them needs, and still within the 64-bit integers a C++ reader parses them into.
MAX_WHOLE_DIGITS = 18


def number(text: str) -> float | None:
    """``text`` as a float when it is ``xs:double`` text (white space around it allowed), else
    None. ``INF``/``NaN`` read as such; whether they are allowed is the caller's check."""
    text = text.strip(_XML_SPACE)
    return float(text) if _DOUBLE.fullmatch(text) else None


def whole(text: str) -> int | None:
    """``text`` as an int when it is ``xs:integer`` text of at most :data:`MAX_WHOLE_DIGITS`
    digits (leading zeros not counted), else None."""
    m = _INTEGER.fullmatch(text.strip(_XML_SPACE))
    if m is None or len(m.group(2)) > MAX_WHOLE_DIGITS:
        return None
    return int(m.group(1) + m.group(2))


def shown(text: str, limit: int = 24) -> str:
    """``repr(text)`` for a message, cut after ``limit`` characters: a value of 5000 digits is
    named, not echoed."""
    if len(text) <= limit:
        return repr(text)
    return f"{text[:limit]!r}… ({len(text)} characters)"
