"""What every check of ``ucr doctor`` shares: the :class:`Finding` it returns, the segment
PARAM ids it reads (docs/firmware.md) and reading one (host/doctor_checks.py,
host/doctor_telemetry.py, host/doctor_config.py)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# parameter ids (docs/firmware.md)
P_WATCHDOG_MS = 0
P_CRC_ERRORS = 7
P_FRAMING_ERRORS = 8
P_DROPPED = 9
P_SERVO_FAULTS = 12
P_CYCLE_US = 13
P_OVERRUNS = 14
P_CONFIG_ERROR = 16
P_FAULT = 20
P_FAULT_COUNT = 21
P_SERVO_TELEMETRY = 22
P_CPU_LOAD = 23
P_TICK_MS = 24


@dataclass
class Finding:
    """One check's result. ``level``: ok | warning | error; ``fix`` says what to do about it."""

    check: str
    level: str
    message: str
    fix: str = ""
    position: int | None = None


def _param(link: Any, pos: int, pid: int, uid: str | None) -> Any:
    """PARAM ``pid`` of the segment at ``pos`` (read-only), within 0.5 s."""
    return link.param_get(pos, pid, uid, timeout=0.5)
