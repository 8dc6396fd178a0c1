"""Regression tests of a review of the kinematics commands: bad --config values are one-line
errors (never a traceback), baked exports bake rigid joints too, the subdivision count is bounded,
and bendable variables are checked like rigid joint values."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yourdfpy

from tests.cli_run import run_ucr
from ucrdf.export import export_urdf
from ucrdf.fk import ConfigError, RobotKinematics
from ucrdf.parser import load

from .conftest import ROBOTS_DIR
from .test_cli import run

SOFTROBOT2 = str(ROBOTS_DIR / "softrobot2.ucrdf")
REPO = ROBOTS_DIR.parent
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


# -- review of the commands' input and output ----------------------------------------------------
def test_a_config_file_that_is_not_utf8_is_a_usage_error(tmp_path, capsys):
    cfg = tmp_path / "cfg.json"
    data = '{"segment_1": {"kappa": 1.0, "phi": 0.5}} // Kr\xfcmmung'.encode("latin-1")
    cfg.write_bytes(data)
    for argv in (
        ["fk", SOFTROBOT2, "--config", f"@{cfg}"],
        ["ik", SOFTROBOT2, "--target", "0,0,0.3", "--initial", f"@{cfg}"],
    ):
        code, out, err = run(argv, capsys)
        assert (code, out) == (2, "") and err.count("\n") == 1, err
        assert "cannot read" in err and f"not UTF-8 text (byte {data.index(0xFC)})" in err


@pytest.mark.parametrize(
    "config",
    [
        '{"segment_1": {"kappa": 1.0}, "segment_1": {"kappa": 2.0}}',
        '{"segment_1": {"kappa": 1.0, "kappa": 2.0}}',
    ],
)
def test_a_key_given_twice_is_refused_not_the_last_one_taken(config, capsys):
    code, out, err = run(["fk", SOFTROBOT2, "--config", config], capsys)
    assert (code, out) == (2, "") and err.count("\n") == 1
    assert "--config: key 'segment_1' is given twice" in err or "key 'kappa' is given twice" in err


@pytest.mark.parametrize("tol", ["abc", "-1", "nan", "1_0"])
def test_every_unusable_tol_is_the_same_usage_error(tol, capsys):
    code, out, err = run(["ik", SOFTROBOT2, "--target", "0,0,0.3", f"--tol={tol}"], capsys)
    assert (code, out) == (2, "")
    assert err == f"ucr ik: error: --tol must be a positive number of metres, got {tol!r}\n"


@pytest.mark.parametrize("n", ["abc", "0", "1_0", "٣"])
def test_every_unusable_subdivision_count_is_the_same_usage_error(n, capsys):
    code, out, err = run(["export-urdf", SOFTROBOT2, "-n", n, "-o", "-"], capsys)
    assert (code, out) == (2, "")
    assert err == f"ucr export-urdf: error: --subdivisions must be in 1..1000, got {n!r}\n"


def test_a_target_python_alone_reads_is_refused(capsys):
    code, _, err = run(["ik", SOFTROBOT2, "--target", "0,0,1_0"], capsys)
    assert code == 2 and "--target must be three numbers x,y,z in m, got '0,0,1_0'" in err


def test_a_non_finite_fk_result_is_an_error_not_invalid_json(monkeypatch, capsys):
    from ucrdf import fk  # noqa: PLC0415

    def overflowed(self, config=None):
        return {"base": np.eye(4), "tip": np.full((4, 4), np.nan)}

    monkeypatch.setattr(fk.RobotKinematics, "fk", overflowed)
    code, out, err = run(["fk", SOFTROBOT2], capsys)
    assert (code, out) == (1, "")
    assert err == "ucr fk: error: the transform of link 'tip' is not finite (numbers overflow)\n"


def test_a_non_finite_ik_result_is_an_error_not_invalid_json(monkeypatch, capsys):
    import types  # noqa: PLC0415

    from ucrdf import ik  # noqa: PLC0415

    result = types.SimpleNamespace(
        success=False, residual=math.inf, iterations=3, message="no solution", tip="t", config={}
    )
    monkeypatch.setattr(ik, "solve_ik", lambda *a, **k: result)
    code, out, err = run(["ik", SOFTROBOT2, "--target", "0,0,0.3"], capsys)
    assert (code, out) == (1, "") and err.count("\n") == 1
    assert "the solution is not finite (residual inf)" in err


def test_a_robot_whose_numbers_overflow_never_reaches_fk(tmp_path, capsys):
    path = tmp_path / "far.ucrdf"
    path.write_text(
        '<robot name="r"><link name="a"/><link name="b"/><link name="c"/>\n'
        '<joint name="j1" type="fixed"><parent link="a"/><child link="b"/>'
        '<origin xyz="1e308 0 0"/></joint>\n'
        '<joint name="j2" type="fixed"><parent link="b"/><child link="c"/>'
        '<origin xyz="1e308 0 0"/></joint></robot>\n'
    )
    code, out, err = run(["fk", str(path)], capsys)
    assert (code, out) == (1, "") and "NaN" not in err and "Warning" not in err
    why = "origin xyz 1e+308 m is beyond ±1e+06 m: no robot is that large (a unit mistake?)"
    assert err.splitlines() == [f"{path}:2: joint 'j1': {why}", f"{path}:3: joint 'j2': {why}"]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
@pytest.mark.parametrize(
    "argv",
    [
        ["fk", SOFTROBOT2],
        ["ik", SOFTROBOT2, "--target", "0,0,0.3"],
        ["export-urdf", SOFTROBOT2, "-n", "2", "-o", "-"],
    ],
)
def test_a_stdout_that_cannot_take_the_output_is_one_line(argv):
    with open("/dev/full", "w") as full:
        result = run_ucr(*argv, stdout=full)
    assert result.returncode == 1
    assert (
        result.stderr == f"ucr {argv[0]}: error: cannot write the output: No space left on device\n"
    )
