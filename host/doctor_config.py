"""``ucr doctor``: the chain against the U(C)RDF: its segments (count, model, geometry, limits,
pinned uids, names), and the flashed configuration by hash and by board.

The configuration hash (descriptor key 17, protocol/confighash.py) covers geometry, limits,
servo ids, the calibration (zero offsets, directions) and the safety params (watchdog_ms,
tick_ms, hw_watchdog_ms, fault_action) where they are not the firmware's defaults: a segment
flashed from an older U(C)RDF, or calibrated since without the robot file being updated, shows a
different hash even when only one zero offset differs. The board a segment reports (CALIBRATE
read, read-only) must be the ``<actuation board=…>`` of its bendable (protocol/boards.py
profiles).
"""

from __future__ import annotations

from typing import Any

from host.doctor_checks import Finding
from host.positions import label as position_label
from host.positions import labels as position_labels
from protocol import calibration as cal
from protocol.constants import T_CALIBRATE, T_CALIBRATION

_FIX_STALE = (
    "stale flash: reflash the segment from this U(C)RDF (`ucr flash --robot ... --segment ...`); "
    "if it was calibrated since, write the calibration into the U(C)RDF "
    "(`ucr calibrate --robot ...`)"
)


def _bendables(robot_path: str) -> list[tuple[Any, dict | None]] | None:
    """(bendable, the configuration ``ucr flash`` writes for it, hashed part only) per segment of
    the chain, in chain order; None when the file does not load (check_robot reports it). The
    configuration is None for a bendable without tendons or with hardware params the firmware
    could not run (``ucr check`` reports those)."""
    from host.topology import chain_bendables  # noqa: PLC0415
    from ucrdf.checks import (  # noqa: PLC0415
        DEFAULT_WATCHDOG_MS,
        segment_config,
        segment_hardware_params,
    )
    from ucrdf.parser import load  # noqa: PLC0415

    try:
        robot = load(robot_path)
    except Exception:  # noqa: BLE001 - check_robot reports the file's errors
        return None
    out = []
    for name in chain_bendables(robot):
        b = robot.bendables[name]
        flashed = None
        if b.actuation is not None:
            try:
                params = segment_hardware_params(robot, b)
            except ValueError:
                params = None
            if params is not None:
                watchdog = params.pop("watchdog_ms", DEFAULT_WATCHDOG_MS)
                flashed = {**segment_config(b, watchdog), **params}
        out.append((b, flashed))
    return out


def check_config_hash(robot_path: str, descs: list[dict]) -> list[Finding]:
    """Each segment's configuration hash against the one its bendable's configuration has."""
    bendables = _bendables(robot_path)
    if bendables is None:
        return []
    out = []
    for d, (b, flashed) in zip(descs, bendables, strict=False):
        pos = d.get("position")
        have = d.get("config_hash")
        if have is None:
            out.append(
                Finding("config_hash", "warning", "the firmware reports no hash", "update it", pos)
            )
            continue
        if flashed is None:
            continue
        want = cal.config_hash(flashed)
        if have == want:
            out.append(Finding("config_hash", "ok", f"{b.name}: hash {have:08x}", position=pos))
        elif (
            d.get("servo_driver") not in (None, b.actuation.driver)
            and cal.config_hash({**flashed, "servo_driver": d["servo_driver"]}) == have
        ):
            # the driver alone differs (the hash covers it): a `--servo-driver` override (an
            # emulator) is not a stale flash
            out.append(
                Finding(
                    "config_hash",
                    "warning",
                    f"{b.name}: the segment runs servo driver {d['servo_driver']!r}, the U(C)RDF "
                    f"says {b.actuation.driver!r} (hash {have:08x} vs {want:08x}; the hash covers "
                    "the driver)",
                    "expected after `ucr flash --servo-driver` or on an emulator; else reflash "
                    "without the override",
                    pos,
                )
            )
        else:
            out.append(
                Finding(
                    "config_hash",
                    "error",
                    f"{b.name}: the segment runs configuration {have:08x}, the U(C)RDF gives "
                    f"{want:08x} (geometry, limits, servo ids, zero offsets, directions, or the "
                    "watchdog, tick or fault action differ)",
                    _FIX_STALE,
                    pos,
                )
            )
    return out


def check_board(link: Any, robot_path: str, descs: list[dict]) -> list[Finding]:
    """The board each segment says it runs on against its bendable's ``<actuation board=…>``."""
    from host.link import LinkError  # noqa: PLC0415
    from ucrdf.boards import board_of  # noqa: PLC0415

    bendables = _bendables(robot_path)
    if bendables is None:
        return []
    out = []
    for d, (b, _) in zip(descs, bendables, strict=False):
        pos = d.get("position")
        if b.actuation is None:
            continue
        payload = cal.calibrate_payload(cal.ACTION_READ, uid=d.get("uid"))
        try:
            got = cal.decode_calibration(
                link.request(pos, T_CALIBRATE, payload, T_CALIBRATION, 0.5)
            )
        except (LinkError, ValueError) as exc:
            out.append(Finding("board", "warning", f"board not reported: {exc}", "", pos))
            continue
        want = board_of(b.actuation)
        have = got.get("board")
        if have == want:
            out.append(Finding("board", "ok", f"board {have}", position=pos))
        else:
            out.append(
                Finding(
                    "board",
                    "error",
                    f"the segment runs as board {have!r}, the U(C)RDF says {want!r}",
                    "flash the segment with the configuration of its board (`ucr flash`), or "
                    "fix <actuation board=…> (`ucr check` shows each board's pins and UARTs)",
                    pos,
                )
            )
    return out


def check_robot(robot_path: str, descs: list[dict]) -> list[Finding]:
    """The chain against the U(C)RDF: count, model, geometry, limits, pinned uids."""
    from host.topology import compare  # noqa: PLC0415
    from ucrdf.parser import load  # noqa: PLC0415

    try:
        robot = load(robot_path)
    except Exception as exc:  # noqa: BLE001 - shown as a finding, never a traceback
        return [Finding("robot", "error", str(exc), "fix the U(C)RDF (`ucr check` it)")]
    cmp = compare(robot, descs)
    out = _same_names(descs)
    if cmp.ok:
        return [*out, Finding("robot", "ok", cmp.text())]
    found = len(descs)
    for d in cmp.differences:
        if d.kind == "count" and found < len(cmp.expected):
            last, first_missing = position_label(found - 1), position_label(found)
            fix = (
                f"no answer beyond {last}: check the cable from {last} to {first_missing} and "
                f"the power of {cmp.expected[found]} (a segment that does not answer cuts the "
                "chain there)"
            )
            if found and descs[found - 1].get("config_error"):
                # a refused segment may open no downstream UART (its pins unknown, or a board
                # whose one free UART is upstream, e.g. an esp32c3): the cut may be its own
                fix = (
                    f"{last} refused its configuration ({descs[found - 1]['config_error']}) and "
                    "may not forward the chain beyond itself: fix and reflash it first "
                    f"(`ucr flash ... --segment {cmp.expected[found - 1]}`); if the chain is still "
                    f"cut, {fix}"
                )
        elif d.kind == "count":
            fix = "add the extra segment(s) to the U(C)RDF, or let `ucr daemon --adopt` write one"
        else:
            fix = (
                "stale flash: reflash the segment from this U(C)RDF "
                "(`ucr flash --robot ... --segment ...`), "
                "or edit the U(C)RDF to match (`ucr daemon --adopt` writes one)"
            )
        out.append(
            Finding("robot", "error" if d.blocking else "warning", d.message, fix, d.position)
        )
    return out


def _same_names(descs: list[dict]) -> list[Finding]:
    """Two segments that call themselves by one name (one flashed with the other's bendable)."""
    at: dict[str, list[int]] = {}
    for i, d in enumerate(descs):
        if isinstance(d.get("name"), str):
            at.setdefault(d["name"], []).append(i)
    return [
        Finding(
            "robot",
            "error",
            f"{position_labels(indices)} all call themselves {name!r}",
            "each segment needs its own bendable's configuration: reflash the wrong one "
            "(`ucr flash --robot ... --segment NAME` with the bendable at its position)",
        )
        for name, indices in at.items()
        if len(indices) > 1
    ]
