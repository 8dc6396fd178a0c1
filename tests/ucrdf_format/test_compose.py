"""Composition: an ordered list of segment descriptors becomes a checked U(C)RDF robot."""

from __future__ import annotations

import math

import pytest

from ucrdf.checks import check
from ucrdf.compose import robot_from_descriptors, write_robot_from_descriptors
from ucrdf.errors import UcrdfError
from ucrdf.parser import load

from .conftest import ROBOTS

KAPPA_MAX = (math.pi / 3) / 0.316


def descriptor(k: int, **over) -> dict:
    """A DESCRIPTOR as the host decodes it (docs/architecture.md), for the paper's segment."""
    d = {
        "uid": f"a4cf12{k:06x}",
        "fw_version": "0.1.0",
        "protocol_version": 1,
        "model": "pcc",
        "length": 0.316,
        "tendon_angles": [0.0, 2 * math.pi / 3, 4 * math.pi / 3],
        "tendon_radius": 0.06,
        "spool_radius": 0.025,
        "kappa_max": KAPPA_MAX,
        "kappa_rate_max": 5.0,
        "mass": 0.3,
        "backbone_radius": 0.003,
        "name": f"seg{k}",
        "servo_driver": "feetech_sts",
        "watchdog_ms": 200,
        "downstream_present": k < 2,
        "position": k,
    }
    d.update(over)
    return d


def test_three_descriptors_compose_write_parse_and_check_clean(tmp_path):
    path = tmp_path / "chain.ucrdf"
    robot = write_robot_from_descriptors([descriptor(k) for k in range(3)], path, "chain")
    loaded = load(path)  # parses and checks clean
    assert loaded == robot
    assert check(loaded) == []
    assert list(loaded.bendables) == ["seg0", "seg1", "seg2"]
    chain = ["base", "seg0_tip", "seg1_tip", "seg2_tip"]
    assert list(loaded.links) == chain
    for k, b in enumerate(loaded.bendables.values()):
        assert (b.parent, b.child) == (chain[k], chain[k + 1])
        assert b.model.limits.kappa_max == KAPPA_MAX and b.length == 0.316
        assert b.actuation is not None and b.actuation.driver == "feetech_sts"
        assert b.actuation.angles == descriptor(k)["tendon_angles"]
        assert b.inertial is not None and b.inertial.mass == 0.3
    (control,) = loaded.ros2_control
    assert control.hardware_params == {
        "model": "pcc",
        "port": "auto",
        "baudrate": "921600",
        "seg0/uid": "a4cf12000000",
        "seg1/uid": "a4cf12000001",
        "seg2/uid": "a4cf12000002",
    }
    kappa = control.joints[1].command_interfaces[0]
    assert kappa.name == "kappa" and kappa.params["max"] == KAPPA_MAX and kappa.params["min"] == 0


def test_composed_paper_chain_matches_the_softrobot3_example_kinematically():
    composed = robot_from_descriptors([descriptor(k, name="") for k in range(3)], "softrobot3")
    example = load(ROBOTS / "softrobot3.ucrdf")
    assert list(composed.bendables) == list(example.bendables)
    assert list(composed.links) == list(example.links)
    for name, b in composed.bendables.items():
        e = example.bendables[name]
        assert (b.parent, b.child) == (e.parent, e.child)
        assert b.model.limits.kappa_max == pytest.approx(e.model.limits.kappa_max)
        assert b.length == e.length and b.actuation.radius == e.actuation.radius


def test_duplicate_or_missing_names_fall_back_to_segment_k():
    descs = [descriptor(0, name="twin"), descriptor(1, name="twin"), descriptor(2, name="")]
    descs.append(descriptor(3, name="wrist"))
    robot = robot_from_descriptors(descs)
    assert list(robot.bendables) == ["segment_1", "segment_2", "segment_3", "wrist"]


def test_name_that_would_clash_with_a_generated_name_is_made_unique():
    descs = [descriptor(0, name="segment_2"), descriptor(1, name="")]
    robot = robot_from_descriptors(descs)
    assert len(set(robot.bendables)) == 2 and check(robot) == []


def test_missing_and_invalid_values_are_all_reported():
    bad = descriptor(1)
    del bad["kappa_max"]
    worse = descriptor(2, length="long", tendon_angles=[])
    with pytest.raises(UcrdfError) as info:
        robot_from_descriptors([descriptor(0), bad, worse, None])  # type: ignore[list-item]
    text = str(info.value)
    assert "descriptor 2 (seg1): missing kappa_max" in text
    assert "descriptor 3 (seg2): length must be a finite number, got 'long'" in text
    assert "descriptor 3 (seg2): tendon_angles must be a non-empty list" in text
    assert "descriptor 4: expected a dict, got NoneType" in text


def test_physically_impossible_descriptor_is_rejected_by_the_checks():
    with pytest.raises(UcrdfError) as info:
        robot_from_descriptors([descriptor(0, kappa_max=20.0)])  # 20 * 0.316 > pi
    assert "kappa_max*length" in str(info.value)


def test_empty_chain_is_an_error():
    with pytest.raises(UcrdfError, match="chain is empty"):
        robot_from_descriptors([])
