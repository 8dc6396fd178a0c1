"""Robots for the kinematics tests, built directly from the ucrdf.model dataclasses."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from ucrdf.model import (
    Actuation,
    Backbone,
    Bendable,
    ControlJoint,
    CurvatureLimits,
    Interface,
    Joint,
    JointLimit,
    Link,
    ModelSpec,
    Origin,
    Robot,
    Ros2Control,
)

SEGMENT_LENGTH = 0.316  # m, the paper's segment
KAPPA_MAX = math.radians(60.0) / SEGMENT_LENGTH  # 1/m: a 60 deg bend
ROBOTS_DIR = Path(__file__).resolve().parents[2] / "robots"


def segment_spec(
    length: float = SEGMENT_LENGTH,
    kappa_max: float = KAPPA_MAX,
    model: str = "pcc",
    params: dict | None = None,
) -> ModelSpec:
    return ModelSpec(
        type=model,
        limits=CurvatureLimits(kappa_max=kappa_max, kappa_rate_max=1.0),
        backbone=Backbone(length=length, radius=0.004, youngs_modulus=200e9),
        params=dict(params or {}),
    )


def chain_robot(
    n: int = 3,
    *,
    model: str = "pcc",
    params: dict | None = None,
    length: float = SEGMENT_LENGTH,
    kappa_max: float = KAPPA_MAX,
    initial: dict[str, tuple[float, float]] | None = None,
) -> Robot:
    """base -> seg1 -> link1 -> seg2 -> ... -> link<n>, with a ros2_control block."""
    robot = Robot(name=f"chain{n}")
    robot.links["base"] = Link("base")
    rc = Ros2Control(name="hw", plugin="ucr/Hardware")
    parent = "base"
    for i in range(1, n + 1):
        child = f"link{i}"
        robot.links[child] = Link(child)
        name = f"seg{i}"
        robot.bendables[name] = Bendable(
            name=name,
            parent=parent,
            child=child,
            model=segment_spec(length, kappa_max, model, params),
            actuation=Actuation(
                angles=[0.0, 2 * math.pi / 3, 4 * math.pi / 3], radius=0.06, spool_radius=0.01
            ),
        )
        k0, p0 = (initial or {}).get(name, (0.0, 0.0))
        rc.joints.append(
            ControlJoint(
                name=name,
                command_interfaces=[
                    Interface("kappa", {"initial_value": k0, "min": 0.0, "max": kappa_max}),
                    Interface("phi", {"initial_value": p0, "min": -math.pi, "max": math.pi}),
                ],
                state_interfaces=[Interface("kappa"), Interface("phi")],
            )
        )
        parent = child
    robot.ros2_control.append(rc)
    return robot


def hybrid_robot() -> Robot:
    """A rigid arm (revolute + prismatic + fixed) with a 2-segment continuum wrist."""
    robot = Robot(name="hybrid")
    for name in ("world", "shoulder", "upper", "slider", "flange", "w1", "w2", "tool"):
        robot.links[name] = Link(name)
    robot.joints["j1"] = Joint(
        "j1", "revolute", "world", "shoulder", Origin((0, 0, 0.1)), (0, 0, 1),
        JointLimit(-math.pi, math.pi, 10, 1),
    )  # fmt: skip
    robot.joints["j2"] = Joint(
        "j2", "revolute", "shoulder", "upper", Origin((0, 0, 0.2), (0.3, 0, 0)), (0, 1, 0),
        JointLimit(-1.5, 1.5, 10, 1),
    )  # fmt: skip
    robot.joints["j3"] = Joint(
        "j3", "prismatic", "upper", "slider", Origin((0, 0, 0.3)), (0, 0, 1),
        JointLimit(0.0, 0.2, 10, 1),
    )  # fmt: skip
    robot.joints["j4"] = Joint(
        "j4", "fixed", "slider", "flange", Origin((0, 0.02, 0.05), (0, 0, 0.5))
    )
    robot.bendables["wrist1"] = Bendable(
        "wrist1", "flange", "w1", segment_spec(0.1, 10.0), Origin((0, 0, 0.01))
    )
    robot.bendables["wrist2"] = Bendable("wrist2", "w1", "w2", segment_spec(0.1, 10.0))
    robot.joints["tool_mount"] = Joint("tool_mount", "fixed", "w2", "tool", Origin((0, 0, 0.03)))
    return robot


@pytest.fixture
def robot3() -> Robot:
    return chain_robot(3)
