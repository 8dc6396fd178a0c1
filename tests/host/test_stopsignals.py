"""The one stop rule of long-running ``ucr`` commands (host/stopsignals.py): SIGTERM and
Ctrl-C both set the stop event; the exit code is 0 after SIGTERM, 130 after Ctrl-C, and a
failure stays a failure."""

from __future__ import annotations

import signal

import pytest

from host.stopsignals import INTERRUPTED, StopSignals


@pytest.fixture
def handlers():
    saved = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    yield
    signal.signal(signal.SIGTERM, saved[0])
    signal.signal(signal.SIGINT, saved[1])


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGTERM, 0), (signal.SIGINT, INTERRUPTED)])
def test_either_signal_stops_and_only_ctrl_c_is_130(handlers, sig, code):
    s = StopSignals().install()
    assert not s.stop.is_set() and s.exit_code() == 0
    signal.raise_signal(sig)  # handled in the main thread before raise_signal returns
    assert s.stop.is_set()
    assert s.interrupted.is_set() == (sig == signal.SIGINT)
    assert s.exit_code() == code
    assert s.exit_code(1) == 1  # a failure stays a failure
