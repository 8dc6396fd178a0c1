"""URDF export: loads in yourdfpy, and the pseudo-rigid chain converges to the model as the
number of subdivisions grows."""

from __future__ import annotations

import numpy as np
import pytest
import yourdfpy

from ucrdf.export import export_urdf, exported_tip_error, urdf_joint_positions
from ucrdf.fk import ConfigError, RobotKinematics
from ucrdf.model import Joint

from .conftest import ROBOTS_DIR, chain_robot, hybrid_robot

CFG3 = {
    "seg1": {"kappa": 3.0, "phi": 0.3},
    "seg2": {"kappa": 2.0, "phi": -2.0},
    "seg3": {"kappa": 3.3, "phi": 1.0},
}
HYBRID = {"j1": 0.5, "j2": -0.4, "j3": 0.1, "wrist1": {"kappa": 9.0, "phi": 1.0},
          "wrist2": {"kappa": 5.0, "phi": -1.0}}  # fmt: skip


def load(tmp_path, text, name="robot.urdf"):
    path = tmp_path / name
    path.write_text(text)
    return yourdfpy.URDF.load(str(path), load_meshes=False)


def test_tip_error_decreases_quadratically_with_subdivisions():
    robot = chain_robot(3)
    errors = [exported_tip_error(robot, n, CFG3)["link3"] for n in (2, 4, 8, 16, 32)]
    assert all(a > b for a, b in zip(errors, errors[1:], strict=False))
    assert all(3.5 < a / b < 4.5 for a, b in zip(errors, errors[1:], strict=False))  # O(1/N^2)
    assert errors[-1] < 1e-4


@pytest.mark.parametrize("n", [4, 32])
def test_movable_export_loads_in_yourdfpy_and_matches_fk(tmp_path, n):
    robot = chain_robot(3)
    urdf = load(tmp_path, export_urdf(robot, n))
    assert len(urdf.actuated_joint_names) == 3 * (2 * n + 1)
    q = urdf_joint_positions(robot, n, CFG3)
    urdf.update_cfg({name: q[name] for name in urdf.actuated_joint_names})
    exact = RobotKinematics(robot).fk(CFG3)
    got = urdf.get_transform("link3", "base")
    err = np.linalg.norm(got[:3, 3] - exact["link3"][:3, 3])
    assert err == pytest.approx(exported_tip_error(robot, n, CFG3)["link3"], abs=1e-12)
    assert np.allclose(got[:3, :3], exact["link3"][:3, :3], atol=1e-12)  # orientation exact
    # joint values stay inside the exported limits
    for name in urdf.actuated_joint_names:
        lim = urdf.joint_map[name].limit
        if lim is not None and lim.lower is not None:
            assert lim.lower <= q[name] <= lim.upper


def test_fixed_pose_export_and_straight_zero(tmp_path):
    robot = chain_robot(3)
    baked = load(tmp_path, export_urdf(robot, 16, CFG3), "baked.urdf")
    assert baked.actuated_joint_names == []
    exact = RobotKinematics(robot).fk(CFG3)["link3"]
    got = baked.get_transform("link3", "base")
    assert np.linalg.norm(got[:3, 3] - exact[:3, 3]) < 1e-3
    movable = load(tmp_path, export_urdf(robot, 5), "movable.urdf")
    assert np.allclose(movable.get_transform("link3", "base")[:3, 3], [0, 0, 3 * 0.316])


def test_example_robots_export_and_load(tmp_path):
    """Every example robot in robots/ exports (no generated-name clashes) and loads."""
    from ucrdf.parser import load as load_ucrdf

    files = sorted(ROBOTS_DIR.glob("*.ucrdf"))
    if not files:
        pytest.skip("no example robots yet")
    for path in files:
        robot = load_ucrdf(path)
        urdf = load(tmp_path, export_urdf(robot, 3), path.stem + ".urdf")
        assert set(robot.links) <= set(urdf.link_map), path.name
        mass = sum(link.inertial.mass for link in urdf.robot.links if link.inertial is not None)
        expected = sum(x.inertial.mass for x in [*robot.links.values(), *robot.bendables.values()]
                       if x.inertial is not None)  # fmt: skip
        assert mass == pytest.approx(expected), path.name


def test_hybrid_export_keeps_rigid_joints(tmp_path):
    robot = hybrid_robot()
    urdf = load(tmp_path, export_urdf(robot, 16))
    for name in ("j1", "j2", "j3"):
        assert name in urdf.actuated_joint_names
    assert urdf.joint_map["j3"].type == "prismatic"
    q = urdf_joint_positions(robot, 16, HYBRID)
    urdf.update_cfg({name: q[name] for name in urdf.actuated_joint_names})
    exact = RobotKinematics(robot).fk(HYBRID)["tool"]
    assert np.linalg.norm(urdf.get_transform("tool", "world")[:3, 3] - exact[:3, 3]) < 1e-4


def test_bad_subdivisions_and_name_clashes():
    with pytest.raises(ConfigError, match="subdivisions"):
        export_urdf(chain_robot(1), 0)
    robot = chain_robot(1)
    robot.links["seg1_prb1"] = robot.links["base"].__class__("seg1_prb1")
    robot.joints["j"] = Joint("j", "fixed", "link1", "seg1_prb1")
    with pytest.raises(ConfigError, match="seg1_prb1 already used"):
        export_urdf(robot, 4)
