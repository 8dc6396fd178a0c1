"""Build a U(C)RDF robot from the segment descriptors a discovered chain reports.

Each descriptor (the host-side decoded DESCRIPTOR dict of docs/architecture.md: ``uid, model,
length, tendon_angles, tendon_radius, spool_radius, kappa_max, kappa_rate_max, mass,
backbone_radius, name, servo_driver, …``) becomes one bendable, chained from the base link:
``base -> <seg1>_tip -> <seg2>_tip -> …``, with a ros2_control block whose kappa/phi interfaces
are bounded by each segment's own limits and whose ``<hardware>`` pins each segment's unique id
(``<param name="<bendable>/uid">``). The result is checked before it is returned, so a
descriptor with impossible values is reported, never written.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ucrdf.checks import check
from ucrdf.errors import Diagnostic, UcrdfError
from ucrdf.model import (
    Actuation,
    Backbone,
    Bendable,
    ControlJoint,
    CurvatureLimits,
    Inertial,
    Interface,
    Link,
    ModelSpec,
    Origin,
    Robot,
    Ros2Control,
)
from ucrdf.writer import dump

#: Descriptor keys a segment must report for a usable description (SI units).
REQUIRED_KEYS = ("length", "tendon_angles", "tendon_radius", "spool_radius", "kappa_max")

#: Hardware plugin named in generated ros2_control blocks (the paper's Listing 1).
PLUGIN = "SoftRobotInterface"
DEFAULT_BAUDRATE = 921600

_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]*$")


def _number(desc: Mapping[str, Any], key: str, where: str, problems: list[str]) -> float:
    value = desc.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        problems.append(f"{where}: {key} must be a finite number, got {value!r}")
        return math.nan
    return float(value)


def _segment_names(descriptors: Sequence[Mapping[str, Any]]) -> list[str]:
    """The descriptor's own name when it is a usable identifier given to exactly one segment,
    else ``segment_<k>`` (k = 1-based chain position); never clashing with another name."""
    given = [
        d["name"] if isinstance(d, Mapping) and isinstance(d.get("name"), str) else ""
        for d in descriptors
    ]
    counts = Counter(given)
    names: list[str] = []
    taken: set[str] = {"base"}
    for k, name in enumerate(given, start=1):
        usable = bool(name) and counts[name] == 1 and _NAME_RE.match(name) and name != "base"
        candidate = name if usable else f"segment_{k}"
        while candidate in taken or f"{candidate}_tip" in taken:
            candidate += "_"
        names.append(candidate)
        taken.update((candidate, f"{candidate}_tip"))
    return names


def _inertial(mass: float, length: float, radius: float) -> Inertial:
    """Mass as a solid cylinder of the given radius along the straight backbone (an
    approximation: descriptors carry the mass only), centre of mass at half length."""
    ixx = mass * (3.0 * radius**2 + length**2) / 12.0
    izz = mass * radius**2 / 2.0
    return Inertial(
        mass=mass,
        origin=Origin(xyz=(0.0, 0.0, length / 2.0)),
        inertia=(ixx, 0.0, 0.0, ixx, 0.0, izz),
    )


def robot_from_descriptors(
    descriptors: Sequence[Mapping[str, Any]],
    name: str = "robot",
    *,
    port: str = "auto",
    baudrate: int = DEFAULT_BAUDRATE,
) -> Robot:
    """A checked Robot for the chain ``descriptors`` (chain order, base first).

    Raises UcrdfError (source ``<descriptors>``) listing every missing or invalid value, or the
    semantic problems of the resulting description.
    """
    source = "<descriptors>"
    if not descriptors:
        raise UcrdfError([Diagnostic(source, 0, "no segment descriptors: the chain is empty")])
    problems: list[str] = []
    names = _segment_names(descriptors)
    robot = Robot(name=name, source=source)
    robot.links["base"] = Link(name="base")
    control = Ros2Control(
        name=name,
        type="system",
        plugin=PLUGIN,
        hardware_params={"port": port, "baudrate": str(int(baudrate))},
    )
    parent = "base"
    models: list[str] = []
    uids: dict[str, str] = {}
    for k, (desc, seg) in enumerate(zip(descriptors, names, strict=True), start=1):
        where = f"descriptor {k} ({seg})"
        if not isinstance(desc, Mapping):
            problems.append(f"descriptor {k}: expected a dict, got {type(desc).__name__}")
            continue
        missing = [key for key in REQUIRED_KEYS if key not in desc]
        if missing:
            problems.append(f"{where}: missing {', '.join(missing)}")
            continue
        length = _number(desc, "length", where, problems)
        kappa_max = _number(desc, "kappa_max", where, problems)
        tendon_radius = _number(desc, "tendon_radius", where, problems)
        spool_radius = _number(desc, "spool_radius", where, problems)
        rate = (
            _number(desc, "kappa_rate_max", where, problems) if "kappa_rate_max" in desc else None
        )
        mass = _number(desc, "mass", where, problems) if "mass" in desc else None
        backbone_radius = (
            _number(desc, "backbone_radius", where, problems) if "backbone_radius" in desc else 0.0
        )
        angles_raw = desc.get("tendon_angles")
        if not isinstance(angles_raw, list | tuple) or not angles_raw:
            problems.append(f"{where}: tendon_angles must be a non-empty list, got {angles_raw!r}")
            angles: list[float] = []
        else:
            angles = [
                _number({"a": a}, "a", f"{where} tendon_angles", problems) for a in angles_raw
            ]
        model_type = desc.get("model", "pcc")
        if not isinstance(model_type, str) or not model_type:
            problems.append(f"{where}: model must be a model type name, got {model_type!r}")
            model_type = "pcc"
        driver = desc.get("servo_driver", "pwm")
        if not isinstance(driver, str) or not driver:
            problems.append(f"{where}: servo_driver must be a name, got {driver!r}")
            driver = "pwm"
        models.append(model_type)
        uid = desc.get("uid")
        if isinstance(uid, str) and uid.strip():
            uids[seg] = uid.strip().lower()

        tip = f"{seg}_tip"
        robot.links[tip] = Link(name=tip)
        spec = ModelSpec(
            type=model_type,
            limits=CurvatureLimits(kappa_max=kappa_max, kappa_rate_max=rate),
            backbone=Backbone(length=length, radius=backbone_radius),
        )
        inertial = None
        if mass is not None:
            inertial = _inertial(mass, length, max(tendon_radius, backbone_radius))
        robot.bendables[seg] = Bendable(
            name=seg,
            parent=parent,
            child=tip,
            model=spec,
            inertial=inertial,
            actuation=Actuation(
                type="tendon",
                angles=angles,
                radius=tendon_radius,
                spool_radius=spool_radius,
                driver=driver,
            ),
        )
        control.joints.append(
            ControlJoint(
                name=seg,
                command_interfaces=[
                    Interface("kappa", {"initial_value": 0.0, "min": 0.0, "max": kappa_max}),
                    Interface("phi", {"initial_value": 0.0, "min": -math.pi, "max": math.pi}),
                ],
                state_interfaces=[Interface("kappa"), Interface("phi")],
            )
        )
        parent = tip
    if problems:
        raise UcrdfError(Diagnostic(source, 0, p) for p in problems)
    if len(set(models)) == 1:
        control.hardware_params = {"model": models[0], **control.hardware_params}
    # pin each segment's identity: the daemon refuses a chain whose uids differ
    for seg, uid in uids.items():
        control.hardware_params[f"{seg}/uid"] = uid
    robot.ros2_control.append(control)
    diagnostics = check(robot)
    if diagnostics:
        raise UcrdfError(diagnostics)
    return robot


def write_robot_from_descriptors(
    descriptors: Sequence[Mapping[str, Any]], path: str | Path, name: str = "robot"
) -> Robot:
    """Compose (see :func:`robot_from_descriptors`), write the U(C)RDF file, return the Robot."""
    robot = robot_from_descriptors(descriptors, name)
    dump(robot, path)
    robot.source = str(path)
    return robot
