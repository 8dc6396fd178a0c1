"""The kinematic model plugin interface (paper REQ 3).

A model turns a bendable's configuration (a dict of named variables, SI units) into the transform
from the segment base frame to its tip frame. Models are registered by name (``<model type="…">``)
in ``ucrdf.models`` and through the entry-point group ``ucrdf.models``; a third-party package adds a
model by subclassing :class:`CurvatureModel` and declaring
``[project.entry-points."ucrdf.models"] mymodel = "mypkg.module:MyModel"``.

Two views of one configuration:

* the *interface form* (``variables()``): named values such as ``kappa`` and ``phi`` — what the
  ``<ros2_control>`` interfaces, the CLI and the daemon exchange;
* the *coordinate form* (``coordinate_names()``): a flat float vector in which the model is smooth
  and free of singular parametrisations, e.g. PCC's curvature vector (kx, ky). IK, interpolation and
  Jacobians work in coordinates. By default the coordinates are the variables themselves.

A minimal plugin implements ``variables()`` and ``transform()``; Jacobians then come from central
finite differences. Models with analytic derivatives override ``coordinate_jacobians()``.
"""

from __future__ import annotations

import math
import numbers
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ucrdf.model import ModelSpec

#: Relative slack accepted when checking a value against its bound (float round-off from
#: conversions such as (kx, ky) -> (kappa, phi) must not turn into a limit violation).
LIMIT_SLACK = 1e-9

#: Largest total bend kappa_max*l a constant- or affine-curvature segment may declare (rad): up to
#: a half circle, (kx, ky)*l is the principal rotation vector (see docs/kinematics.md).
THETA_MAX = math.pi


@dataclass(frozen=True)
class Variable:
    """One configuration variable of a model: name as used by interfaces ("kappa", "phi"), unit
    text for docs and UIs, default, and bounds (None = unbounded or taken from ``<limits>``)."""

    name: str
    unit: str
    default: float = 0.0
    lower: float | None = None
    upper: float | None = None


class ModelError(ValueError):
    """A model's parameters or configuration are invalid (message says which and why)."""


def wrap_angle(phi: float) -> float:
    """Angle wrapped into (-pi, pi] (rad)."""
    w = math.remainder(phi, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


def kappa_phi(
    kx: float, ky: float, previous: Mapping[str, float] | None = None
) -> dict[str, float]:
    """Curvature vector (1/m) -> {"kappa", "phi"}; at kappa = 0 phi keeps ``previous["phi"]``
    (else 0), so a path through straight never spins the bending plane."""
    kappa = math.hypot(kx, ky)
    if kappa == 0.0:
        phi = wrap_angle(float(previous.get("phi", 0.0))) if previous else 0.0
    else:
        phi = wrap_angle(math.atan2(ky, kx))
    return {"kappa": kappa, "phi": phi}


def skew_to_vector(m: np.ndarray) -> np.ndarray:
    """The vector w of a (nearly) skew-symmetric 3x3 matrix [w]x (its skew part is used)."""
    return 0.5 * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])


class CurvatureModel(ABC):
    """Base class of every kinematic model. One instance per bendable, built from its ``<model>``.

    Subclasses set ``type_name`` and implement ``variables()`` and ``transform()``; everything
    takes and returns SI units. The constructor calls ``validate()`` so an unusable ``<model>``
    fails early with a :class:`ModelError`.
    """

    type_name: str = ""
    #: Step (in coordinate units) of the default finite-difference Jacobian.
    fd_step: float = 1e-6
    #: Model-specific ``<limits>`` attributes the model reads (besides kappa_max, kappa_rate_max,
    #: phi_min, phi_max); any other attribute is refused, so a misspelt limit never silently
    #: becomes its default.
    extra_limits: tuple[str, ...] = ()

    def __init__(self, spec: ModelSpec):
        self.spec = spec
        self.length = spec.backbone.length
        if not (self.length > 0.0 and math.isfinite(self.length)):
            raise ModelError(f"backbone length must be a positive number (m), got {self.length}")
        unknown = sorted(set(spec.limits.extra) - set(self.extra_limits))
        if unknown:
            known = ", ".join(self.extra_limits) or "none"
            raise ModelError(
                f"unknown <limits> attribute(s) {', '.join(unknown)} for model "
                f"{self.type_name!r} (model-specific limits it reads: {known})"
            )
        self.validate()

    # -- description -------------------------------------------------------------------------
    @classmethod
    @abstractmethod
    def variables(cls) -> list[Variable]:
        """The configuration variables, in order; their names are the interface names."""

    def validate(self) -> None:  # noqa: B027 - optional hook
        """Raise ModelError if ``self.spec`` is not usable (e.g. kappa_max*l beyond the model)."""

    def check_total_bend(self, label: str) -> None:
        """ModelError unless kappa_max is a finite number >= 0 with kappa_max*l <= THETA_MAX."""
        lim = self.spec.limits
        if not (math.isfinite(lim.kappa_max) and lim.kappa_max >= 0.0):
            raise ModelError(f"kappa_max must be a finite number >= 0 1/m, got {lim.kappa_max}")
        theta = lim.kappa_max * self.length
        if theta > THETA_MAX * (1.0 + LIMIT_SLACK):
            raise ModelError(
                f"kappa_max*length = {theta:.4g} rad ({math.degrees(theta):.1f} deg) exceeds the "
                f"{label} bound of pi rad (180 deg): kappa_max must be <= "
                f"{THETA_MAX / self.length:.4g} 1/m for this length"
            )

    def limits(self) -> dict[str, tuple[float, float]]:
        """Bounds of each variable from ``<limits>`` (name -> (lower, upper))."""
        lim = self.spec.limits
        out: dict[str, tuple[float, float]] = {}
        for v in self.variables():
            if v.name == "kappa":
                out[v.name] = (0.0, lim.kappa_max)
            elif v.name == "phi":
                out[v.name] = (lim.phi_min, lim.phi_max)
            elif v.lower is not None and v.upper is not None:
                out[v.name] = (v.lower, v.upper)
        return out

    def full_circle(self) -> bool:
        """True when ``<limits>`` allow every bending-plane angle (no phi restriction)."""
        lim = self.spec.limits
        return lim.phi_max - lim.phi_min >= 2.0 * math.pi - 1e-9

    def check_config(self, config: Mapping[str, float]) -> dict[str, float]:
        """The complete, checked configuration: unknown names and values outside ``limits()``
        raise ModelError; missing variables take their defaults; phi is wrapped to (-pi, pi]."""
        names = [v.name for v in self.variables()]
        unknown = sorted(set(config) - set(names))
        if unknown:
            raise ModelError(
                f"unknown variable(s) {', '.join(unknown)} for model {self.type_name!r} "
                f"(it has: {', '.join(names)})"
            )
        out: dict[str, float] = {}
        bounds = self.limits()
        for v in self.variables():
            raw = config.get(v.name, v.default)
            if isinstance(raw, (bool, str, bytes)) or not isinstance(raw, numbers.Real):
                # "1" or True are not numbers: refused as for rigid joints, never converted
                raise ModelError(f"{v.name} must be a number ({v.unit}), got {raw!r}")
            value = float(raw)
            if not math.isfinite(value):
                raise ModelError(f"{v.name} must be finite, got {value}")
            if v.name == "phi":
                value = wrap_angle(value)
                if self.full_circle():
                    out[v.name] = value
                    continue
            if v.name in bounds:
                lo, hi = bounds[v.name]
                slack = LIMIT_SLACK * max(1.0, abs(lo), abs(hi))
                if value < lo - slack or value > hi + slack:
                    raise ModelError(
                        f"{v.name} = {value:g} {v.unit} is outside its limits [{lo:g}, {hi:g}]"
                    )
                value = min(max(value, lo), hi)
            out[v.name] = value
        return out

    # -- coordinates -------------------------------------------------------------------------
    def coordinate_names(self) -> list[str]:
        """Names of the smooth coordinates IK and Jacobians use (default: the variables)."""
        return [v.name for v in self.variables()]

    def to_coordinates(self, config: Mapping[str, float]) -> np.ndarray:
        """Coordinate vector of a configuration (interface form, missing names -> defaults)."""
        return np.array([float(config.get(v.name, v.default)) for v in self.variables()])

    def from_coordinates(
        self, q: np.ndarray, previous: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        """Interface form of a coordinate vector. ``previous`` lets models hold values that are
        undefined at a singular point (PCC holds phi when kappa = 0)."""
        return {v.name: float(x) for v, x in zip(self.variables(), q, strict=True)}

    def project(self, q: np.ndarray) -> np.ndarray:
        """The nearest coordinate vector within the limits (used by IK after each step)."""
        out = np.array(q, dtype=float)
        bounds = self.limits()
        for i, name in enumerate(self.coordinate_names()):
            if name in bounds:
                lo, hi = bounds[name]
                out[i] = min(max(out[i], lo), hi)
        return out

    # -- kinematics ----------------------------------------------------------------------------
    @abstractmethod
    def transform(self, config: Mapping[str, float], s: float | None = None) -> np.ndarray:
        """4x4 transform from base to the point at arc length ``s`` (m, default: the tip)."""

    def transform_coordinates(self, q: np.ndarray, s: float | None = None) -> np.ndarray:
        """4x4 transform from base to arc length ``s`` for a coordinate vector."""
        return self.transform(self.from_coordinates(q), s)

    def coordinate_jacobians(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Jv, Jw), each 3xk: tip linear and angular velocity in the segment base frame per unit
        change of each coordinate. Default: central finite differences of transform_coordinates."""
        q = np.asarray(q, dtype=float)
        k = q.size
        jv = np.empty((3, k))
        jw = np.empty((3, k))
        t0 = self.transform_coordinates(q)
        for i in range(k):
            h = self.fd_step * max(1.0, abs(q[i]))
            dq = np.zeros(k)
            dq[i] = h
            tp = self.transform_coordinates(q + dq)
            tm = self.transform_coordinates(q - dq)
            jv[:, i] = (tp[:3, 3] - tm[:3, 3]) / (2.0 * h)
            jw[:, i] = skew_to_vector((tp[:3, :3] - tm[:3, :3]) / (2.0 * h) @ t0[:3, :3].T)
        return jv, jw

    def jacobian(self, config: Mapping[str, float]) -> np.ndarray:
        """3xk Jacobian of the tip position w.r.t. the model's coordinates (for PCC: (kx, ky)),
        used by IK."""
        return self.coordinate_jacobians(self.to_coordinates(config))[0]

    def backbone_curve(self, config: Mapping[str, float], samples: int = 20) -> np.ndarray:
        """(samples, 3) points along the backbone, base to tip, for drawing."""
        return np.array(
            [self.transform(config, s)[:3, 3] for s in np.linspace(0.0, self.length, samples)]
        )

    def backbone_frames(self, config: Mapping[str, float], samples: int = 20) -> np.ndarray:
        """(samples, 4, 4) frames along the backbone, base to tip (for drawing and export)."""
        return np.array([self.transform(config, s) for s in np.linspace(0.0, self.length, samples)])
