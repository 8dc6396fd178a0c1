"""Review 3 defect B: ``ucr doctor --port <a segment's REPL port>`` is read-only: it recognises
the MicroPython REPL, says so, and sends no frame (whose Ctrl-C/Ctrl-D bytes reset the segment)."""

from __future__ import annotations

import time

import pytest

from host import doctor
from host.link import ChainLink
from tools.emulator import EmulatedChain

pytestmark = pytest.mark.timeout(120)


def _wait_discover(link: ChainLink, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if link.discover(timeout=0.3):
            return
    raise AssertionError("segment did not answer DISCOVER")


def test_doctor_on_a_segments_repl_port_says_so_and_resets_nothing() -> None:
    with EmulatedChain(1, config_for=[{"name": "segment_1"}]) as chain:
        with ChainLink(chain.host_port) as link:  # the daemon's place: the chain port is busy
            _wait_discover(link)
            restarts = chain.stats()["segments"][0]["restarts"]
            for _ in range(2):
                findings = doctor.run(chain.repl_port(0), 921600, None, 0.0)
                errs = [f for f in findings if f.level == "error"]
                # a running firmware's REPL is silent: doctor sends it no frame and says why
                assert errs and "the port is silent" in errs[0].message, findings
                assert "REPL port" in errs[0].fix
            time.sleep(1.0)
            assert chain.stats()["segments"][0]["restarts"] == restarts  # nothing reset
            assert link.discover(timeout=1.0)  # and the chain still answers


def test_doctor_recognises_a_micropython_prompt() -> None:
    import os

    from test_review_commissioning import _pty  # a fake REPL: answers \r with a prompt

    master, slave, got = _pty(b"\r\n>>> ")
    try:
        findings = doctor.run(os.ttyname(slave), 921600, None, 0.0)
    finally:
        os.close(slave)
    errs = [f for f in findings if f.level == "error"]
    assert errs and "is a segment's REPL port" in errs[0].message, findings
    assert "not the chain port" in errs[0].message
    assert bytes(got) == b"\r"  # a carriage return, nothing that stops or resets a board
    os.close(master)
