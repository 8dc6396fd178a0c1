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


# -- what the export carries over from the rigid part ----------------------------------------------
EXTENDED = """<robot name="r" xmlns:v="http://example.com/vendor">
  <material name="red"><color rgba="1 0 0 1"/></material>
  <link name="a">
    <visual><geometry><box size="0.1 0.1 0.1"/></geometry><material name="red"/></visual>
    <v:note k="1"/>
  </link>
  <link name="b"/><link name="c"/><link name="d"/>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
    <dynamics damping="0.7" friction="0.1"/><calibration rising="0.1"/>
    <safety_controller soft_lower_limit="-0.9" soft_upper_limit="0.9" k_position="10"
                       k_velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
    <origin xyz="0.2 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
    <mimic joint="j1" multiplier="2" offset="0.1"/></joint>
  <bendable name="seg"><parent link="c"/><child link="d"/>
    <curvature><model type="pcc"><limits kappa_max="3.0" kappa_rate_max="1.0"/>
      <backbone length="0.3" radius="0.003" youngs_modulus="1e11"/></model></curvature>
  </bendable>
  <gazebo reference="a"><material>Gazebo/Red</material></gazebo>
  <transmission name="t"><type>transmission_interface/SimpleTransmission</type>
    <joint name="j1"><hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>
    </joint><actuator name="m"><mechanicalReduction>1</mechanicalReduction></actuator>
  </transmission>
  <v:extra x="1"><v:y/></v:extra>
</robot>
"""
_URDF_JOINT_PARTS = ("origin", "parent", "child", "axis", "limit")


def _children(el, skip=()):
    from ucrdf.parser import normalise_xml

    return [normalise_xml(c) for c in el if isinstance(c.tag, str) and c.tag not in skip]


def test_export_keeps_materials_joint_children_and_extensions(tmp_path):
    """The export dropped global materials (visuals then named a colour defined nowhere),
    <dynamics>, <calibration>, <safety_controller>, <mimic>, link and top-level extensions."""
    from lxml import etree

    from ucrdf.parser import parse_string

    robot = parse_string(EXTENDED)
    warned = []
    text = export_urdf(robot, 3, warn=warned.append)
    assert warned == []
    out = etree.fromstring(text.encode())
    top = [e for e in out if isinstance(e.tag, str) and e.tag not in ("link", "joint")]
    assert _children(top) == robot.extensions  # every one, unchanged, in document order
    assert out.index(out.find("material")) < out.index(out.find("link"))
    for joint in robot.joints.values():
        exported = out.find(f"joint[@name='{joint.name}']")
        assert _children(exported, _URDF_JOINT_PARTS) == joint.extensions, joint.name
    assert _children(out.find("link[@name='a']"), ("visual",)) == robot.links["a"].extensions
    urdf = load(tmp_path, text)
    assert urdf.validate()
    assert urdf.robot.materials[0].color.rgba.tolist() == [1, 0, 0, 1]
    assert float(urdf.joint_map["j1"].dynamics.damping) == 0.7
    mimic = urdf.joint_map["j2"].mimic
    assert (mimic.joint, mimic.multiplier, mimic.offset) == ("j1", 2.0, 0.1)
    assert "j2" not in urdf.actuated_joint_names
    config = {"j1": 0.3, "seg": {"kappa": 2.0, "phi": 0.4}}
    q = urdf_joint_positions(robot, 3, config)
    urdf.update_cfg({name: q[name] for name in urdf.actuated_joint_names})
    exact = RobotKinematics(robot).fk(config)
    assert np.allclose(urdf.get_transform("c", "a"), exact["c"], atol=1e-12)  # 0.3 + 0.7 rad


def test_hybrid_arm_export_keeps_its_dynamics_gazebo_transmission_and_material(tmp_path):
    from lxml import etree

    from ucrdf.parser import load as load_ucrdf

    robot = load_ucrdf(ROBOTS_DIR / "hybrid_arm.ucrdf")
    warned = []
    text = export_urdf(robot, 4, warn=warned.append)
    assert warned == []
    out = etree.fromstring(text.encode())
    assert [e.tag for e in out if e.tag in ("material", "gazebo", "transmission")] == [
        "material", "gazebo", "transmission"
    ]  # fmt: skip
    assert _children(out.find("joint[@name='shoulder_yaw']"), _URDF_JOINT_PARTS) == [
        '<dynamics damping="0.1" friction="0.0"></dynamics>'
    ]
    assert out.find("ros2_control") is None  # replaced, as the bendables are
    urdf = load(tmp_path, text)
    assert urdf.robot.materials[0].name == "grey"
    assert urdf.robot.materials[0].color.rgba.tolist() == [0.6, 0.6, 0.6, 1.0]


def test_baked_export_names_the_mimic_it_cannot_keep(tmp_path, capsys):
    """A fixed joint follows nothing: the baked export leaves out <mimic>, with a warning on
    stderr, and keeps the joint's other children."""
    from lxml import etree

    from ucrdf.parser import parse_string

    robot = parse_string(EXTENDED)
    config = {"j1": 0.3, "seg": {"kappa": 2.0, "phi": 0.4}}
    text = export_urdf(robot, 3, config)
    err = capsys.readouterr().err
    assert err.splitlines() == [
        (
            "warning: URDF export: joint 'j2': <mimic joint='j1'> not carried over: the fixed "
            "pose bakes its position (0.7) into a fixed joint"
        )
    ]
    out = etree.fromstring(text.encode())
    assert _children(out.find("joint[@name='j2']"), _URDF_JOINT_PARTS) == []
    kept = _children(out.find("joint[@name='j1']"), _URDF_JOINT_PARTS)
    assert kept == robot.joints["j1"].extensions
    baked = load(tmp_path, text)
    exact = RobotKinematics(robot).fk(config)
    assert np.allclose(baked.get_transform("c", "a"), exact["c"], atol=1e-12)


def test_an_extension_naming_a_bendable_is_kept_with_a_warning():
    from ucrdf.parser import parse_string

    text = EXTENDED.replace('<gazebo reference="a">', '<gazebo reference="seg">')
    warned = []
    out = export_urdf(parse_string(text), 2, warn=warned.append)
    assert '<gazebo reference="seg">' in out
    assert len(warned) == 1 and "top-level <gazebo> refers to bendable 'seg'" in warned[0]
