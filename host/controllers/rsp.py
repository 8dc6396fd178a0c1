"""cRSP: the continuum robot state publisher. From the measured joint states it computes, with the
U(C)RDF forward kinematics (``ucrdf.fk.RobotKinematics``), the transform of every link frame in the
root frame, plus points sampled along each backbone for drawing, and publishes them at ``rate_hz``.

Message: ``{"kind": "transforms", "t": s, "root": link, "frames": {link: {"xyz": [m ×3],
"quat": [x, y, z, w]}}, "backbones": {bendable: [[x, y, z] m, …]}, "tip": {"link": name,
"xyz": [m ×3]}}``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from host.controllers.base import (
    Commands,
    Controller,
    ControllerContext,
    ControllerError,
    RobotState,
)
from ucrdf.fk import RobotKinematics
from ucrdf.models.base import ModelError


def quaternion(r: np.ndarray) -> list[float]:
    """Unit quaternion [x, y, z, w] of a 3x3 rotation matrix (Shepperd's method)."""
    t = r[0, 0] + r[1, 1] + r[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        w, x, y, z = (
            0.25 * s,
            (r[2, 1] - r[1, 2]) / s,
            (r[0, 2] - r[2, 0]) / s,
            (r[1, 0] - r[0, 1]) / s,
        )
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
        w, x, y, z = (
            (r[2, 1] - r[1, 2]) / s,
            0.25 * s,
            (r[0, 1] + r[1, 0]) / s,
            (r[0, 2] + r[2, 0]) / s,
        )
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
        w, x, y, z = (
            (r[0, 2] - r[2, 0]) / s,
            (r[0, 1] + r[1, 0]) / s,
            0.25 * s,
            (r[1, 2] + r[2, 1]) / s,
        )
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
        w, x, y, z = (
            (r[1, 0] - r[0, 1]) / s,
            (r[0, 2] + r[2, 0]) / s,
            (r[1, 2] + r[2, 1]) / s,
            0.25 * s,
        )
    return [x, y, z, w]


class RobotStatePublisher(Controller):
    """cRSP. Parameters: rate_hz (Hz, default 20), backbone_samples (points per bendable, 12)."""

    type_name = "rsp"
    claims_commands = False
    defaults = {**Controller.defaults, "rate_hz": 20.0, "backbone_samples": 12}

    @classmethod
    def parse_params(cls, name: str, params: dict[str, Any]) -> dict[str, Any]:
        p = super().parse_params(name, params)
        p["rate_hz"] = cls.number_param(name, p, "rate_hz", lo=0.01)
        n = p["backbone_samples"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ControllerError(f"controller {name!r}: backbone_samples must be an integer >= 2")
        return p

    def __init__(self, name: str, params: dict[str, Any], ctx: ControllerContext):
        super().__init__(name, params, ctx)
        self.period = 1.0 / self.params["rate_hz"]
        n = self.samples = self.params["backbone_samples"]
        if ctx.robot is None:
            raise ControllerError(f"controller {name!r}: needs the robot description for FK")
        try:
            self.kin = RobotKinematics(ctx.robot)
        except ModelError as exc:
            raise ControllerError(f"controller {name!r}: FK unavailable: {exc}") from None
        self._joints = {
            j: self.kin.defaults.get(j, {}).get("position", 0.0) for j in self.kin.movable_joints
        }
        self._s = {b: np.linspace(0.0, m.length, n) for b, m in self.kin.models.items()}
        self._next = 0.0
        order = [el.child for el in self.kin.order]
        self.tip = order[-1] if order else self.kin.root

    def on_activate(self, state: RobotState) -> None:
        self._next = 0.0
        self.active = True

    def on_deactivate(self, reason: str = "") -> None:
        self.active = False

    def compute(self, state: RobotState) -> dict[str, Any]:
        """FK of the measured state: the message this publisher sends."""
        coords = {}
        for i, name in enumerate(state.names):
            model = self.kin.models.get(name)
            if model is not None:
                coords[name] = model.to_coordinates({"kappa": state.kappa[i], "phi": state.phi[i]})
        for name, model in self.kin.models.items():
            coords.setdefault(name, model.to_coordinates({}))
        frames = self.kin.fk_coordinates(coords, self._joints)
        backbones = {}
        for name, model in self.kin.models.items():
            el = self.kin.elements[name]
            base = frames[el.parent] @ el.origin
            try:  # batched for PCC: one call for all samples
                local = model.backbone_curve(model.from_coordinates(coords[name]), self.samples)
            except ModelError:  # measured slightly beyond a limit: sample one by one, unchecked
                local = np.array(
                    [
                        model.transform_coordinates(coords[name], float(s))[:3, 3]
                        for s in self._s[name]
                    ]
                )
            pts = local @ base[:3, :3].T + base[:3, 3]
            backbones[name] = pts.round(6).tolist()
        return {
            "kind": "transforms",
            "t": state.t,
            "root": self.kin.root,
            "frames": {
                k: {"xyz": [float(v) for v in m[:3, 3]], "quat": quaternion(m[:3, :3])}
                for k, m in frames.items()
            },
            "backbones": backbones,
            "tip": {"link": self.tip, "xyz": [float(v) for v in frames[self.tip][:3, 3]]},
        }

    def update(self, state: RobotState, dt: float) -> Commands | None:
        if state.t >= self._next:
            self._next += self.period
            if self._next < state.t:
                self._next = state.t + self.period
            # FK of every frame is the heaviest work of a cycle and feeds only subscribers: run it
            # outside the control cycle (RobotState objects are never modified after creation).
            self.ctx.offload(lambda st=state: self.ctx.publish(self.compute(st)))
        return None
