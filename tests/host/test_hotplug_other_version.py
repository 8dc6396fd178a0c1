"""A segment flashed with another protocol version, plugged in while the daemon runs, ends the
chain before it: the segments before it stay under control and an event says to reflash it
(docs/daemon.md "Hot-plug"; issue 14 audit: it used to drop the whole chain)."""

from __future__ import annotations

import queue
from pathlib import Path

import pytest
from daemon_helpers import emulated_configs, start_daemon, wait_for

from host.config import DaemonConfig
from host.daemon import Daemon
from protocol import constants as C
from tests.chain.chain_helpers import protocol_speaking
from tools.emulator import EmulatedChain, populate_segment_dir

pytestmark = pytest.mark.timeout(240)

REPO = Path(__file__).resolve().parents[2]


def _reflash(chain: EmulatedChain, k: int, protocol_dir: Path, config: dict) -> None:
    """Power segment ``k`` off, lay out its flash from ``protocol_dir``, power it on."""
    chain.power_off(k)
    populate_segment_dir(chain._seg(k).dir, protocol_dir=protocol_dir, config=config)
    chain.power_on(k)


def test_a_hot_plugged_segment_of_another_version_keeps_the_chain_before_it(tmp_path, robot3):
    other = protocol_speaking(tmp_path, C.VERSION_MAX + 1)
    configs = emulated_configs(robot3)
    with EmulatedChain(3, config_for=configs) as chain:
        d = Daemon(robot3, DaemonConfig(port=chain.host_port))
        start_daemon(d)
        q = d.subscribe(["event"])
        try:
            _reflash(chain, 2, other, configs(2))

            def refused() -> list[dict]:
                out = []
                while True:
                    try:
                        msg = q.get_nowait()
                    except queue.Empty:
                        return out
                    if msg.get("event") == "segment_refused":
                        out.append(msg)

            seen: list[dict] = []
            assert wait_for(lambda: bool(seen.extend(refused()) or seen), 20.0), "no refusal"
            assert seen[0]["position"] == 3 and "ucr flash" in seen[0]["message"]
            assert wait_for(
                lambda: (
                    d.status()["state"] == "connected"
                    and d.status()["segments"] == ["segment_1", "segment_2"]
                    and all(v["valid"] for v in d.status()["joint_states"].values())
                ),
                20.0,
            ), d.status()
            topo = d.topology()
            assert topo["cut"]["lost"] == ["segment_3"] and "ucr flash" in topo["refused"]
            # reflashed with this host's firmware, it rejoins by itself (the probe past the cut)
            _reflash(chain, 2, REPO / "protocol", configs(2))
            assert wait_for(
                lambda: d.status()["segments"] == ["segment_1", "segment_2", "segment_3"], 30.0
            ), d.status()
            assert d.topology()["refused"] is None
        finally:
            d.unsubscribe(q)
            d.stop()
