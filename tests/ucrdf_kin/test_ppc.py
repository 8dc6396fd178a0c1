"""PPC (affine curvature) model: reduces to PCC, 4th-order accurate against an independent
fine-step reference, limits along the whole arc."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ucrdf.fk import RobotKinematics
from ucrdf.ik import solve_ik
from ucrdf.models import create
from ucrdf.models.base import ModelError
from ucrdf.models.pcc import pcc_transforms
from ucrdf.models.ppc import ppc_transforms

from .conftest import KAPPA_MAX, SEGMENT_LENGTH, chain_robot, segment_spec

L = SEGMENT_LENGTH


def reference(k0x, k0y, sx, sy, length, n=3000):
    """Classic RK4 on the 4x4 matrix ODE g' = g xi(s): independent of the Magnus integrator."""

    def f(s, g):
        kx, ky = k0x + sx * s, k0y + sy * s
        x = np.zeros((4, 4))
        x[0, 2], x[1, 2], x[2, 0], x[2, 1] = kx, ky, -kx, -ky  # [w]x with w = (-ky, kx, 0)
        x[2, 3] = 1.0
        return g @ x

    g, h = np.eye(4), length / n
    for i in range(n):
        s = i * h
        a = f(s, g)
        b = f(s + h / 2, g + h / 2 * a)
        c = f(s + h / 2, g + h / 2 * b)
        d = f(s + h, g + h * c)
        g = g + h / 6 * (a + 2 * b + 2 * c + d)
    return g


@settings(max_examples=40, deadline=None)
@given(
    kx=st.floats(-KAPPA_MAX, KAPPA_MAX),
    ky=st.floats(-KAPPA_MAX, KAPPA_MAX),
    steps=st.integers(1, 20),
)
def test_reduces_to_pcc_when_slopes_are_zero(kx, ky, steps):
    t = ppc_transforms(kx, ky, 0.0, 0.0, L, steps)[0]
    assert np.allclose(t, pcc_transforms(kx, ky, L)[0], atol=1e-13)


def test_model_with_zero_slopes_equals_pcc_model():
    ppc = create(segment_spec(model="ppc"))
    pcc = create(segment_spec())
    cfg = {"kappa": 2.5, "phi": -1.2}
    assert np.allclose(ppc.transform({**cfg, "kappa_x_slope": 0.0}), pcc.transform(cfg), atol=1e-13)
    assert np.allclose(ppc.transform(cfg, 0.1), pcc.transform(cfg, 0.1), atol=1e-13)


def test_accuracy_is_fourth_order_and_small_at_default_steps():
    coeffs = (1.0, -0.5, 6.0, 5.0)  # tip curvature 3.25 1/m: within the paper segment's limit
    ref = reference(*coeffs, L)
    errors = []
    for steps in (2, 4, 8, 16):
        t = ppc_transforms(*coeffs, L, steps)[0]
        errors.append(np.abs(t - ref).max())
    ratios = [errors[i] / errors[i + 1] for i in range(3)]
    assert all(r > 12 for r in ratios), (errors, ratios)  # 2^4 = 16 per halving
    assert errors[-1] < 1e-7  # default steps = 16: below 0.1 micrometre / microradian


def test_curvature_limit_holds_along_the_whole_arc():
    model = create(segment_spec(model="ppc"))
    model.check_config({"kappa": 1.0, "phi": 0.0, "kappa_x_slope": (KAPPA_MAX - 1.0) / L})
    with pytest.raises(ModelError, match="curvature at the segment tip"):
        model.check_config({"kappa": 1.0, "phi": 0.0, "kappa_x_slope": (KAPPA_MAX + 0.1) / L})
    q = model.project(np.array([0.0, 0.0, 100.0, 0.0]))
    assert math.hypot(q[0] + q[2] * L, q[1] + q[3] * L) <= KAPPA_MAX * (1 + 1e-12)


def test_params_are_checked():
    assert create(segment_spec(model="ppc", params={"steps": 4.0})).steps == 4
    with pytest.raises(ModelError, match="steps must be an integer"):
        create(segment_spec(model="ppc", params={"steps": 2.5}))
    with pytest.raises(ModelError, match="accepts only"):
        create(segment_spec(model="ppc", params={"order": 3.0}))


def test_ppc_robot_fk_and_ik_round_trip():
    robot = chain_robot(2, model="ppc")
    kin = RobotKinematics(robot)
    cfg = {
        "seg1": {"kappa": 1.5, "phi": 0.3, "kappa_x_slope": 2.0, "kappa_y_slope": -1.0},
        "seg2": {"kappa": 2.0, "phi": -1.0, "kappa_x_slope": -1.0},
    }
    target = kin.fk(cfg)["link2"][:3, 3]
    res = solve_ik(robot, target)
    assert res.success, res.message
    assert np.linalg.norm(kin.fk(res.config)["link2"][:3, 3] - target) <= 1e-4
