"""EmulatorProcess: `ucr emulate` in a child process, which the host-side benchmarks drive."""

from __future__ import annotations

import time

import pytest

from host.link import ChainLink
from host.link_frames import LinkError
from tools.emulator import EmulatorError, EmulatorProcess


def test_a_chain_in_its_own_process_answers_and_takes_link_settings() -> None:
    with EmulatorProcess(2) as chain:
        with ChainLink(chain.host_port) as link:
            end = time.monotonic() + 60
            descs: list[dict] = []
            while len(descs) != 2 and time.monotonic() < end:
                try:
                    descs = link.discover(timeout=1.0)
                except LinkError:  # a reply lost while the segments boot on a loaded host (CI)
                    descs = []
                time.sleep(0.1)
            assert [d["position"] for d in descs] == [0, 1]
            chain.set_all_links(baud=115200)
            assert "link 2: plugged, 115200 bd" in chain.command("status")
            answered = False
            for _ in range(5):  # a loaded machine may miss one cycle; a dead link misses all
                answered = all(s is not None for s in link.sync([(0.5, 0.1)] * 2, timeout=1.0))
                if answered:
                    break
            assert answered
            chain.set_all_links(baud=None)
            assert "unthrottled" in chain.command("status")
        with pytest.raises(EmulatorError, match="position must be 1..2"):
            chain.command("baud 3 9600")
        proc = chain._proc
    assert proc.poll() is not None  # closed: the child is gone


def test_an_emulator_that_cannot_start_says_why() -> None:
    with pytest.raises(EmulatorError, match="ucr emulate exited"):
        EmulatorProcess(0)


def test_a_benchmark_chain_is_in_a_process_or_a_thread_and_nothing_else() -> None:
    from tools.emulator.process import emulated_chain

    with pytest.raises(ValueError, match="where must be 'process' or 'thread'"):
        emulated_chain(1, where="nowhere")
