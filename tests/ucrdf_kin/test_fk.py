"""Robot FK: every link frame, bendables chained, rigid joints (origin then axis motion),
defaults from ros2_control initial values, clear errors for bad configurations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ucrdf.fk import ConfigError, RobotKinematics, axis_rotation, bendable_frames, robot_fk
from ucrdf.model import Origin
from ucrdf.models.base import ModelError
from ucrdf.models.pcc import pcc_transforms

from .conftest import ROBOTS_DIR, SEGMENT_LENGTH, chain_robot, hybrid_robot

CFG3 = {
    "seg1": {"kappa": 2.0, "phi": 0.5},
    "seg2": {"kappa": 3.0, "phi": -1.0},
    "seg3": {"kappa": 1.0, "phi": 2.5},
}


def seg(kappa, phi, length=SEGMENT_LENGTH):
    return pcc_transforms(kappa * math.cos(phi), kappa * math.sin(phi), length)[0]


def test_chain_frames_are_products_of_segment_transforms():
    frames = robot_fk(chain_robot(3), CFG3)
    assert set(frames) == {"base", "link1", "link2", "link3"}
    t1 = seg(2.0, 0.5)
    t2 = t1 @ seg(3.0, -1.0)
    t3 = t2 @ seg(1.0, 2.5)
    assert np.allclose(frames["base"], np.eye(4))
    assert np.allclose(frames["link1"], t1) and np.allclose(frames["link2"], t2)
    assert np.allclose(frames["link3"], t3, atol=1e-14)


def test_rigid_joints_apply_origin_then_axis_motion():
    robot = hybrid_robot()
    cfg = {"j1": 0.4, "j2": -0.3, "j3": 0.15, "wrist1": {"kappa": 5.0, "phi": 1.0}}
    frames = robot_fk(robot, cfg)

    def rot(axis, a):
        t = np.eye(4)
        t[:3, :3] = axis_rotation(np.array(axis, float), a)
        return t

    def trans(v):
        t = np.eye(4)
        t[:3, 3] = v
        return t

    shoulder = Origin((0, 0, 0.1)).matrix() @ rot((0, 0, 1), 0.4)
    upper = shoulder @ Origin((0, 0, 0.2), (0.3, 0, 0)).matrix() @ rot((0, 1, 0), -0.3)
    slider = upper @ Origin((0, 0, 0.3)).matrix() @ trans((0, 0, 0.15))
    flange = slider @ Origin((0, 0.02, 0.05), (0, 0, 0.5)).matrix()
    w1 = flange @ Origin((0, 0, 0.01)).matrix() @ seg(5.0, 1.0, 0.1)
    tool = w1 @ seg(0.0, 0.0, 0.1) @ Origin((0, 0, 0.03)).matrix()
    for name, expected in [("shoulder", shoulder), ("upper", upper), ("slider", slider),
                           ("flange", flange), ("w1", w1), ("tool", tool)]:  # fmt: skip
        assert np.allclose(frames[name], expected, atol=1e-14), name


def test_unnamed_variables_take_ros2_control_initial_values():
    robot = chain_robot(2, initial={"seg1": (1.5, 0.25), "seg2": (0.0, 0.0)})
    kin = RobotKinematics(robot)
    frames = kin.fk({"seg2": {"kappa": 2.0}})
    assert np.allclose(frames["link1"], seg(1.5, 0.25))
    assert np.allclose(frames["link2"], seg(1.5, 0.25) @ seg(2.0, 0.0))
    # a variable given alone keeps the other's initial value
    frames = kin.fk({"seg1": {"kappa": 1.0}})
    assert np.allclose(frames["link1"], seg(1.0, 0.25))


@pytest.mark.parametrize(
    "config,match",
    [
        ({"nope": {}}, r"unknown name\(s\) in configuration: 'nope'.*bendables: seg1"),
        ({"seg1": 1.0}, "needs an object of variables"),
        ({"seg1": {"kappa": 99.0}}, r"bendable 'seg1': kappa = 99 1/m is outside its limits"),
        ({"seg1": {"kappa": float("nan")}}, "must be finite"),
        ({"seg1": {"kapa": 1.0}}, "unknown variable"),
    ],
)
def test_bad_configurations_raise_clear_errors(config, match):
    with pytest.raises(ConfigError, match=match):
        robot_fk(chain_robot(2), config)


def test_rigid_joint_errors():
    robot = hybrid_robot()
    with pytest.raises(ConfigError, match="outside its limits"):
        robot_fk(robot, {"j3": 0.5})
    with pytest.raises(ConfigError, match="not movable"):
        robot_fk(robot, {"j4": 0.5})
    with pytest.raises(ConfigError, match="finite number"):
        robot_fk(robot, {"j1": "x"})
    # the host may pass measured values slightly past a limit: strict=False accepts them
    RobotKinematics(robot).fk({"j3": 0.21}, strict=False)
    # ... but never unknown names or non-numbers
    with pytest.raises(ConfigError, match="unknown variable"):
        RobotKinematics(robot).fk({"wrist1": {"kapa": 1.0}}, strict=False)
    with pytest.raises(ConfigError, match="finite number"):
        RobotKinematics(robot).fk({"wrist1": {"kappa": None}}, strict=False)


def test_broken_model_is_reported_with_the_bendable_name():
    robot = chain_robot(2)
    robot.bendables["seg2"].model.type = "nope"
    with pytest.raises(ModelError, match="bendable 'seg2': unknown model type 'nope'"):
        RobotKinematics(robot)


def test_backbone_frames_run_from_parent_to_child():
    robot = hybrid_robot()
    cfg = {"j1": 0.3, "wrist1": {"kappa": 8.0, "phi": -0.5}}
    frames = robot_fk(robot, cfg)
    curves = bendable_frames(robot, cfg, samples=9)
    assert curves["wrist1"].shape == (9, 4, 4)
    base = frames["flange"] @ Origin((0, 0, 0.01)).matrix()
    assert np.allclose(curves["wrist1"][0], base)
    assert np.allclose(curves["wrist1"][-1], frames["w1"])
    assert np.allclose(curves["wrist2"][-1], frames["w2"])
    steps = np.linalg.norm(np.diff(curves["wrist1"][:, :3, 3], axis=0), axis=1)
    assert np.allclose(steps, steps[0])  # equal arc steps give equal chords on a circle
    kin = RobotKinematics(robot)
    coords, joints = kin.coordinates(cfg)
    fast = kin.backbone_frames_coordinates(coords, joints, 9)
    assert all(np.allclose(fast[n], curves[n]) for n in curves)


def test_example_robot_file_if_present():
    path = ROBOTS_DIR / "softrobot3.ucrdf"
    if not path.exists():
        pytest.skip("robots/softrobot3.ucrdf not written yet")
    from ucrdf.parser import load

    robot = load(path)
    names = list(robot.bendables)
    kin = RobotKinematics(robot)
    frames = kin.fk({names[0]: {"kappa": 2.0, "phi": 0.5}})
    tip = robot.bendables[names[-1]].child
    assert frames[tip][2, 3] < 3 * 0.316  # bent: lower than the straight robot
    straight = kin.fk()
    assert np.allclose(
        straight[tip][:3, 3], [0, 0, sum(b.length for b in robot.bendables.values())]
    )
