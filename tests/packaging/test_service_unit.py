"""host/ucr-daemon.service: valid for systemd, unprivileged, sandboxed (issue 13, finding 6);
host/ucr-zenoh.service, the other unit the project installs, held to the same verify and
exposure checks (it rated 3.2: no syscall filter, W+X memory allowed, the process tree visible).

`systemd-analyze verify` runs against a scratch root holding this machine's system units, the
unit, and an executable at the unit's ExecStart path (verify checks that it exists);
`systemd-analyze security --offline=true` rates the sandbox (0 = locked down, 10 = exposed).
Skips with the reason where systemd-analyze is missing.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "host" / "ucr-daemon.service"
ZENOH_UNIT = REPO / "host" / "ucr-zenoh.service"
UNITS = pytest.mark.parametrize("unit", [UNIT, ZENOH_UNIT], ids=lambda u: u.name)
MAX_EXPOSURE = 3.0

pytestmark = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None,
    reason="systemd-analyze not installed (Debian package systemd)",
)


def service_section(unit: Path = UNIT) -> dict[str, list[str]]:
    section, out = None, {}
    for line in unit.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line
        elif section == "[Service]":
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


def exposure(unit: Path) -> tuple[float, str]:
    proc = subprocess.run(
        ["systemd-analyze", "security", "--offline=true", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    out = proc.stdout + proc.stderr
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+)", out)
    assert m, out
    return float(m.group(1)), out


@UNITS
def test_unit_passes_systemd_analyze_verify(tmp_path, unit) -> None:
    root = tmp_path / "root"
    units = Path("/lib/systemd/system")
    if not (units / "sysinit.target").exists():
        pytest.skip(f"no system units in {units} to verify against")
    shutil.copytree(units, root / "usr" / "lib" / "systemd" / "system", symlinks=True)
    (root / "etc" / "systemd" / "system").mkdir(parents=True)
    shutil.copy(unit, root / "etc" / "systemd" / "system" / unit.name)
    exe = root / service_section(unit)["ExecStart"][-1].split()[0].lstrip("/")
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    proc = subprocess.run(
        ["systemd-analyze", "verify", f"--root={root}", unit.name],
        capture_output=True,
        text=True,
        timeout=120,
    )
    # verify exits 0 on unknown keys and prints them: any output is a defect
    assert proc.returncode == 0 and not (proc.stdout + proc.stderr).strip(), (
        proc.stdout + proc.stderr
    )


@UNITS
def test_unit_sandbox_rates_at_most_3_in_systemd_analyze_security(unit) -> None:
    """The daemon's unit rated 8.5 EXPOSED (ProtectSystem=full, no device, address-family or
    syscall restrictions, no resource limits); the Zenoh bridge's 3.2."""
    level, out = exposure(unit)
    assert level <= MAX_EXPOSURE, f"exposure {level} > {MAX_EXPOSURE}:\n{out}"


def test_the_rating_notices_a_weaker_unit(tmp_path) -> None:
    """The check can fail: the same unit without its sandbox rates far above the limit."""
    weak = tmp_path / UNIT.name
    keep = ("User=", "ExecStart=", "Type=", "[", "Description=", "WantedBy=", "Restart")
    weak.write_text(
        "\n".join(ln for ln in UNIT.read_text().splitlines() if ln.startswith(keep)) + "\n"
    )
    level, _ = exposure(weak)
    assert level > MAX_EXPOSURE + 3


def test_unit_runs_unprivileged_with_read_only_code_and_its_own_state() -> None:
    svc = service_section()
    assert svc["User"] == ["ucr"] and "root" not in svc.get("Group", [])
    assert "dialout" in " ".join(svc.get("SupplementaryGroups", []))
    assert svc["ProtectSystem"] == ["strict"]  # /opt/ucr (code, venv) and /etc read-only
    assert svc["StateDirectory"] == ["ucr"] and svc["UMask"] == ["0077"]
    assert svc["NoNewPrivileges"] == ["true"] and svc["CapabilityBoundingSet"] == [""]
    assert svc["ProtectHome"] == ["true"] and svc["PrivateTmp"] == ["true"]
    assert svc["Restart"] == ["on-failure"] and svc["KillSignal"] == ["SIGTERM"]
    assert svc["ExecStart"][-1].startswith("/opt/ucr/.venv/bin/ucr daemon ")


def test_unit_allows_only_serial_devices_and_bounds_resources() -> None:
    svc = service_section()
    assert svc["DevicePolicy"] == ["closed"]
    allowed = [v.split()[0] for v in svc["DeviceAllow"]]
    assert allowed and all(re.fullmatch(r"char-tty(USB|ACM|AMA|S)", a) for a in allowed), allowed
    assert set(svc["RestrictAddressFamilies"][-1].split()) == {"AF_UNIX", "AF_INET", "AF_INET6"}
    assert any(v.startswith("@system-service") for v in svc["SystemCallFilter"])
    for key in ("MemoryMax", "TasksMax", "LimitNOFILE"):
        assert svc.get(key), f"no {key}"


def test_the_zenoh_unit_keeps_what_zenoh_needs_and_filters_the_rest() -> None:
    """Zenoh needs TCP/UDP over IPv4/IPv6, netlink (it reads the host's interfaces) and local
    sockets (the journal); its native library runs without writable executable memory."""
    svc = service_section(ZENOH_UNIT)
    families = set(svc["RestrictAddressFamilies"][-1].split())
    assert families == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}
    assert svc["MemoryDenyWriteExecute"] == ["true"] and svc["ProtectProc"] == ["invisible"]
    assert any(v.startswith("@system-service") for v in svc["SystemCallFilter"])
    assert svc["User"] == ["ucr"] and svc["ProtectSystem"] == ["strict"]
    assert "RemoveIPC" not in svc  # it would remove the daemon's (same user) IPC objects
    for key in ("MemoryMax", "TasksMax", "LimitNOFILE"):
        assert svc.get(key), f"no {key}"


def _group(name: str) -> set[str]:
    """The system calls of a systemd syscall group (``@resources``), or the name itself."""
    if not name.startswith("@"):
        return {name}
    out = subprocess.run(
        ["systemd-analyze", "syscall-filter", "--no-pager", name],
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    calls: set[str] = set()
    for line in out.splitlines()[1:]:
        line = line.strip()
        if line and not line.startswith("#"):
            calls |= _group(line)
    return calls


def test_the_syscall_filter_lets_the_daemon_set_its_priorities() -> None:
    """Review 2026-11-26: ``~@resources`` took setpriority away, so the API process's
    ``os.nice(5)`` failed with EPERM (host/api/process.py suppresses it) and it kept the loop's
    Nice=-5. The filter lines are applied as systemd does: the first allows, ``~`` removes,
    later lines add back."""
    allowed: set[str] = set()
    for value in service_section()["SystemCallFilter"]:
        names = value.split()
        if names[0].startswith("~"):
            names[0] = names[0][1:]
            for n in names:
                allowed -= _group(n)
        else:
            for n in names:
                allowed |= _group(n)
    need = {"setpriority", "sched_setscheduler", "sched_getscheduler", "sched_getparam"}
    assert need <= allowed, need - allowed
