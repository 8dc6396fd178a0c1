"""Regression tests of a review of the kinematics commands: bad --config values are one-line
errors (never a traceback), baked exports bake rigid joints too, the subdivision count is bounded,
and bendable variables are checked like rigid joint values."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yourdfpy

from ucrdf.export import export_urdf
from ucrdf.fk import ConfigError, RobotKinematics
from ucrdf.parser import load

from .conftest import ROBOTS_DIR
from .test_cli import run

SOFTROBOT2 = str(ROBOTS_DIR / "softrobot2.ucrdf")
HYBRID = ROBOTS_DIR / "hybrid_arm.ucrdf"


# -- 7: --config with a huge integer -------------------------------------------------------------
@pytest.mark.parametrize("option", ["fk", "ik", "export"])
def test_huge_integer_in_json_option_is_one_line(option, capsys, tmp_path):
    huge = '{"segment_1": {"kappa": 1' + "0" * 5000 + "}}"
    argv = {
        "fk": ["fk", SOFTROBOT2, "--config", huge],
        "ik": ["ik", SOFTROBOT2, "--target", "0,0,0.6", "--initial", huge],
        "export": ["export-urdf", SOFTROBOT2, "-o", str(tmp_path / "x.urdf"), "--config", huge],
    }[option]
    code, out, err = run(argv, capsys)
    assert code == 2 and out == ""  # a bad option value: usage, exit 2
    assert err.count("\n") == 1 and "digits" in err and "is not usable JSON" in err


# -- 8: export-urdf --config bakes rigid joints ---------------------------------------------------
def test_baked_export_fixes_rigid_joints_at_their_configured_value(tmp_path):
    robot = load(HYBRID)
    config = {"shoulder_yaw": 0.7, "elbow": -0.4, "wrist": {"kappa": 5.0, "phi": 0.3}}
    path = tmp_path / "baked.urdf"
    path.write_text(export_urdf(robot, 8, config))
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    assert urdf.actuated_joint_names == []  # a static snapshot: nothing left movable
    exact = RobotKinematics(robot).fk(config)
    for link in ("upper_arm", "forearm", "wrist_base"):
        got = urdf.get_transform(link, "base_link")
        np.testing.assert_allclose(got, exact[link], atol=1e-9)


# -- 9: --subdivisions bound ----------------------------------------------------------------------
def test_subdivisions_have_an_upper_bound(capsys, tmp_path):
    from ucrdf.export import MAX_SUBDIVISIONS  # noqa: PLC0415 - the bound under test

    code, _, err = run(
        ["export-urdf", SOFTROBOT2, "-n", "100000000", "-o", str(tmp_path / "x.urdf")], capsys
    )
    assert code == 2 and f"--subdivisions must be in 1..{MAX_SUBDIVISIONS}" in err
    with pytest.raises(ConfigError, match="1..1000"):
        export_urdf(load(SOFTROBOT2), MAX_SUBDIVISIONS + 1)


# -- 11: bendable variables are numbers; ik --initial is checked like fk --config -----------------
@pytest.mark.parametrize("value", ['"1"', "true"])
def test_bendable_variable_must_be_a_number(value, capsys):
    code, out, err = run(
        ["fk", SOFTROBOT2, "--config", f'{{"segment_1": {{"kappa": {value}, "phi": 0}}}}'], capsys
    )
    assert code == 1 and out == ""
    assert "kappa must be a number" in err
    with pytest.raises(ConfigError, match="kappa must be a number"):
        RobotKinematics(load(SOFTROBOT2)).fk({"segment_1": {"kappa": json.loads(value)}})


@pytest.mark.parametrize("kappa", [9, -2])
def test_ik_initial_outside_the_limits_is_refused_like_fk_config(kappa, capsys):
    config = f'{{"segment_1": {{"kappa": {kappa}}}}}'
    fk_code, _, fk_err = run(["fk", SOFTROBOT2, "--config", config], capsys)
    code, out, err = run(["ik", SOFTROBOT2, "--target", "0,0,0.6", "--initial", config], capsys)
    assert fk_code == 1 and code == 1 and out == ""
    assert "outside its limits" in fk_err and "--initial: " in err and "outside its limits" in err


@pytest.mark.parametrize("command", ["fk", "export-urdf"])
def test_the_cli_refuses_a_phi_in_degrees_instead_of_wrapping_it(command, capsys) -> None:
    """Commissioning audit 2026-11-26: `ucr fk --config '{"seg1": {"kappa": 2, "phi": 90}}'`
    was accepted and wrapped (90 rad = 116.6 deg): a unit mistake, refused with the radians."""
    name = next(iter(load(SOFTROBOT2).bendables))
    config = json.dumps({name: {"kappa": 2.0, "phi": 90}})
    extra = ["-o", "-"] if command == "export-urdf" else []
    code, _, err = run([command, SOFTROBOT2, "--config", config, *extra], capsys)
    assert code != 0 and "1.5708 rad" in err and "Traceback" not in err, err
    within = json.dumps({name: {"kappa": 2.0, "phi": -6.0}})
    assert run(["fk", SOFTROBOT2, "--config", within], capsys)[0] == 0
