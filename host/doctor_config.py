"""``ucr doctor``: the flashed configuration against the U(C)RDF, by hash and by board.

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
