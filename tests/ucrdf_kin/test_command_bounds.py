"""FK and IK keep to the bounds the robot accepts: the model's limits narrowed by the
``<ros2_control>`` command interface min/max, the intersection the daemon enforces
(ucrdf/limits.py, used by host/limits.py). They checked the model limits only."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ucrdf.fk import ConfigError, RobotKinematics
from ucrdf.ik import IKSolver, solve_ik
from ucrdf.model import ControlJoint, Interface, Ros2Control
from ucrdf.models.base import ModelError
from ucrdf.parser import load

from .conftest import ROBOTS_DIR, chain_robot, hybrid_robot
from .test_cli import run

LISTING1 = ROBOTS_DIR / "listing1.ucrdf"  # kappa_max 3.31 1/m, kappa command interface max 3
#: the tip of listing1 at kappa = 3.25 1/m, phi = 0 (inside the model limits, beyond max 3)
BEYOND_MAX = (0.1484958703395038, 0.0, 0.2633079006547136)


def test_fk_refuses_a_kappa_beyond_the_command_interface_max():
    kin = RobotKinematics(load(LISTING1))
    narrowed = (
        r"kappa = 3\.25 1/m is outside its limits \[0, 3\] "
        r"\(its <ros2_control> command interface bounds, tighter than the model's\)"
    )
    with pytest.raises(ConfigError, match=narrowed):
        kin.fk({"segment": {"kappa": 3.25}})
    with pytest.raises(ConfigError, match=r"kappa = 3\.5 1/m is outside its limits \[0, 3\]$"):
        kin.fk({"segment": {"kappa": 3.5}})  # beyond the model's 3.31 too: no note
    kin.fk({"segment": {"kappa": 3.0}})
    kin.fk({"segment": {"kappa": 3.25}}, strict=False)  # a measured state is not checked


def test_ik_solves_within_the_command_interface_max():
    """IK reached BEYOND_MAX with kappa 3.2499: a configuration the daemon refuses."""
    robot = load(LISTING1)
    result = solve_ik(robot, BEYOND_MAX)
    assert not result.success
    assert result.config["segment"]["kappa"] <= 3.0 + 1e-12
    inside = RobotKinematics(robot).fk({"segment": {"kappa": 2.9, "phi": 0.7}})["eef"][:3, 3]
    result = solve_ik(robot, inside)
    assert result.success and result.config["segment"]["kappa"] == pytest.approx(2.9, abs=1e-3)


def test_cli_fk_and_ik_keep_to_the_command_interface_max(capsys):
    config = json.dumps({"segment": {"kappa": 3.25}})
    code, _out, err = run(["fk", str(LISTING1), "--config", config], capsys)
    assert code == 1 and "kappa = 3.25 1/m is outside its limits [0, 3]" in err
    code, out, _err = run(["ik", str(LISTING1), "--target", ",".join(map(str, BEYOND_MAX))], capsys)
    assert code == 1 and json.loads(out)["config"]["segment"]["kappa"] <= 3.0 + 1e-12


def _with_phi_bounds(lo: float, hi: float):
    robot = chain_robot(1)
    phi = robot.ros2_control[0].joints[0].command_interfaces[1]
    phi.params.update({"min": lo, "max": hi})
    return robot


def test_a_narrower_phi_interface_bounds_fk_and_ik():
    kin = RobotKinematics(_with_phi_bounds(0.0, 1.0))
    assert kin.fk({"seg1": {"kappa": 1.0, "phi": 0.9}})
    with pytest.raises(ConfigError, match=r"phi = 1\.5 rad is outside its limits \[0, 1\] \(its"):
        kin.fk({"seg1": {"kappa": 1.0, "phi": 1.5}})
    solver = IKSolver(kin)
    for phi, reachable in ((0.5, True), (2.0, False)):
        target = kin.fk({"seg1": {"kappa": 2.0, "phi": phi}}, strict=False)["link1"][:3, 3]
        result = solver.solve(target)
        assert result.success is reachable
        assert 0.0 - 1e-12 <= result.config["seg1"]["phi"] <= 1.0 + 1e-12
        kin.fk(result.config)


def _hybrid_with_position_bounds(lo: float, hi: float):
    robot = hybrid_robot()
    position = Interface("position", {"min": lo, "max": hi})
    robot.ros2_control.append(Ros2Control("arm", joints=[ControlJoint("j2", [position])]))
    return robot


def test_a_rigid_joints_position_interface_bounds_fk_and_ik():
    kin = RobotKinematics(_hybrid_with_position_bounds(-0.5, 0.5))
    narrowed = r"joint 'j2' = 1 is outside its limits \[-0\.5, 0\.5\] \(its <ros2_control> command"
    with pytest.raises(ConfigError, match=narrowed):
        kin.fk({"j2": 1.0})
    with pytest.raises(ConfigError, match=r"joint 'j2' = 2 is outside its limits \[-0\.5, 0\.5\]$"):
        kin.fk({"j2": 2.0})  # beyond its <limit> (1.5) too: no note
    config = {"j1": 0.4, "j2": 1.2, "j3": 0.1}  # j2 inside its <limit>, beyond the interface
    target = kin.fk(config, strict=False)["tool"][:3, 3]
    result = IKSolver(kin, "tool").solve(target)
    assert -0.5 - 1e-12 <= result.config["j2"] <= 0.5 + 1e-12
    kin.fk(result.config)


def test_ik_never_reports_success_beyond_a_plugin_variables_interface_bounds():
    """Bounds IK's projection does not know (a PPC slope's interface) are checked at the end."""
    robot = chain_robot(1, model="ppc")
    robot.ros2_control[0].joints[0].command_interfaces.append(
        Interface("kappa_x_slope", {"min": -1.0, "max": 1.0})
    )
    kin = RobotKinematics(robot)
    assert kin.variable_bounds == {"seg1": {"kappa_x_slope": (-1.0, 1.0)}}
    with pytest.raises(ConfigError, match=r"kappa_x_slope = 3 is outside its limits \[-1, 1\]"):
        kin.fk({"seg1": {"kappa_x_slope": 3.0}})
    solver = IKSolver(kin)
    for slope in (-4.0, 0.5, 3.0):
        config = {"seg1": {"kappa": 1.0, "phi": 0.3, "kappa_x_slope": slope}}
        target = kin.fk(config, strict=False)["link1"][:3, 3]
        result = solver.solve(target)
        if result.success:
            kin.fk(result.config)
        elif result.residual <= 1e-4:  # on target, but beyond the bound: said so
            assert "breaks a command interface bound: bendable 'seg1'" in result.message


@pytest.mark.parametrize(
    ("param", "value", "match"),
    [
        ("max", math.inf, r"command_interface 'kappa' param max must be a finite number"),
        ("max", "three", r"command_interface 'kappa' param max must be a finite number"),
        ("max", -1.0, r"command_interface 'kappa' max must be > 0 1/m, got -1"),
        ("min", 0.5, r"kappa is a magnitude; a minimum above 0 is not supported"),
    ],
)
def test_unusable_command_interface_bounds_are_refused(param, value, match):
    robot = chain_robot(1)
    robot.ros2_control[0].joints[0].command_interfaces[0].params[param] = value
    with pytest.raises(ModelError, match=match):
        RobotKinematics(robot)


def test_bounds_that_do_not_overlap_are_refused():
    with pytest.raises(ModelError, match=r"bendable 'seg1': empty phi range"):
        RobotKinematics(_with_phi_bounds(4.0, 5.0))
    with pytest.raises(ModelError, match=r"joint 'j2': empty range \[2, 1\.5\]"):
        RobotKinematics(_hybrid_with_position_bounds(2.0, 3.0))


def test_example_robots_take_their_initial_values():
    """Every example robot's initial configuration lies within the narrowed bounds."""
    for path in sorted(ROBOTS_DIR.glob("*.ucrdf")):
        frames = RobotKinematics(load(path)).fk()
        assert all(np.isfinite(t).all() for t in frames.values()), path.name


def test_ucr_check_refuses_a_kappa_minimum_above_zero_as_fk_and_the_daemon_do(tmp_path):
    """A kappa command interface with min > 0 passed `ucr check`, then FK and the daemon
    refused the robot: the check says it, at the interface."""
    from ucrdf.errors import UcrdfError

    text = LISTING1.read_text().replace(
        '<param name="max">3</param>', '<param name="max">3</param>\n<param name="min">0.5</param>'
    )
    f = tmp_path / "kmin.ucrdf"
    f.write_text(text)
    with pytest.raises(UcrdfError) as info:
        load(f)
    assert any(
        "command_interface 'kappa': param min 0.5 1/m: kappa is a magnitude" in str(d)
        for d in info.value.diagnostics
    )
