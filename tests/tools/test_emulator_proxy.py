"""The link proxy keeps working when the process has many files open (fd numbers past 1024,
where select(2) cannot look), by moving its registrations to the default selector."""

from __future__ import annotations

import os
import resource
import time

import pytest

from tools.emulator.pipe import Pipe
from tools.emulator.proxy import SELECT_MAX_FD, Proxy


def _read_for(fd: int, want: int, timeout: float) -> bytes:
    got = b""
    end = time.monotonic() + timeout
    while len(got) < want and time.monotonic() < end:
        try:
            got += os.read(fd, 4096)
        except BlockingIOError:
            time.sleep(0.005)
    return got


def test_proxy_moves_to_the_default_selector_when_an_fd_is_past_select_range():
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < SELECT_MAX_FD + 200:
        pytest.skip(f"hard limit of open files is {hard}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, SELECT_MAX_FD + 200), hard))
    filler = [os.open(os.devnull, os.O_RDONLY) for _ in range(SELECT_MAX_FD + 20)]
    proxy = Proxy()
    try:
        a = proxy.add_end("a")
        b = proxy.add_end("b")
        assert max(a.master, b.master) >= SELECT_MAX_FD
        pipe = Pipe("a->b")
        pipe.configure(baud=921600)
        proxy.connect(a, pipe, b)
        proxy.start()
        os.write(a.slave, b"hello over a throttled link")
        os.set_blocking(b.slave, False)
        assert _read_for(b.slave, 27, 5.0) == b"hello over a throttled link"
        assert proxy.error is None
    finally:
        proxy.close()
        for fd in filler:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
