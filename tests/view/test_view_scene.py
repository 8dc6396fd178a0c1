"""What the view draws, without a browser: tubes follow the model plugin's true curve, tendon
routes have the lengths the tendon model gives, visuals come from the U(C)RDF; plus the slider
servo law, the Host/Origin guard and the missing-extra message."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from view_helpers import ROBOT

from ucrdf.fk import RobotKinematics
from ucrdf.parser import load
from ucrdf.tendons import TendonMap
from view.control import ARRIVED, FFC_DEADZONE, deflection
from view.guard import is_loopback, page_guard, refuse_reason
from view.scene import SceneModel, tube_faces

ROOT = ROBOT.parents[1]


@pytest.fixture(scope="module")
def model():
    return SceneModel(load(ROBOT))


def test_tubes_wrap_the_true_pcc_arc_not_a_straight_link(model):
    state = {"segment_1": {"kappa": 3.0, "phi": 0.7}, "segment_2": {"kappa": 1.0, "phi": -2.0}}
    fr = model.frame(state)
    kin = RobotKinematics(model.robot)
    links = kin.fk(state)
    for name in model.bendables:
        verts, faces = fr.tubes[name]
        assert faces.shape == ((model.samples - 1) * model.sides * 2, 3)
        rings = verts.reshape(model.samples, model.sides, 3)
        centres = rings.mean(axis=1)
        # the ring centres are the backbone samples: base and tip frames of the segment
        b = model.robot.bendables[name]
        assert np.allclose(centres[0], links[b.parent][:3, 3], atol=1e-6)
        assert np.allclose(centres[-1], links[b.child][:3, 3], atol=1e-6)
        # every vertex at the tube radius from its centre
        r = np.linalg.norm(rings - centres[:, None, :], axis=2)
        assert np.allclose(r, model.radius[name], atol=1e-6)
    # segment_1 bent at kappa = 3 1/m: its midpoint lies on the arc of radius 1/3 m, off the chord
    c = fr.tubes["segment_1"][0].reshape(model.samples, model.sides, 3).mean(axis=1)
    mid = c[model.samples // 2]
    chord_mid = (c[0] + c[-1]) / 2
    theta = 3.0 * model.robot.bendables["segment_1"].length
    sagitta = (1 / 3.0) * (1 - math.cos(theta / 2))
    assert np.linalg.norm(mid - chord_mid) == pytest.approx(sagitta, rel=0.02)


def test_tendon_routes_have_the_lengths_of_the_tendon_model(model):
    state = {"segment_2": {"kappa": 2.5, "phi": 1.1}}
    fr = model.frame(state)
    b = model.robot.bendables["segment_2"]
    tmap = TendonMap.for_bendable(b)
    want = tmap.lengths(2.5 * math.cos(1.1), 2.5 * math.sin(1.1))
    got = [float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) for p in fr.tendons["segment_2"]]
    assert got == pytest.approx(list(want), rel=5e-3)


def test_a_segment_without_a_declared_rate_uses_the_project_default(model):
    from protocol.constants import DEFAULT_KAPPA_RATE_MAX

    m = SceneModel(load(ROOT / "robots" / "hybrid_arm.ucrdf"))
    for name in m.bendables:
        declared = m.robot.bendables[name].model.limits.kappa_rate_max
        assert m.limits(name)[1] == (declared or DEFAULT_KAPPA_RATE_MAX)
    assert model.limits("segment_1") == (pytest.approx(3.3139163), 5.0)


def test_rigid_visuals_come_from_the_ucrdf():
    m = SceneModel(load(ROOT / "robots" / "hybrid_arm.ucrdf"))
    kinds = sorted(v.kind for v in m.visuals)
    assert kinds == ["box", "cylinder", "cylinder", "cylinder"]
    assert not any(v.problem for v in m.visuals)
    assert tube_faces(3, 4).max() == 3 * 4 - 1


def test_slider_deflection_points_at_the_target_and_never_stalls_in_the_deadzone():
    (ux, uy), _ = deflection((1.0, 0.0), (0.0, 0.0), 5.0)
    assert uy == 0.0 and 0 < ux <= 1.0
    assert deflection((3.0, 0.0), (-3.0, 0.0), 5.0) == ((1.0, 0.0), (5.0, 0.0))
    small, _ = deflection((0.1, 0.0), (0.0, 0.0), 5.0)
    assert FFC_DEADZONE < math.hypot(*small) <= 1.0
    assert deflection((0.5, 0.5), (0.5, 0.5 + ARRIVED / 2), 5.0) == ((0.0, 0.0), (0.0, 0.0))


def test_slider_deflection_cannot_carry_the_setpoint_past_the_target():
    """Whatever the distance, the setpoint rate that deflection gives the cFFC (default deadzone,
    gain 1), held for as long as one input can stay in force, stops at or before the target."""
    from view.control import HORIZON_S

    for d in (0.021, 0.05, 0.2, 1.0, 1.75, 3.0, 6.0):
        (ux, uy), (rx, ry) = deflection((d, 0.0), (0.0, 0.0), 5.0)
        mag = math.hypot(ux, uy)
        cffc = 5.0 * (min(mag, 1.0) - FFC_DEADZONE) / (1.0 - FFC_DEADZONE)  # ffc.rate_of
        assert math.isclose(cffc, math.hypot(rx, ry), rel_tol=1e-9)
        assert cffc * HORIZON_S <= d + 1e-12, d


@pytest.mark.parametrize(
    "params",
    [
        {"deadzone": 0.0},
        {"deadzone": 0.2},
        {"gain": 0.5},
        {"deadman_timeout": 1.0},
        {"deadzone": 0.0, "gain": 0.4, "deadman_timeout": 2.0},
    ],
)
def test_slider_deflection_follows_the_daemons_cffc_parameters(params):
    """docs/view.md "Limits" (2026-11-27): the drive assumed the cFFC's default deadzone,
    gain and deadman; a cFFC configured otherwise (e.g. no deadzone, or a 1 s deadman) moved
    faster, or longer on one input, than modelled and could carry its setpoint past a slider
    target. With the cFFC's own parameters (its controllers.list entry) the rate that deflection
    gives it is what the real cFFC does, and held as long as one input can stay in force it
    stops at or before the target."""
    from host.config import bendable_limits
    from host.controllers.base import ControllerContext
    from host.controllers.ffc import FeedForwardController
    from view.control import FfcParams

    robot = load(ROBOT)
    ffc = FeedForwardController("ffc", params, ControllerContext(bendable_limits(robot), robot,
                                                                 lambda _m: None))  # fmt: skip
    known = FfcParams.from_describe(ffc.describe())
    assert known is not None, ffc.describe()
    for d in (0.021, 0.05, 0.2, 1.0, 1.75, 3.0, 6.0):
        (ux, uy), (rx, ry) = deflection((d, 0.0), (0.0, 0.0), 5.0, known)
        real = math.hypot(*ffc.rate_of(ux, uy, 5.0))
        assert math.isclose(real, math.hypot(rx, ry), rel_tol=1e-9), (d, real, rx)
        assert real * (ffc.deadman_timeout + 0.05) <= d + 1e-12, (d, real)


def test_guard_allows_loopback_page_and_refuses_rebinding_and_cross_site():
    guard = page_guard("127.0.0.1", 8080)
    ok = {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:8080"}
    assert refuse_reason(ok, guard) is None
    assert refuse_reason({"Host": "localhost:8080"}, guard) is None
    local = {"Host": "localhost:8080", "Origin": "http://localhost:8080"}
    assert refuse_reason(local, guard) is None
    assert "host" in refuse_reason({"Host": "attacker.example:8080"}, guard)
    assert "Host" in refuse_reason({}, guard)
    bad_origin = {"Host": "127.0.0.1:8080", "Origin": "https://attacker.example"}
    assert "origin" in refuse_reason(bad_origin, guard)
    assert "origin" in refuse_reason({"Host": "127.0.0.1:8080", "Origin": "null"}, guard)
    other_port = {"Host": "127.0.0.1:8080", "Origin": "http://127.0.0.1:9999"}
    assert "origin" in refuse_reason(other_port, guard)
    assert refuse_reason(ok, None) is not None  # not started yet: nothing passes
    lan = page_guard("0.0.0.0", 8080, ["robot.local"])
    lan_page = {"Host": "robot.local:8080", "Origin": "http://robot.local:8080"}
    assert refuse_reason(lan_page, lan) is None
    assert is_loopback("127.0.0.2") and is_loopback("::1") and not is_loopback("0.0.0.0")


def test_missing_viser_gives_one_line_telling_what_to_install(tmp_path):
    # a site dir that hides viser
    hide = "raise ModuleNotFoundError(\"No module named 'viser'\", name='viser')\n"
    (tmp_path / "viser.py").write_text(hide)
    code = (
        f"import sys; sys.path.insert(0, {str(tmp_path)!r}); from tools.cli import main; "
        "sys.exit(main(['view']))"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert r.returncode == 1
    hint = f"ucr: ucr view needs the `view` extra (viser): pip install -e '{ROOT}[view]'"
    assert r.stderr.strip().startswith(hint), r.stderr
