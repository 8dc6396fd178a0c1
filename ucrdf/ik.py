"""Inverse kinematics of a multi-segment robot by damped least squares (Levenberg-Marquardt).

Unknowns are the coordinates of every bendable on the path from the root to the tip link (PCC:
the curvature vector (kx, ky), never (kappa, phi), so crossing "straight" is smooth) plus the
positions of movable rigid joints on that path (a mimic joint's unknown is its master's position).
Each step solves (J J^T + lambda I) y = e, dq = J^T y, then projects q back into the effective
limits (ucrdf/limits.py: the model's, narrowed by the ``<ros2_control>`` command interface bounds
the daemon enforces; PCC: the disc |k| <= kappa_max; a master joint also within what its mimic
joints' limits allow). lambda adapts:
smaller after a step that lowers the error, larger after one that does not. When a start point
stalls, the solver restarts from further seeds (deterministic pseudo-random points in the limits).
It never returns a bad answer silently: ``success`` is False with the best residual and a message.

The chain is evaluated in plain Python floats (a 3-segment chain is a few hundred multiplications;
numpy's per-call overhead would dominate), with PCC in closed form and its analytic Jacobian.
Other models go through their numpy ``transform_coordinates``/``coordinate_jacobians``.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ucrdf.fk import Config, ConfigError, RobotKinematics
from ucrdf.model import Robot
from ucrdf.models.base import ModelError
from ucrdf.models.pcc import _A, _B, _C, _DA, _DB, SERIES_T, PCCModel, project_disc

#: A start point is abandoned when this many iterations have not halved its error.
STALL_ITERATIONS = 30
#: A start point is also abandoned after this many accepted steps in a row that each lower the
#: squared error by less than FLAT_DECREASE of itself: a local minimum (often on a kappa limit)
#: the error no longer leaves; a slow valley still gains a few per cent per step.
FLAT_STEPS = 3
FLAT_DECREASE = 1e-3
#: After all start points, the best one continues for this many times max_iter (no stall rule).
POLISH_FACTOR = 4

_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)


@dataclass
class IKResult:
    """Outcome of :func:`solve_ik`.

    success: both residuals within tolerance. config: complete configuration (bendable ->
    {"kappa", "phi"} or the model's variables; movable joint -> position; mimic joints follow
    their masters and are not part of it) of the best solution found. residual: tip position
    error (m). rotation_residual: tip orientation error (rad), None without an orientation
    target. iterations: total over all restarts."""

    success: bool
    config: dict[str, dict[str, float] | float]
    residual: float
    iterations: int
    message: str
    rotation_residual: float | None = None
    tip: str = ""
    restarts: int = 0
    coordinates: dict[str, list[float]] = field(default_factory=dict)


# -- small pure-Python rigid-body helpers: a transform is a 12-tuple (R row-major, p) -------------
def _tuple(t: np.ndarray) -> tuple[float, ...]:
    r = t[:3, :3].ravel().tolist()
    return (*r, float(t[0, 3]), float(t[1, 3]), float(t[2, 3]))


def _mul(a: Sequence[float], b: Sequence[float]) -> tuple[float, ...]:
    a0, a1, a2, a3, a4, a5, a6, a7, a8, ax, ay, az = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8, bx, by, bz = b
    return (
        a0 * b0 + a1 * b3 + a2 * b6,
        a0 * b1 + a1 * b4 + a2 * b7,
        a0 * b2 + a1 * b5 + a2 * b8,
        a3 * b0 + a4 * b3 + a5 * b6,
        a3 * b1 + a4 * b4 + a5 * b7,
        a3 * b2 + a4 * b5 + a5 * b8,
        a6 * b0 + a7 * b3 + a8 * b6,
        a6 * b1 + a7 * b4 + a8 * b7,
        a6 * b2 + a7 * b5 + a8 * b8,
        a0 * bx + a1 * by + a2 * bz + ax,
        a3 * bx + a4 * by + a5 * bz + ay,
        a6 * bx + a7 * by + a8 * bz + az,
    )


def _poly(t: float, c: tuple[float, ...]) -> float:
    out = c[-1]
    for x in c[-2::-1]:
        out = out * t + x
    return out


def _pcc_local(kx: float, ky: float, ln: float):
    """PCC tip transform (12-tuple) and its Jacobians as two 3x2 lists (columns kx, ky)."""
    l2 = ln * ln
    l3 = l2 * ln
    wx, wy = -ky * ln, kx * ln
    t = wx * wx + wy * wy
    if t < SERIES_T:
        a, b, c, da, db = (_poly(t, _A), _poly(t, _B), _poly(t, _C), _poly(t, _DA), _poly(t, _DB))
    else:
        th = math.sqrt(t)
        s, co = math.sin(th), math.cos(th)
        one_c = 2.0 * math.sin(0.5 * th) ** 2
        a = s / th
        b = one_c / t
        c = (th - s) / (t * th)
        da = (th * co - s) / (2.0 * t * th)
        db = (th * s - 2.0 * one_c) / (2.0 * t * t)
    bwx, bwy = b * wx, b * wy
    tr = (
        1.0 - bwy * wy, bwx * wy, a * wy,
        bwx * wy, 1.0 - bwx * wx, -a * wx,
        -a * wy, a * wx, 1.0 - b * t,
        bwy * ln, -bwx * ln, a * ln,
    )  # fmt: skip
    l4db2 = 2.0 * l2 * l2 * db
    jv = (
        (l2 * b + kx * kx * l4db2, kx * ky * l4db2, 2.0 * kx * l3 * da),
        (kx * ky * l4db2, l2 * b + ky * ky * l4db2, 2.0 * ky * l3 * da),
    )
    jw = (
        (-c * kx * ky * l3, ln - c * ky * ky * l3, -b * ky * l2),
        (-ln + c * kx * kx * l3, c * kx * ky * l3, b * kx * l2),
    )
    return tr, jv, jw


def _rot_vec(r: Sequence[float]) -> tuple[float, float, float]:
    """Rotation vector (axis * angle, rad) of a row-major 3x3 rotation."""
    vx, vy, vz = 0.5 * (r[7] - r[5]), 0.5 * (r[2] - r[6]), 0.5 * (r[3] - r[1])
    sn = math.sqrt(vx * vx + vy * vy + vz * vz)
    cs = 0.5 * (r[0] + r[4] + r[8] - 1.0)
    if sn < 1e-12:
        if cs > 0.0:
            return vx, vy, vz
        # angle pi: axis from the largest diagonal entry of (R + I) / 2
        d = [0.5 * (r[0] + 1.0), 0.5 * (r[4] + 1.0), 0.5 * (r[8] + 1.0)]
        i = d.index(max(d))
        ax = [0.5 * (r[3 * i + j] + r[3 * j + i]) if j != i else d[i] for j in range(3)]
        n = math.sqrt(sum(x * x for x in ax)) or 1.0
        return tuple(math.pi * x / n for x in ax)  # type: ignore[return-value]
    ang = math.atan2(sn, cs)
    f = ang / sn
    return vx * f, vy * f, vz * f


def _solve_spd(m: list[list[float]], e: list[float]) -> list[float]:
    """Solve m y = e for a small symmetric positive definite m (Cholesky, in place)."""
    n = len(e)
    low = [[0.0] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            s = m[i][j] - sum(low[i][k] * low[j][k] for k in range(j))
            if i == j:
                if s <= 0.0:
                    raise ZeroDivisionError
                low[i][i] = math.sqrt(s)
            else:
                low[i][j] = s / low[j][j]
    y = [0.0] * n
    for i in range(n):
        y[i] = (e[i] - sum(low[i][k] * y[k] for k in range(i))) / low[i][i]
    for i in range(n - 1, -1, -1):
        y[i] = (y[i] - sum(low[k][i] * y[k] for k in range(i + 1, n))) / low[i][i]
    return y


class _Chain:
    """The root -> tip path compiled into constant transforms and variable elements."""

    def __init__(self, kin: RobotKinematics, tip: str):
        path = []
        link = tip
        while link != kin.root:
            el = kin.by_child.get(link)
            if el is None:
                raise ConfigError(f"tip link {tip!r} is not in the robot")
            path.append(el)
            link = el.parent
        path.reverse()
        self.ops: list[tuple] = []  # ("const", T) | ("pcc", name, l, i, model) | ...
        self.names: list[tuple[str, str, int, int]] = []  # (kind, name, start, size)
        #: unknown index of each joint -> its (lower, upper), narrowed by every mimic joint that
        #: follows it on the path (a mimic joint's unknown is its master's position)
        self.bounds: dict[int, tuple[float, float]] = {}
        const = _IDENTITY
        self.size = 0
        for el in path:
            const = _mul(const, _tuple(el.origin))
            if el.kind == "joint" and el.joint_type not in ("revolute", "continuous", "prismatic"):
                continue
            if const != _IDENTITY:
                self.ops.append(("const", const))
            const = _IDENTITY
            if el.kind == "bendable":
                model = el.model
                kind = "pcc" if type(model) is PCCModel else "model"
                self.ops.append((kind, el.name, model.length, self.size, model,
                                 model.full_circle()))  # fmt: skip
                self.names.append((kind, el.name, self.size, len(model.coordinate_names())))
                self.size += len(model.coordinate_names())
                continue
            kind = "pri" if el.joint_type == "prismatic" else "rev"
            mimic = kin.mimics.get(el.name)
            i = self._joint_index(kin, el.name if mimic is None else mimic.joint)
            scale, offset = (1.0, 0.0) if mimic is None else (mimic.multiplier, mimic.offset)
            if mimic is not None:  # its own limits bound the master's position
                if scale != 0.0:
                    a, b = sorted(((el.lower - offset) / scale, (el.upper - offset) / scale))
                else:  # a constant position: within its limits, or no master position will do
                    a, b = (-math.inf, math.inf) if el.lower <= offset <= el.upper else (1.0, 0.0)
                lo, hi = self.bounds[i]
                self.bounds[i] = (max(lo, a), min(hi, b))
                if self.bounds[i][0] > self.bounds[i][1]:
                    raise ConfigError(
                        f"the limits of mimic joint {el.name!r} leave no position of "
                        f"{mimic.joint!r} within its own limits"
                    )
            self.ops.append((kind, el.name, tuple(el.axis.tolist()), i, scale, offset))
        if const != _IDENTITY:
            self.ops.append(("const", const))

    def _joint_index(self, kin: RobotKinematics, name: str) -> int:
        """The unknown of joint ``name`` (added at the end when new, with its limits)."""
        for kind, known, start, _size in self.names:
            if known == name and kind in ("rev", "pri"):
                return start
        el = kin.elements[name]
        kind = "pri" if el.joint_type == "prismatic" else "rev"
        self.names.append((kind, name, self.size, 1))
        self.bounds[self.size] = (el.lower, el.upper)
        self.size += 1
        return self.size - 1

    def evaluate(self, q: list[float], want_rot: bool, rot_weight: float = 1.0):
        """Tip transform and the Jacobian rows (3, or 6 with the angular rows scaled by
        ``rot_weight`` m/rad, each a list of length size)."""
        tw = _IDENTITY
        cols: list[tuple] = []  # (index, Rb*jv, Rb*jw, p_end, scale) per coordinate
        for op in self.ops:
            kind = op[0]
            if kind == "const":
                tw = _mul(tw, op[1])
                continue
            i = op[3]
            r0, r1, r2, r3, r4, r5, r6, r7, r8 = tw[:9]
            if kind == "pcc":
                local, jv, jw = _pcc_local(q[i], q[i + 1], op[2])
                tw = _mul(tw, local)
                for j, (v, w) in enumerate(zip(jv, jw, strict=True)):
                    cols.append(
                        (
                            i + j,
                            (
                                r0 * v[0] + r1 * v[1] + r2 * v[2],
                                r3 * v[0] + r4 * v[1] + r5 * v[2],
                                r6 * v[0] + r7 * v[1] + r8 * v[2],
                            ),
                            (
                                r0 * w[0] + r1 * w[1] + r2 * w[2],
                                r3 * w[0] + r4 * w[1] + r5 * w[2],
                                r6 * w[0] + r7 * w[1] + r8 * w[2],
                            ),
                            tw,
                            1.0,
                        )
                    )
            elif kind in ("rev", "pri"):
                ax, ay, az = op[2]
                wa = (r0 * ax + r1 * ay + r2 * az, r3 * ax + r4 * ay + r5 * az,
                      r6 * ax + r7 * ay + r8 * az)  # fmt: skip
                scale = op[4]
                d = scale * q[i] + op[5]  # the joint's position (a mimic joint's from its master)
                if kind == "rev":
                    rot = _axis_rot(op[2], d)
                    tw = _mul(tw, (*rot, 0.0, 0.0, 0.0))
                    cols.append((i, (0.0, 0.0, 0.0), wa, tw, scale))
                else:
                    tw = _mul(tw, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, ax * d, ay * d,
                                   az * d))  # fmt: skip
                    cols.append((i, wa, (0.0, 0.0, 0.0), None, scale))
            else:  # generic model through its numpy interface
                model = op[4]
                k = len(model.coordinate_names())
                qq = np.array(q[i : i + k])
                local = _tuple(model.transform_coordinates(qq))
                jv, jw = model.coordinate_jacobians(qq)
                rb = np.array(tw[:9]).reshape(3, 3)
                tw = _mul(tw, local)
                jvw, jww = rb @ jv, rb @ jw
                for j in range(k):
                    cols.append((i + j, tuple(jvw[:, j]), tuple(jww[:, j]), tw, 1.0))
        px, py, pz = tw[9], tw[10], tw[11]
        rows = [[0.0] * self.size for _ in range(6 if want_rot else 3)]
        for i, v, w, te, scale in cols:  # a joint and its mimic joints add up in one column
            if te is None:
                lin = v
            else:
                dx, dy, dz = px - te[9], py - te[10], pz - te[11]
                lin = (
                    v[0] + w[1] * dz - w[2] * dy,
                    v[1] + w[2] * dx - w[0] * dz,
                    v[2] + w[0] * dy - w[1] * dx,
                )
            rows[0][i] += scale * lin[0]
            rows[1][i] += scale * lin[1]
            rows[2][i] += scale * lin[2]
            if want_rot:
                rows[3][i] += scale * rot_weight * w[0]
                rows[4][i] += scale * rot_weight * w[1]
                rows[5][i] += scale * rot_weight * w[2]
        return tw, rows

    def active(self, q: list[float], dq: list[float]) -> list[tuple[int, float, float | None]]:
        """Limits that are active at q and violated by the step dq: (index, tangent x, tangent y)
        for a PCC disc (tangent of the kappa_max circle), (index, 0, None) for a joint bound."""
        out: list[tuple[int, float, float | None]] = []
        for op in self.ops:
            kind = op[0]
            if kind == "pcc":
                i = op[3]
                kx, ky = q[i], q[i + 1]
                k = math.hypot(kx, ky)
                kmax = op[4].spec.limits.kappa_max
                if k > 0.0 and k >= kmax * (1.0 - 1e-9) and kx * dq[i] + ky * dq[i + 1] > 0.0:
                    out.append((i, -ky / k, kx / k))
        for i, (lo, hi) in self.bounds.items():
            if (q[i] <= lo and dq[i] < 0.0) or (q[i] >= hi and dq[i] > 0.0):
                out.append((i, 0.0, None))
        return out

    def project(self, q: list[float]) -> list[float]:
        for op in self.ops:
            kind = op[0]
            if kind == "const":
                continue
            i = op[3]
            if kind == "pcc":
                model = op[4]
                q[i], q[i + 1] = project_disc(q[i], q[i + 1], model.spec.limits, op[5])
            elif kind == "model":
                model = op[4]
                k = len(model.coordinate_names())
                q[i : i + k] = model.project(np.array(q[i : i + k])).tolist()
        for i, (lo, hi) in self.bounds.items():
            q[i] = min(max(q[i], lo), hi)
        return q


def _axis_rot(axis: Sequence[float], angle: float) -> tuple[float, ...]:
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    return (
        c + x * x * v, x * y * v - z * s, x * z * v + y * s,
        y * x * v + z * s, c + y * y * v, y * z * v - x * s,
        z * x * v - y * s, z * y * v + x * s, c + z * z * v,
    )  # fmt: skip


def default_tip(kin: RobotKinematics) -> str:
    """The one leaf link of the tree; ConfigError if there are several (pass ``tip``)."""
    parents = {el.parent for el in kin.order}
    leaves = [el.child for el in kin.order if el.child not in parents]
    if len(leaves) != 1:
        raise ConfigError(
            f"robot has {len(leaves)} end links ({', '.join(leaves) or '-'}); choose one as tip"
        )
    return leaves[0]


class IKSolver:
    """Reusable solver for one robot and tip link (precomputes the chain)."""

    def __init__(
        self, robot: Robot | RobotKinematics, tip: str | None = None, *, rot_weight: float = 0.1
    ):
        self.kin = robot if isinstance(robot, RobotKinematics) else RobotKinematics(robot)
        self.tip = tip if tip is not None else default_tip(self.kin)
        if self.tip not in self.kin.robot.links:
            raise ConfigError(
                f"tip link {self.tip!r} is not in the robot (links: "
                f"{', '.join(self.kin.robot.links)})"
            )
        if self.tip == self.kin.root:
            raise ConfigError(f"tip link {self.tip!r} is the root link: nothing to solve")
        self.chain = _Chain(self.kin, self.tip)
        if self.chain.size == 0:
            raise ConfigError(f"no bendable or movable joint between the root and {self.tip!r}")
        self._has_joints = any(kind in ("rev", "pri") for kind, *_ in self.chain.names)
        #: m per rad: orientation errors are scaled by this to be comparable with positions
        self.rot_weight = rot_weight

    def _seeds(self, first: list[float], count: int, rng: random.Random):
        yield list(first)
        for i in range(count):
            # every second seed keeps the segments nearly straight (scale 0.1): with rigid joints on
            # the path this finds targets at full stretch, where bent starts crawl along a valley
            scale = 0.1 if (i % 2 and self._has_joints) else 1.0
            q = []
            for kind, name, start, _size in self.chain.names:
                if kind == "pcc":
                    kmax = self.kin.models[name].spec.limits.kappa_max * scale
                    r = kmax * math.sqrt(rng.random())
                    a = rng.uniform(-math.pi, math.pi)
                    q += [r * math.cos(a), r * math.sin(a)]
                elif kind == "model":
                    model = self.kin.models[name]
                    lims = model.limits()
                    base = model.to_coordinates(
                        {v: rng.uniform(*lims[v]) for v in lims if math.isfinite(lims[v][1])}
                    )
                    q += model.project(base).tolist()
                else:
                    lo, hi = self.chain.bounds[start]
                    lo = lo if math.isfinite(lo) else min(-math.pi, hi - 2 * math.pi)
                    hi = hi if math.isfinite(hi) else max(math.pi, lo + 2 * math.pi)
                    q.append(rng.uniform(lo, hi))
            yield self.chain.project(q)

    def solve(
        self,
        target_xyz: Sequence[float],
        *,
        target_rot: np.ndarray | None = None,
        initial: Config | None = None,
        tol: float = 1e-4,
        rot_tol: float = 1e-3,
        max_iter: int = 150,
        restarts: int = 12,
        seed: int = 0,
    ) -> IKResult:
        """Solve for the tip at ``target_xyz`` (m, root frame) and optionally orientation
        ``target_rot`` (3x3, root frame). See module docstring."""
        target = _check_target(target_xyz)
        rt = None
        if target_rot is not None:
            rt = _check_rotation(target_rot)
        if not (tol > 0.0 and rot_tol > 0.0 and max_iter >= 1 and restarts >= 0):
            raise ConfigError("tol and rot_tol must be > 0, max_iter >= 1, restarts >= 0")
        bend, joints = self.kin.resolve(initial, strict=False)
        coords = {n: self.kin.models[n].to_coordinates(c) for n, c in bend.items()}
        q0: list[float] = []
        for kind, name, _start, _size in self.chain.names:
            q0 += coords[name].tolist() if kind in ("pcc", "model") else [joints[name]]
        rng = random.Random(seed)
        want_rot = rt is not None
        w = self.rot_weight
        best = (math.inf, q0, math.inf, None)
        total = 0
        tries = 0
        for q in self._seeds(self.chain.project(list(q0)), restarts, rng):
            tries += 1
            q, cost, perr, rerr, it = self._descend(q, target, rt, want_rot, w, tol, rot_tol,
                                                    max_iter)  # fmt: skip
            total += it
            if cost < best[0]:
                best = (cost, q, perr, rerr)
            if perr <= tol and (not want_rot or rerr <= rot_tol):
                break
        if not (best[2] <= tol and (not want_rot or best[3] <= rot_tol)):
            # polish: the best start point gets a long run without the stall rule (targets at a
            # singular boundary, e.g. an arm at full stretch, converge steadily but slowly)
            budget = POLISH_FACTOR * max_iter
            q, cost, perr, rerr, it = self._descend(
                list(best[1]), target, rt, want_rot, w, tol, rot_tol, budget, stall=None
            )
            total += it
            if cost < best[0]:
                best = (cost, q, perr, rerr)
        _cost, q, perr, rerr = best
        success = perr <= tol and (not want_rot or rerr <= rot_tol)
        config: dict[str, dict[str, float] | float] = {n: dict(c) for n, c in bend.items()}
        config.update((n, v) for n, v in joints.items() if n not in self.kin.mimics)
        out_coords = {n: c.tolist() for n, c in coords.items()}
        beyond = ""
        for kind, name, start, size in self.chain.names:
            if kind in ("pcc", "model"):
                qq = np.array(q[start : start + size])
                config[name] = self.kin.models[name].from_coordinates(qq, bend[name])
                out_coords[name] = qq.tolist()
                try:  # bounds the projection does not know (a plugin variable's interface)
                    self.kin.check_variable_bounds(name, config[name])
                except ModelError as exc:
                    success, beyond = False, f"bendable {name!r}: {exc}"
            else:
                config[name] = q[start]
        if beyond:
            msg = f"the best configuration found breaks a command interface bound: {beyond}"
        elif success:
            msg = f"converged after {total} iterations ({tries} start point(s))"
        else:
            msg = (
                f"no solution within tolerance after {tries} start point(s) and {total} "
                f"iterations: best position error {perr:.3g} m"
                + (f", orientation error {rerr:.3g} rad" if want_rot else "")
                + " (target may be outside the workspace or the limits)"
            )
        return IKResult(success, config, perr, total, msg, rerr if want_rot else None,
                        self.tip, tries - 1, out_coords)  # fmt: skip

    def _descend(self, q, target, rt, want_rot, w, tol, rot_tol, max_iter, stall=STALL_ITERATIONS):
        chain = self.chain
        gx, gy, gz = target

        def errors(tw):
            e = [gx - tw[9], gy - tw[10], gz - tw[11]]
            perr = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
            rerr = 0.0
            if want_rot:
                rc = tw[:9]
                # R_err = Rt Rc^T
                rerr_m = [
                    sum(rt[3 * i + k] * rc[3 * j + k] for k in range(3))
                    for i in range(3)
                    for j in range(3)
                ]
                ev = _rot_vec(rerr_m)
                rerr = math.sqrt(ev[0] ** 2 + ev[1] ** 2 + ev[2] ** 2)
                e += [w * ev[0], w * ev[1], w * ev[2]]
            return e, perr, rerr

        tw, rows = chain.evaluate(q, want_rot, w)
        e, perr, rerr = errors(tw)
        cost = sum(x * x for x in e)
        mu = 1e-3
        nu = 2.0  # growth of mu after a rejected step; doubles while steps keep failing
        flat = 0  # accepted steps in a row that hardly lowered the error
        it = 0
        ref_cost, ref_it = cost, 0
        while it < max_iter:
            if perr <= tol and (not want_rot or rerr <= rot_tol):
                break
            it += 1
            dq = _dls_step(rows, e, mu, chain.size)
            if dq is None:
                mu *= 10.0
                continue
            active = chain.active(q, dq)
            held: list[tuple[int, float, float | None]] = []
            while active:
                # limits active and the step pushes outwards: solve again in the remaining
                # directions (tangent of the kappa_max circle, or nothing for a joint at its
                # bound); a limit the new step pushes against joins them (several segments at
                # kappa_max at once would otherwise zigzag between them, one per iteration)
                held += active
                dq2 = _restricted_step(rows, e, mu, chain.size, held)
                if dq2 is None:
                    break
                dq = dq2
                # a limit joins once: a step along a held kappa_max circle's tangent can still
                # point outwards by a rounding error (k . t ~ 1e-16), which looped here forever
                active = [a for a in chain.active(q, dq) if a[0] not in {h[0] for h in held}]
            qn = chain.project([a + b for a, b in zip(q, dq, strict=True)])
            twn, rowsn = chain.evaluate(qn, want_rot, w)
            en, perrn, rerrn = errors(twn)
            costn = sum(x * x for x in en)
            if costn < cost:
                # gain ratio: actual over predicted (linear model) decrease; a step the model
                # predicts well lets the damping fall fast, a poor one keeps it (Nielsen 1999)
                pred = _predicted_decrease(rows, e, [a - b for a, b in zip(qn, q, strict=True)])
                rho = (cost - costn) / pred if pred > 0.0 else 0.0
                flat = flat + 1 if cost - costn < FLAT_DECREASE * cost else 0
                q, tw, rows, e, perr, rerr, cost = qn, twn, rowsn, en, perrn, rerrn, costn
                mu = max(mu * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-9)
                nu = 2.0
                if (
                    stall is not None
                    and flat >= FLAT_STEPS
                    and not (perr <= tol and (not want_rot or rerr <= rot_tol))
                ):
                    break  # a local minimum: let the caller restart elsewhere
            else:
                mu *= nu
                nu *= 2.0
                if mu > 1e4:
                    break  # no descent direction left: stuck here
            if cost < 0.5 * ref_cost:
                ref_cost, ref_it = cost, it
            elif stall is not None and it - ref_it >= stall:
                break  # stalled: let the caller restart elsewhere
        return q, cost, perr, rerr, it


def _restricted_step(
    rows: list[list[float]],
    e: list[float],
    mu: float,
    n: int,
    held: list[tuple[int, float, float | None]],
) -> list[float] | None:
    """The damped step with the ``held`` limits kept: a PCC coordinate pair moves only along
    its tangent (tx, ty), a joint at its bound not at all. None if singular."""
    rows2 = [list(r) for r in rows]
    for i, tx, ty in held:
        for r in rows2:
            if ty is None:
                r[i] = 0.0
            else:
                r[i], r[i + 1] = r[i] * tx + r[i + 1] * ty, 0.0
    dq = _dls_step(rows2, e, mu, n)
    if dq is not None:
        for i, tx, ty in held:
            if ty is None:
                dq[i] = 0.0
            else:
                dq[i], dq[i + 1] = dq[i] * tx, dq[i] * ty
    return dq


def _predicted_decrease(rows: list[list[float]], e: list[float], dq: list[float]) -> float:
    """|e|^2 - |e - J dq|^2: the decrease of the squared error the linear model predicts."""
    out = 0.0
    for r, ei in zip(rows, e, strict=True):
        jd = sum(a * b for a, b in zip(r, dq, strict=True))
        out += 2.0 * ei * jd - jd * jd
    return out


def _dls_step(rows: list[list[float]], e: list[float], mu: float, n: int) -> list[float] | None:
    """dq = J^T (J J^T + lambda I)^-1 e with lambda = mu * mean(diag(J J^T)); None if singular."""
    m = len(rows)
    jjt = [[sum(a * b for a, b in zip(rows[i], rows[j], strict=True)) for j in range(m)]
           for i in range(m)]  # fmt: skip
    lam = mu * (sum(jjt[i][i] for i in range(m)) / m or 1.0)
    for i in range(m):
        jjt[i][i] += lam
    try:
        y = _solve_spd(jjt, e)
    except ZeroDivisionError:
        return None
    return [sum(rows[i][j] * y[i] for i in range(m)) for j in range(n)]


def _check_target(target_xyz: Sequence[float]) -> tuple[float, float, float]:
    try:
        t = tuple(float(x) for x in target_xyz)
    except (TypeError, ValueError):
        raise ConfigError(f"target must be three numbers x, y, z (m), got {target_xyz!r}") from None
    if len(t) != 3 or not all(math.isfinite(x) for x in t):
        raise ConfigError(f"target must be three finite numbers x, y, z (m), got {target_xyz!r}")
    return t  # type: ignore[return-value]


def _check_rotation(r: np.ndarray) -> tuple[float, ...]:
    arr = np.asarray(r, dtype=float)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
        raise ConfigError("target_rot must be a finite 3x3 rotation matrix")
    if np.abs(arr @ arr.T - np.eye(3)).max() > 1e-6 or np.linalg.det(arr) < 0.0:
        raise ConfigError("target_rot is not a rotation matrix (must be orthonormal, det +1)")
    return tuple(arr.ravel().tolist())


def solve_ik(
    robot: Robot | RobotKinematics,
    target_xyz: Sequence[float],
    *,
    tip: str | None = None,
    target_rot: np.ndarray | None = None,
    initial: Config | None = None,
    tol: float = 1e-4,
    rot_tol: float = 1e-3,
    max_iter: int = 150,
    restarts: int = 12,
) -> IKResult:
    """Configuration that puts link ``tip`` (default: the one end link) at ``target_xyz`` (m,
    root frame) and, if given, orientation ``target_rot``. For repeated calls on one robot build
    an :class:`IKSolver` once and call ``solve``."""
    solver = IKSolver(robot, tip)
    return solver.solve(
        target_xyz, target_rot=target_rot, initial=initial, tol=tol, rot_tol=rot_tol,
        max_iter=max_iter, restarts=restarts,
    )  # fmt: skip


__all__ = ["IKResult", "IKSolver", "default_tip", "solve_ik"]
