"""Write a segment's calibration into the robot's U(C)RDF (its ``<servo>`` elements).

The U(C)RDF stays the single source of truth: the calibration goes into the ``zero_offset`` and
``direction`` attributes of the bendable's ``<servo index=…>`` elements, changing nothing else in
the file (comments and layout stay). The new file is checked as ``ucr check`` checks it (errors
``path:line: message``) before it replaces the old one atomically; a file that would not pass is
never written. Afterwards ``ucr flash`` writes the same values into config.json, and the
configuration hash the segment reports equals the one computed from the file (``ucr doctor``).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

from host.errors import not_utf8
from ucrdf.errors import UcrdfError

_ATTR = r'(\s{name}\s*=\s*)(["\'])(.*?)\2'


class RobotFileError(ValueError):
    """The robot file cannot take this calibration (message says where and why)."""


def _set_attr(tag: str, name: str, value: str) -> str:
    pat = re.compile(_ATTR.format(name=re.escape(name)))
    if pat.search(tag):
        return pat.sub(lambda m: f"{m.group(1)}{m.group(2)}{value}{m.group(2)}", tag, count=1)
    end = tag.rstrip(">").rstrip("/").rstrip()
    close = tag[len(end) :]
    return f'{end} {name}="{value}"{close.lstrip() if close.strip() else close}'


def updated_text(text: str, bendable: str, zeros: list[float], dirs: list[int]) -> str:
    """``text`` with servo i of ``bendable`` at zero offset ``zeros[i]`` and ``dirs[i]``."""
    m = re.search(r"<bendable\b[^>]*\bname\s*=\s*([\"'])" + re.escape(bendable) + r"\1", text)
    if m is None:
        raise RobotFileError(f"no <bendable name={bendable!r}> in the robot file")
    end = text.find("</bendable>", m.end())
    if end < 0:
        raise RobotFileError(f"<bendable name={bendable!r}> is not closed")
    block = text[m.start() : end]
    seen: set[int] = set()

    def fix(sm: re.Match[str]) -> str:
        tag = sm.group(0)
        im = re.search(_ATTR.format(name="index"), tag)
        if im is None:
            return tag
        try:
            i = int(im.group(3))
        except ValueError:
            return tag
        if not 0 <= i < len(zeros):
            return tag
        seen.add(i)
        tag = _set_attr(tag, "zero_offset", f"{zeros[i]:.4f}")
        return _set_attr(tag, "direction", str(int(dirs[i])))

    new_block = re.sub(r"<servo\b[^>]*>", fix, block)
    missing = sorted(set(range(len(zeros))) - seen)
    if missing:
        raise RobotFileError(
            f"bendable {bendable!r} has no <servo index=…> for servo(s) "
            f"{', '.join(map(str, missing))}: add one <servo> per tendon to the <actuation>"
        )
    return text[: m.start()] + new_block + text[end:]


def _read(p: Path) -> str:
    """The robot file's text; RobotFileError (one line naming the file) if it cannot be read
    or is not UTF-8 (a UnicodeDecodeError was a traceback)."""
    try:
        return p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise RobotFileError(f"{p}: cannot read the robot file: {not_utf8(exc)}") from None
    except OSError as exc:
        raise RobotFileError(f"{p}: cannot read the robot file: {exc.strerror or exc}") from None


def _writable_problem(p: Path) -> str | None:
    """Why :func:`write` could not replace ``p``, or None. It writes a temporary file in the
    file's directory and renames it over the file, so the directory must take a new file; and
    a file made read-only is not replaced behind its owner's back."""
    folder = p.parent
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"its directory {folder} is not writable (a new file cannot be made there)"
    if not os.access(p, os.W_OK):
        return "the file is not writable"
    return None


def check(path: str | Path, bendable: str, zeros: list[float], dirs: list[int]) -> None:
    """Would :func:`write` succeed? The file is read, its directory and the file checked to be
    writable, the file given this calibration in memory and checked as ``ucr check`` checks it;
    nothing is written. ``ucr calibrate --robot`` calls it before the segment moves, so a file
    that cannot take the result is refused up front, not after the calibration was already
    stored on the segment (a read-only file used to fail only at persist, after the segment had
    stored it). RobotFileError says why not."""
    from ucrdf.parser import parse_string  # noqa: PLC0415 - lxml only when checking

    p = Path(path)
    text = _read(p)
    problem = _writable_problem(p)
    if problem is not None:
        raise RobotFileError(f"{p}: cannot write the calibration into the robot file: {problem}")
    try:
        new = updated_text(text, bendable, zeros, dirs)
    except RobotFileError as exc:
        raise RobotFileError(f"{p}: {exc}") from None
    try:
        parse_string(new, source=str(p))
    except UcrdfError as exc:
        shown = "; ".join(str(d) for d in exc.diagnostics)
        raise RobotFileError(f"the calibrated file would not pass `ucr check`: {shown}") from None


def write(path: str | Path, bendable: str, zeros: list[float], dirs: list[int]) -> Path:
    """Put the calibration into the robot file at ``path``; checked, then replaced atomically.
    A file system refusing it (permissions changed since :func:`check`, a full disk) is a
    RobotFileError naming the file, one line: the segment already stored the calibration, so the
    message must say the file lacks it rather than end in a traceback."""
    p = Path(path)
    try:
        return _write(p, bendable, zeros, dirs)
    except OSError as exc:
        raise RobotFileError(f"{p}: cannot write the robot file: {exc.strerror or exc}") from None


def _write(p: Path, bendable: str, zeros: list[float], dirs: list[int]) -> Path:
    from ucrdf.parser import load  # noqa: PLC0415 - lxml only when writing

    new = updated_text(_read(p), bendable, zeros, dirs)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(new)
        try:
            load(tmp)
        except UcrdfError as exc:
            shown = "; ".join(str(d).replace(tmp, str(p)) for d in exc.diagnostics)
            raise RobotFileError(
                f"the calibrated file would not pass `ucr check`: {shown}"
            ) from None
        os.chmod(tmp, p.stat().st_mode & 0o777)
        os.replace(tmp, p)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return p
