"""The daemon's effective limits (host.limits) and the kinematics' (ucrdf.fk, ucrdf.ik) are one
intersection, ucrdf.limits: the model's <limits> narrowed by the <ros2_control> command interface
min/max. `ucr fk`/`ucr ik` accepted kappa up to the model's 3.31 on listing1, whose interface max
(and so the daemon) is 3."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest

from host.limits import ConfigError, bendable_limits
from ucrdf.fk import RobotKinematics
from ucrdf.parser import load

ROBOTS = Path(__file__).resolve().parents[2] / "robots"


def _agree(robot) -> None:
    kin = RobotKinematics(robot)
    for name, host in bendable_limits(robot).items():
        lim = kin.models[name].spec.limits
        assert (host.kappa_max, host.phi_min, host.phi_max) == (
            lim.kappa_max,
            lim.phi_min,
            lim.phi_max,
        ), name


@pytest.mark.parametrize("path", sorted(ROBOTS.glob("*.ucrdf")), ids=lambda p: p.name)
def test_host_and_kinematics_bound_the_example_robots_alike(path):
    _agree(load(path))


def test_listing1_is_bounded_by_its_interface_max_everywhere():
    robot = load(ROBOTS / "listing1.ucrdf")
    assert robot.bendables["segment"].model.limits.kappa_max > 3.3
    assert bendable_limits(robot)["segment"].kappa_max == 3.0
    _agree(robot)


def test_a_phi_interface_range_narrows_both_alike():
    robot = copy.deepcopy(load(ROBOTS / "softrobot3.ucrdf"))
    phi = robot.ros2_control[0].joints[1].command_interfaces[1]
    assert phi.name == "phi"
    phi.params.update({"min": "-1.0", "max": 2.5})  # a robot built in code may give text
    lim = bendable_limits(robot)["segment_2"]
    assert (lim.phi_min, lim.phi_max) == (-1.0, 2.5)
    _agree(robot)


@pytest.mark.parametrize(
    ("param", "value", "match"),
    [
        (
            "max",
            -1.0,
            r"ros2_control.joint\[segment_1\]: command_interface 'kappa' max must be > 0",
        ),
        ("min", 0.5, r"kappa is a magnitude; a minimum above 0 is not supported"),
        ("max", math.nan, r"command_interface\[kappa\].max: must be finite, got nan"),
    ],
)
def test_the_daemon_still_refuses_unusable_kappa_bounds(param, value, match):
    robot = copy.deepcopy(load(ROBOTS / "softrobot3.ucrdf"))
    robot.ros2_control[0].joints[0].command_interfaces[0].params[param] = value
    with pytest.raises(ConfigError, match=match):
        bendable_limits(robot)
