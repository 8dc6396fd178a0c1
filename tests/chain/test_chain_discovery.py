"""Discovery over emulated chains of 1, 3 and 8 segments running the real firmware."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from chain_helpers import chain_and_link, wait_discover

from protocol import constants as C
from tools.segment_config import configs
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"


def _synthetic_config(k: int) -> dict:
    return {
        "name": f"seg_{k}",
        "length": 0.2 + 0.01 * k,
        "tendon_angles": [0.0, 2 * math.pi / 3, 4 * math.pi / 3],
        "tendon_radius": 0.04,
        "spool_radius": 0.015,
        "kappa_max": 2.0 + 0.1 * k,
        "kappa_rate_max": 4.0,
        "mass": 0.25,
        "backbone_radius": 0.002,
        "model": "pcc",
        "servo_driver": "emulated",
        "servos": [
            {"id": i, "zero_offset": 0.0, "direction": 1, "min_angle": -3.0, "max_angle": 3.0}
            for i in range(3)
        ],
        "watchdog_ms": 300 + k,
    }


@pytest.mark.parametrize("n", [1, 8])
def test_discovery_finds_every_segment_in_chain_order_with_its_configuration(n: int) -> None:
    with chain_and_link(n, config_for=_synthetic_config) as (chain, link):
        descs = wait_discover(link, n)
        assert [d["position"] for d in descs] == list(range(n))
        assert [d["uid"] for d in descs] == [chain.uid(k) for k in range(n)]
        assert len({d["uid"] for d in descs}) == n
        for k, d in enumerate(descs):
            cfg = _synthetic_config(k)
            assert d["name"] == cfg["name"]
            assert d["length"] == pytest.approx(cfg["length"])
            assert d["kappa_max"] == pytest.approx(cfg["kappa_max"])
            assert d["watchdog_ms"] == cfg["watchdog_ms"]
            assert d["protocol_version"] == C.VERSION == 2
            assert d["downstream_present"] is (k < n - 1)


def test_discovery_of_three_segments_configured_from_the_robot_file() -> None:
    cfgs = configs(load(ROBOT))
    with chain_and_link(3, config_for=cfgs) as (chain, link):
        descs = wait_discover(link, 3)
        assert [d["name"] for d in descs] == ["segment_1", "segment_2", "segment_3"]
        for d, cfg in zip(descs, cfgs, strict=True):
            assert d["tendon_radius"] == pytest.approx(cfg["tendon_radius"])
            assert d["spool_radius"] == pytest.approx(cfg["spool_radius"])
            assert d["kappa_rate_max"] == pytest.approx(cfg["kappa_rate_max"])
            assert d["mass"] == pytest.approx(cfg["mass"])
            assert d["tendon_angles"] == pytest.approx(cfg["tendon_angles"])
        assert link.stats["crc_errors"] == 0
