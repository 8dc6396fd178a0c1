"""URDF ``<mimic>`` in FK and IK: a mimic joint's position is multiplier * master + offset, it
takes no value of its own, its limits hold, and a mimic that cannot work is refused."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ucrdf.fk import ConfigError, RobotKinematics
from ucrdf.ik import IKSolver
from ucrdf.models.base import ModelError
from ucrdf.parser import parse_string

from .test_cli import run

MIMIC = """<robot name="r">
  <link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="e"/>
  <joint name="j1" type="revolute"><parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="b"/><child link="c"/><axis xyz="0 0 1"/>
    <origin xyz="0.2 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
    <mimic joint="j1" multiplier="2"{offset}/></joint>
  <joint name="tool" type="fixed"><parent link="c"/><child link="d"/>
    <origin xyz="0.1 0 0" rpy="0 1.5707963267948966 0"/></joint>
  <bendable name="seg"><parent link="d"/><child link="e"/>
    <curvature><model type="pcc"><limits kappa_max="3.0" kappa_rate_max="1.0"/>
      <backbone length="0.2" radius="0.003" youngs_modulus="1e11"/></model></curvature>
  </bendable>
</robot>
"""


def mimic_robot(offset: str = ""):
    return parse_string(MIMIC.format(offset=offset))


def rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize(("offset", "value"), [("", 1.0), (' offset="-0.25"', 0.75)])
def test_mimic_joint_follows_its_master(offset, value):
    """j1 = 0.5 turned link c by 0.5 rad (j2 stayed at 0); with multiplier 2 it is 0.5 + 2*0.5."""
    kin = RobotKinematics(mimic_robot(offset))
    _, joints = kin.resolve({"j1": 0.5})
    assert joints == {"j1": 0.5, "j2": value}
    frames = kin.fk({"j1": 0.5})
    assert np.allclose(frames["c"][:3, :3], rz(0.5 + value), atol=1e-15)
    assert np.allclose(frames["c"][:3, 3], rz(0.5) @ [0.2, 0.0, 0.0], atol=1e-15)
    # the fast path takes the master's position too, without the mimic joint's own
    fast = kin.fk_coordinates({"seg": np.zeros(2)}, {"j1": 0.5})
    assert np.allclose(fast["e"], frames["e"], atol=1e-15)


def test_a_value_for_a_mimic_joint_is_refused():
    kin = RobotKinematics(mimic_robot())
    refused = r"joint 'j2' mimics 'j1' \(position = 2 \* j1 \+ 0\) and takes no value of its own"
    with pytest.raises(ConfigError, match=refused + ": give 'j1'"):
        kin.fk({"j2": 0.5})
    with pytest.raises(ConfigError, match="mimics 'j1'"):
        kin.resolve({"j1": 0.1, "j2": 0.2}, strict=False)


def test_mimic_joint_limits_hold_for_the_masters_value():
    kin = RobotKinematics(mimic_robot())
    outside = (
        r"joint 'j2' = 1\.6 is outside its limits \[-1, 1\] \(mimicking 'j1': 2 \* 0\.8 \+ 0\)"
    )
    with pytest.raises(ConfigError, match=outside):
        kin.fk({"j1": 0.8})
    assert kin.resolve({"j1": 0.8}, strict=False)[1]["j2"] == pytest.approx(1.6)


@pytest.mark.parametrize(
    ("mimic", "match"),
    [
        ('joint="nope"', r"<mimic joint='nope'> names nothing in the robot"),
        ('joint="seg"', r"names a bendable: a joint can mimic a movable joint only"),
        ('joint="tool"', r"names a fixed joint, which does not move"),
        ('joint="j2"', r"a joint cannot mimic itself"),
        ('joint="j1" multiplier="two"', r"multiplier must be a finite number, got 'two'"),
        ('joint="j1" offset="nan"', r"offset must be a finite number, got 'nan'"),
        ('multiplier="2"', r"<mimic> needs a joint attribute"),
    ],
)
def test_a_mimic_that_cannot_work_is_refused(mimic, match):
    text = MIMIC.format(offset="").replace(
        '<mimic joint="j1" multiplier="2"/>', f"<mimic {mimic}/>"
    )
    robot = parse_string(text, check=False)
    with pytest.raises(ModelError, match=match):
        RobotKinematics(robot)


def test_a_chain_of_mimic_joints_is_refused():
    text = MIMIC.format(offset="").replace(
        '<joint name="tool" type="fixed">',
        '<joint name="tool" type="revolute"><limit lower="-1" upper="1" effort="1" velocity="1"/>'
        '<mimic joint="j2"/>',
    )
    with pytest.raises(ModelError, match="names a joint that mimics 'j1' itself"):
        RobotKinematics(parse_string(text, check=False))


@pytest.mark.parametrize("j1", [-0.5, 0.1, 0.4])
def test_ik_moves_a_mimic_joint_with_its_master(j1):
    """IK took the mimic joint for an independent unknown: a configuration FK then refuses."""
    kin = RobotKinematics(mimic_robot(' offset="0.1"'))
    config = {"j1": j1, "seg": {"kappa": 2.0, "phi": 0.4}}
    target = kin.fk(config)["e"][:3, 3]
    result = IKSolver(kin).solve(target)
    assert result.success, result.message
    assert set(result.config) == {"j1", "seg"}
    assert np.linalg.norm(kin.fk(result.config)["e"][:3, 3] - target) <= 1e-4


def test_ik_keeps_the_master_where_the_mimic_joint_stays_in_its_limits():
    """j2 = 2 j1 + 0.1 within [-1, 1] bounds j1 to [-0.55, 0.45] although its own limits are
    [-1, 1]: a target that needs j1 = 0.7 is not reached by breaking j2's limits."""
    kin = RobotKinematics(mimic_robot(' offset="0.1"'))
    config = {"j1": 0.7, "seg": {"kappa": 0.0, "phi": 0.0}}
    target = kin.fk(config, strict=False)["e"][:3, 3]
    result = IKSolver(kin).solve(target)
    assert -0.55 - 1e-12 <= result.config["j1"] <= 0.45 + 1e-12
    kin.fk(result.config)  # within every limit
    if result.success:  # another configuration may reach it; never one FK refuses
        assert np.linalg.norm(kin.fk(result.config)["e"][:3, 3] - target) <= 1e-4


def test_ucr_fk_moves_the_mimic_joint(tmp_path, capsys):
    path = tmp_path / "mimic.ucrdf"
    path.write_text(MIMIC.format(offset=""))
    code, out, err = run(["fk", str(path), "--config", '{"j1": 0.5}'], capsys)
    assert code == 0, err
    assert np.allclose(np.array(json.loads(out)["c"])[:3, :3], rz(1.5), atol=1e-15)
    code, out, err = run(["fk", str(path), "--config", '{"j2": 0.5}'], capsys)
    assert code == 1 and "joint 'j2' mimics 'j1'" in err


def test_a_mimic_joint_no_master_position_can_satisfy_is_refused_by_ik():
    """multiplier 0, offset 5: j2 sits at 5 rad whatever j1 does, outside its limits [-1, 1]."""
    text = MIMIC.format(offset="").replace('multiplier="2"', 'multiplier="0" offset="5"')
    kin = RobotKinematics(parse_string(text, check=False))
    with pytest.raises(ConfigError, match=r"joint 'j2' = 5 is outside its limits \[-1, 1\]"):
        kin.fk({"j1": 0.0})
    with pytest.raises(ConfigError, match="limits of mimic joint 'j2' leave no position of 'j1'"):
        IKSolver(kin)


def test_ucr_check_reports_each_mimic_fk_cannot_follow_at_its_joint(tmp_path, capsys):
    """Whatever `ucr check` accepts, `ucr fk` takes: a <mimic> naming nothing (or a chain of
    them) passed the check and failed only in fk."""
    from tools.cli import main as ucr

    def check(path) -> tuple[int, str]:
        code = ucr(["check", str(path)])
        return code, capsys.readouterr().err

    bad = MIMIC.format(offset="").replace('<mimic joint="j1"', '<mimic joint="nothere"')
    f = tmp_path / "bad.ucrdf"
    f.write_text(bad)
    code, err = check(f)
    line = bad[: bad.index("nothere")].count("\n") - 1  # the <joint name="j2"> line
    assert code == 1
    assert f"{f}:{line}: joint 'j2': <mimic joint='nothere'> names nothing in the robot" in err
    f.write_text(MIMIC.format(offset=""))
    assert check(f)[0] == 0


def test_the_tf_of_a_mimic_joint_follows_its_master():
    """/tf (interop/topics.py) gave a mimic joint 0 unless the daemon's state named it; it is
    multiplier * master + offset, as ucr fk computes it."""
    from interop.topics import RobotTopics
    from ucrdf.writer import dumps

    robot = mimic_robot(' offset="0.1"')
    topics = RobotTopics(robot, dumps(robot), 2)
    js = {"names": ["seg"], "kappa": [0.0], "phi": [0.0], "rigid": {"j1": {"position": 0.3}}}
    q = topics.joint_positions(js)
    assert q["j2"] == pytest.approx(2 * 0.3 + 0.1)
    frames = RobotKinematics(robot).fk_coordinates({"seg": np.zeros(2)}, {"j1": 0.3})
    tf = {t["child_frame_id"]: t for t in topics.tf(js, 0).msg["transforms"]}
    quat = tf["c"]["transform"]["rotation"]
    yaw = 2 * math.atan2(quat["z"], quat["w"])
    assert yaw == pytest.approx(0.7)  # the joint's own rotation: 2 * 0.3 + 0.1 rad
    assert frames["c"][:3, :3] == pytest.approx(rz(1.0))  # j1 then j2: 0.3 + 0.7 rad
