"""The shipped example robots and the paper's Listing 1 parse and check clean."""

from __future__ import annotations

import math

import pytest

from ucrdf.checks import check
from ucrdf.parser import load

from .conftest import EXAMPLES, ROBOTS


def test_all_four_examples_are_shipped():
    names = {p.name for p in EXAMPLES}
    assert {"softrobot3.ucrdf", "softrobot2.ucrdf", "hybrid_arm.ucrdf", "listing1.ucrdf"} <= names


@pytest.mark.parametrize("path", EXAMPLES, ids=lambda p: p.name)
def test_example_parses_and_checks_clean(path):
    robot = load(path)
    assert check(robot) == []
    assert robot.root_link() in robot.links


def test_softrobot3_is_the_papers_robot():
    robot = load(ROBOTS / "softrobot3.ucrdf")
    assert list(robot.bendables) == ["segment_1", "segment_2", "segment_3"]
    chain = ["base", "segment_1_tip", "segment_2_tip", "segment_3_tip"]
    for k, b in enumerate(robot.bendables.values()):
        assert (b.parent, b.child) == (chain[k], chain[k + 1])
        assert b.length == pytest.approx(0.316)
        # a 60 degree bend at the maximum curvature
        assert math.degrees(b.model.limits.kappa_max * b.length) == pytest.approx(60.0)
        assert b.inertial is not None and b.inertial.mass == pytest.approx(0.3)
        act = b.actuation
        assert act is not None and act.count == 3 and len(act.servos) == 3
        gaps = sorted(math.degrees(a) for a in act.angles)
        assert [round(g2 - g1, 9) for g1, g2 in zip(gaps, gaps[1:], strict=False)] == [120, 120]
    (control,) = robot.ros2_control
    assert control.hardware_params["model"] == "pcc"
    assert control.hardware_params["baudrate"] == "921600"
    assert "port" in control.hardware_params
    assert [j.name for j in control.joints] == list(robot.bendables)


def test_hybrid_arm_has_rigid_and_continuum_parts_under_ros2_control():
    robot = load(ROBOTS / "hybrid_arm.ucrdf")
    movable = [j.name for j in robot.joints.values() if j.movable]
    assert len(movable) >= 2 and len(robot.bendables) == 1
    controlled = {j.name for c in robot.ros2_control for j in c.joints}
    assert set(movable) <= controlled and set(robot.bendables) <= controlled
    # the extension elements survive (gazebo, transmission, material) and dynamics is kept
    assert any(e.startswith("<gazebo") for e in robot.extensions)
    assert any(e.startswith("<transmission") for e in robot.extensions)
    assert robot.joints["shoulder_yaw"].extensions[0].startswith("<dynamics")


def test_listing1_keeps_the_shape_of_the_paper():
    robot = load(ROBOTS / "listing1.ucrdf")
    assert robot.name == "softrobot"
    assert list(robot.links) == ["base", "eef"]
    seg = robot.bendables["segment"]
    assert (seg.parent, seg.child, seg.model.type) == ("base", "eef", "pcc")
    assert seg.inertial is not None and seg.inertial.mass == 0.3
    (control,) = robot.ros2_control
    assert (control.name, control.type, control.plugin) == (
        "softrobot",
        "system",
        "SoftRobotInterface",
    )
    (joint,) = control.joints
    kappa, phi = joint.command_interfaces
    assert kappa.params == {"initial_value": 0.0, "max": 3.0}
    assert phi.params == {"initial_value": 0.0}
    assert [i.name for i in joint.state_interfaces] == ["kappa", "phi"]
