"""What the view draws, computed from a U(C)RDF robot and a configuration (no web dependency).

Each bendable becomes a tube along its true backbone curve, sampled from its model plugin through
:meth:`ucrdf.fk.RobotKinematics.backbone_frames_coordinates` (PCC arcs, PPC curves: whatever the
plugin computes); tendons are polylines offset from the backbone frames at their angle and radius;
rigid links carry the primitives and meshes of their ``<visual>`` elements.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lxml import etree

from protocol.constants import DEFAULT_KAPPA_RATE_MAX
from ucrdf.fk import RobotKinematics
from ucrdf.model import Origin, Robot

#: Points sampled along each backbone (base to tip) and sides of the tube around it.
SAMPLES = 24
SIDES = 12


@dataclass
class Visual:
    """One ``<visual>`` of a rigid link: ``kind`` box|cylinder|sphere|mesh, sizes in m."""

    link: str
    kind: str
    origin: np.ndarray  # 4x4 in the link frame
    size: tuple[float, ...] = ()  # box (x, y, z); cylinder (radius, length); sphere (radius,)
    mesh: str = ""  # resolved file path for meshes
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    color: tuple[int, int, int] = (170, 170, 180)
    color_given: bool = False  # a <material><color> overrides a mesh file's own colours
    problem: str = ""  # why it cannot be drawn (e.g. package:// mesh without a path)


@dataclass
class Frame:
    """Everything drawn for one configuration (root frame, m)."""

    links: dict[str, np.ndarray]  # link -> 4x4
    backbones: dict[str, np.ndarray]  # bendable -> (SAMPLES, 4, 4)
    tubes: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # verts, faces
    tendons: dict[str, list[np.ndarray]] = field(default_factory=dict)  # bendable -> [(n, 3)]
    tip: np.ndarray = field(default_factory=lambda: np.zeros(3))


def tube_faces(samples: int, sides: int) -> np.ndarray:
    """Triangles of a tube with ``samples`` rings of ``sides`` vertices (constant for a size)."""
    faces = []
    for i in range(samples - 1):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            c, d = a + sides, b + sides
            faces += [(a, c, b), (b, c, d)]
    return np.asarray(faces, dtype=np.uint32)


def tube_vertices(frames: np.ndarray, radius: float, sides: int = SIDES) -> np.ndarray:
    """Rings of ``sides`` points of ``radius`` (m) around each backbone frame's z axis."""
    ang = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1) * radius  # (sides, 2)
    x, y, p = frames[:, :3, 0], frames[:, :3, 1], frames[:, :3, 3]
    pts = p[:, None, :] + ring[None, :, 0:1] * x[:, None, :] + ring[None, :, 1:2] * y[:, None, :]
    return pts.reshape(-1, 3).astype(np.float32)


def tendon_paths(frames: np.ndarray, angles: list[float], radius: float) -> list[np.ndarray]:
    """Tendon i at angle sigma_i and distance ``radius`` from the backbone in every frame."""
    x, y, p = frames[:, :3, 0], frames[:, :3, 1], frames[:, :3, 3]
    return [p + radius * (math.cos(s) * x + math.sin(s) * y) for s in angles]


def _floats(text: str | None, n: int, default: float = 0.0) -> tuple[float, ...]:
    vals = [float(v) for v in (text or "").split()] if text else []
    if len(vals) != n:
        vals = [default] * n if not vals else (vals + [default] * n)[:n]
    return tuple(vals)


def parse_visuals(robot: Robot, base_dir: Path | None = None) -> list[Visual]:
    """The drawable ``<visual>`` elements of every rigid link (meshes resolved from the file)."""
    out: list[Visual] = []
    materials = named_materials(robot)
    for link in robot.links.values():
        for geom in link.geometry:
            if geom.kind != "visual":
                continue
            el = etree.fromstring(geom.xml)
            o = el.find("origin")
            origin = Origin(
                xyz=_floats(o.get("xyz") if o is not None else None, 3),
                rpy=_floats(o.get("rpy") if o is not None else None, 3),
            ).matrix()
            g = el.find("geometry")
            shape = g[0] if g is not None and len(g) else None
            if shape is None:
                continue
            vis = Visual(link.name, shape.tag, origin)
            rgba = el.find("material/color")
            colour = rgba.get("rgba") if rgba is not None else None
            mat = el.find("material")
            if not colour and mat is not None and mat.get("name") in materials:
                colour = materials[mat.get("name")]  # a robot-level <material name> (URDF)
            if colour:
                r, gg, b, _a = _floats(colour, 4, 1.0)
                vis.color = (round(r * 255), round(gg * 255), round(b * 255))
                vis.color_given = True
            if shape.tag == "box":
                vis.size = _floats(shape.get("size"), 3, 0.01)
            elif shape.tag == "cylinder":
                vis.size = (float(shape.get("radius", 0.01)), float(shape.get("length", 0.01)))
            elif shape.tag == "sphere":
                vis.size = (float(shape.get("radius", 0.01)),)
            elif shape.tag == "mesh":
                vis.scale = _floats(shape.get("scale"), 3, 1.0)  # type: ignore[assignment]
                name = shape.get("filename", "")
                path = _resolve_mesh(name, base_dir)
                if path is None:
                    vis.problem = f"mesh {name!r} not found"
                else:
                    vis.mesh = str(path)
            else:
                vis.problem = f"unknown geometry {shape.tag!r}"
            out.append(vis)
    return out


def named_materials(robot: Robot) -> dict[str, str]:
    """The robot-level ``<material name><color rgba/></material>`` elements (URDF: a visual's
    ``<material name="grey"/>`` refers to them): name -> rgba text."""
    out: dict[str, str] = {}
    for ext in getattr(robot, "extensions", None) or []:
        if not isinstance(ext, str) or not ext.lstrip().startswith("<material"):
            continue
        try:
            el = etree.fromstring(ext)
        except etree.XMLSyntaxError:
            continue
        c = el.find("color")
        if el.get("name") and c is not None and c.get("rgba"):
            out[el.get("name")] = c.get("rgba")
    return out


def _resolve_mesh(name: str, base_dir: Path | None) -> Path | None:
    if name.startswith("file://"):
        name = name[len("file://") :]
    elif name.startswith("package://"):
        # no ROS package index here: try the path below the robot file's directory
        name = name[len("package://") :].split("/", 1)[-1]
    p = Path(name)
    if not p.is_absolute() and base_dir is not None:
        p = base_dir / p
    return p if p.is_file() else None


class SceneModel:
    """One robot's kinematics plus the constant parts of its drawing (faces, tendon layout)."""

    def __init__(self, robot: Robot, samples: int = SAMPLES, sides: int = SIDES):
        self.robot = robot
        self.kin = RobotKinematics(robot)
        self.samples, self.sides = samples, sides
        self.faces = tube_faces(samples, sides)
        self.bendables = list(self.kin.models)
        self.radius: dict[str, float] = {}
        self.tendons: dict[str, tuple[list[float], float]] = {}
        for name in self.bendables:
            b = robot.bendables[name]
            act = b.actuation
            r_tendon = act.radius if act is not None and act.radius > 0 else 0.0
            # tube radius: just inside the tendon circle (the tendons show on its surface), else
            # 3 % of the length
            self.radius[name] = 0.85 * r_tendon if r_tendon else 0.03 * b.length
            if act is not None and act.type == "tendon" and act.angles and act.radius > 0:
                self.tendons[name] = (list(act.angles), act.radius)
        self.tip_link = self._tip_link()
        base = Path(robot.source).parent if getattr(robot, "source", "") else None
        self.visuals = parse_visuals(robot, base)

    def _tip_link(self) -> str:
        parents = {el.parent for el in self.kin.order}
        leaves = [el.child for el in self.kin.order if el.child not in parents]
        return leaves[-1] if leaves else self.kin.root

    def limits(self, name: str) -> tuple[float, float]:
        """(kappa_max 1/m, kappa_rate_max 1/m/s) of a bendable; an undeclared rate is the one the
        host plans with and the segments slew at (protocol.constants.DEFAULT_KAPPA_RATE_MAX)."""
        lim = self.robot.bendables[name].model.limits
        return float(lim.kappa_max), float(lim.kappa_rate_max or DEFAULT_KAPPA_RATE_MAX)

    def coordinates(self, state: Mapping[str, Mapping[str, float]]) -> dict[str, np.ndarray]:
        """Model coordinates per bendable from ``{name: {"kappa", "phi"}}`` (missing: defaults).

        Out-of-limit values are drawn as measured (a view must show the truth, not clamp it)."""
        bend, _ = self.kin.resolve(
            {n: dict(v) for n, v in state.items() if n in self.kin.models}, strict=False
        )
        return {n: self.kin.models[n].to_coordinates(c) for n, c in bend.items()}

    def frame(self, state: Mapping[str, Mapping[str, float]]) -> Frame:
        """Links, backbones, tubes, tendons and tip for a configuration."""
        coords = self.coordinates(state)
        _, joints = self.kin.resolve({}, strict=False)
        links = self.kin.fk_coordinates(coords, joints)
        backbones = self.kin.backbone_frames_coordinates(coords, joints, self.samples, links)
        out = Frame(links, backbones, tip=links[self.tip_link][:3, 3].copy())
        for name, frames in backbones.items():
            out.tubes[name] = (tube_vertices(frames, self.radius[name], self.sides), self.faces)
            if name in self.tendons:
                angles, r = self.tendons[name]
                out.tendons[name] = tendon_paths(frames, angles, r)
        return out
