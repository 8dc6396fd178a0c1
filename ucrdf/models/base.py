"""The kinematic model plugin interface (paper REQ 3).

A model turns a bendable's configuration (a dict of named variables, SI units) into the transform
from the segment base frame to its tip frame. Models are registered by name (``<model type="…">``)
in ``ucrdf.models`` and through the entry-point group ``ucrdf.models``; a third-party package adds a
model by subclassing :class:`CurvatureModel` and declaring
``[project.entry-points."ucrdf.models"] mymodel = "mypkg.module:MyModel"``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ucrdf.model import ModelSpec


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


class CurvatureModel(ABC):
    """Base class of every kinematic model. One instance per bendable, built from its ``<model>``.

    Subclasses set ``type_name`` and implement the abstract methods; everything takes and returns
    SI units. Batched methods accept arrays with a leading batch dimension.
    """

    type_name: str = ""

    def __init__(self, spec: ModelSpec):
        self.spec = spec
        self.length = spec.backbone.length
        self.validate()

    # -- description -------------------------------------------------------------------------
    @classmethod
    @abstractmethod
    def variables(cls) -> list[Variable]:
        """The configuration variables, in order; their names are the interface names."""

    def validate(self) -> None:  # noqa: B027 - optional hook
        """Raise ModelError if ``self.spec`` is not usable (e.g. kappa_max*l beyond the model)."""

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

    # -- kinematics ----------------------------------------------------------------------------
    @abstractmethod
    def transform(self, config: dict[str, float], s: float | None = None) -> np.ndarray:
        """4x4 transform from base to the point at arc length ``s`` (default: the tip)."""

    @abstractmethod
    def jacobian(self, config: dict[str, float]) -> np.ndarray:
        """3xk Jacobian of the tip position w.r.t. the model's Cartesian-style coordinates
        (for PCC: (kx, ky)), used by IK."""

    def backbone_curve(self, config: dict[str, float], samples: int = 20) -> np.ndarray:
        """(samples, 3) points along the backbone, base to tip, for drawing."""
        return np.array(
            [self.transform(config, s)[:3, 3] for s in np.linspace(0.0, self.length, samples)]
        )
