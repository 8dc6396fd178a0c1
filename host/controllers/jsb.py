"""cJSB: the continuum joint state broadcaster. Publishes, at ``rate_hz``, the joint states of the
robot: (kappa, phi) and (kx, ky) per bendable (1/m, rad), each segment's own measurement time
stamp ``t_ms`` (ms since its boot, wraps at 2**30) plus the movable rigid joints.

Rigid joints have no hardware on this robot (the segments are all continuum): their positions are
the ``initial_value`` of their ``<ros2_control>`` state interface ``position`` (0 if none), marked
``"measured": false`` so nobody mistakes them for sensor data.
"""

from __future__ import annotations

from typing import Any

from host.controllers.base import Commands, Controller, ControllerContext, RobotState


def rigid_joint_positions(robot: Any) -> dict[str, float]:
    """Movable rigid joints -> their declared initial position (rad or m)."""
    out: dict[str, float] = {}
    if robot is None:
        return out
    declared: dict[str, float] = {}
    for block in getattr(robot, "ros2_control", []):
        for j in block.joints:
            for itf in list(j.command_interfaces) + list(j.state_interfaces):
                if itf.name == "position" and "initial_value" in itf.params:
                    try:
                        declared[j.name] = float(itf.params["initial_value"])
                    except (TypeError, ValueError):
                        pass
    for name, joint in robot.joints.items():
        if joint.movable:
            out[name] = declared.get(name, 0.0)
    return out


class JointStateBroadcaster(Controller):
    """cJSB. Parameters: rate_hz (publish rate, Hz, default 50)."""

    type_name = "jsb"
    claims_commands = False
    defaults = {**Controller.defaults, "rate_hz": 50.0}

    @classmethod
    def parse_params(cls, name: str, params: dict[str, Any]) -> dict[str, Any]:
        p = super().parse_params(name, params)
        p["rate_hz"] = cls.number_param(name, p, "rate_hz", lo=0.01)
        return p

    def __init__(self, name: str, params: dict[str, Any], ctx: ControllerContext):
        super().__init__(name, params, ctx)
        self.period = 1.0 / self.params["rate_hz"]
        self._next = 0.0
        self._rigid = rigid_joint_positions(ctx.robot)
        self._idx = [ctx.names.index(j) for j in self.joints]

    def on_activate(self, state: RobotState) -> None:
        self._next = 0.0
        self.active = True

    def on_deactivate(self, reason: str = "") -> None:
        self.active = False

    def message(self, state: RobotState) -> dict[str, Any]:
        idx = self._idx
        return {
            "kind": "joint_states",
            "t": state.t,
            "names": [state.names[i] for i in idx],
            "kappa": [state.kappa[i] for i in idx],
            "phi": [state.phi[i] for i in idx],
            "kx": [state.kx[i] for i in idx],
            "ky": [state.ky[i] for i in idx],
            "valid": [state.valid[i] for i in idx],
            "t_ms": [state.t_ms[i] if i < len(state.t_ms) else None for i in idx],
            "rigid": {k: {"position": v, "measured": False} for k, v in self._rigid.items()},
        }

    def update(self, state: RobotState, dt: float) -> Commands | None:
        if state.t >= self._next:
            self._next += self.period
            if self._next < state.t:  # first cycle or after a stall: restart the schedule
                self._next = state.t + self.period
            self.ctx.publish(self.message(state))
        return None
