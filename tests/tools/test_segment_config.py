"""Segment configuration derived from a U(C)RDF bendable."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tools.segment_config import (
    CONFIG_KEYS,
    DEFAULT_KAPPA_RATE_MAX,
    SegmentConfigError,
    config_for,
    write_config,
)
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"


@pytest.fixture(scope="module")
def robot():
    return load(ROBOT)


def test_config_carries_the_bendables_geometry_limits_and_servos(robot) -> None:
    b = robot.bendables["segment_2"]
    cfg = config_for(robot, "segment_2")
    assert set(CONFIG_KEYS) == set(cfg)
    assert cfg["name"] == "segment_2"
    assert cfg["length"] == b.model.backbone.length
    assert cfg["backbone_radius"] == b.model.backbone.radius
    assert cfg["kappa_max"] == b.model.limits.kappa_max
    assert cfg["kappa_rate_max"] == b.model.limits.kappa_rate_max
    assert cfg["tendon_angles"] == b.actuation.angles
    assert cfg["tendon_radius"] == b.actuation.radius
    assert cfg["spool_radius"] == b.actuation.spool_radius
    assert cfg["mass"] == b.inertial.mass
    assert cfg["model"] == "pcc"
    assert [s["id"] for s in cfg["servos"]] == [s.id for s in b.actuation.servos]
    assert cfg["watchdog_ms"] == 200  # the ros2_control hardware param
    json.dumps(cfg)  # serialisable as is


def test_missing_rate_limit_uses_the_firmware_default(robot) -> None:
    robot.bendables["segment_1"].model.limits.kappa_rate_max = None
    assert config_for(robot, "segment_1")["kappa_rate_max"] == DEFAULT_KAPPA_RATE_MAX


def test_bendable_without_actuation_is_a_clear_error(robot) -> None:
    robot.bendables["segment_3"].actuation = None
    with pytest.raises(SegmentConfigError, match="segment_3.*no tendon <actuation>"):
        config_for(robot, "segment_3")


def test_unknown_bendable_names_the_existing_ones(robot) -> None:
    with pytest.raises(SegmentConfigError, match="no bendable 'nope'.*segment_1"):
        config_for(robot, "nope")


def test_write_config_into_a_directory(robot, tmp_path) -> None:
    path = write_config(robot, "segment_2", tmp_path)
    assert path == tmp_path / "config.json"
    data = json.loads(path.read_text())
    assert math.isclose(data["kappa_max"], robot.bendables["segment_2"].model.limits.kappa_max)
