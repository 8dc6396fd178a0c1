"""Diagnostics for U(C)RDF files: every problem is reported as ``path:line: message``.

The parser and the semantic checks collect :class:`Diagnostic` objects instead of stopping at the
first problem, then raise one :class:`UcrdfError` holding all of them, so a user fixes a file in
one pass. Commands print ``str(diagnostic)`` lines and exit 1 (never a traceback).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class Diagnostic:
    """One problem in one file. ``line`` is 1-based; 0 means "no line" (e.g. a missing file)."""

    path: str
    line: int
    message: str

    def __str__(self) -> str:
        if self.line > 0:
            return f"{self.path}:{self.line}: {self.message}"
        return f"{self.path}: {self.message}"


class UcrdfError(ValueError):
    """A U(C)RDF document is unreadable, malformed, schema-invalid or semantically wrong.

    ``diagnostics`` lists every problem found, in file order; ``str(error)`` is one
    ``path:line: message`` line per problem.
    """

    def __init__(self, diagnostics: Iterable[Diagnostic]):
        self.diagnostics: list[Diagnostic] = sorted(diagnostics, key=lambda d: (d.path, d.line))
        if not self.diagnostics:
            raise ValueError("UcrdfError needs at least one diagnostic")
        super().__init__("\n".join(str(d) for d in self.diagnostics))
