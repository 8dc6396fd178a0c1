"""Model registry: built-ins by name, third-party models through the ``ucrdf.models`` entry-point
group (without touching this repository), broken plugins isolated."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

import ucrdf.models as models
from ucrdf.fk import RobotKinematics
from ucrdf.ik import solve_ik
from ucrdf.models.base import CurvatureModel, ModelError
from ucrdf.models.pcc import PCCModel
from ucrdf.models.ppc import PPCModel

from .conftest import chain_robot, segment_spec

PLUGIN_SOURCE = textwrap.dedent(
    '''
    """A third-party model: a straight rod that only pitches at its base (one variable)."""
    import math
    import numpy as np
    from ucrdf.models.base import CurvatureModel, Variable


    class PitchRod(CurvatureModel):
        type_name = "pitchrod"

        @classmethod
        def variables(cls):
            return [Variable("pitch", "rad", 0.0, -1.0, 1.0)]

        def transform(self, config, s=None):
            s = self.length if s is None else s
            a = float(config.get("pitch", 0.0))
            t = np.eye(4)
            t[:3, :3] = [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]
            t[:3, 3] = t[:3, 2] * s
            return t
    '''
)


@pytest.fixture
def plugin_dist(tmp_path, monkeypatch):
    """An installed-looking distribution 'ucr-pitchrod' declaring two entry points: a working
    model and one whose module does not exist."""
    (tmp_path / "pitchrod_plugin.py").write_text(PLUGIN_SOURCE)
    dist = tmp_path / "ucr_pitchrod-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: ucr-pitchrod\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[ucrdf.models]\npitchrod = pitchrod_plugin:PitchRod\nbroken = no_such_module_x:Model\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    return tmp_path


def test_builtin_models_are_found_by_name():
    assert models.get_model("pcc") is PCCModel
    assert models.get_model("ppc") is PPCModel
    assert models.available()[:2] == ["pcc", "ppc"]


def test_unknown_model_error_lists_available_models():
    with pytest.raises(ModelError, match=r"unknown model type 'nope'.*pcc, ppc"):
        models.get_model("nope")


def test_create_builds_a_validated_instance():
    model = models.create(segment_spec())
    assert isinstance(model, PCCModel)
    with pytest.raises(ModelError, match="exceeds the PCC bound"):
        models.create(segment_spec(kappa_max=4 * math.pi))


def test_third_party_model_registers_through_entry_point(plugin_dist):
    assert "pitchrod" in models.available()
    cls = models.get_model("pitchrod")
    assert issubclass(cls, CurvatureModel) and cls.__name__ == "PitchRod"
    model = models.create(segment_spec(0.5, model="pitchrod"))
    t = model.transform({"pitch": 0.5})
    assert np.allclose(t[:3, 3], [0.5 * math.sin(0.5), 0.0, 0.5 * math.cos(0.5)])
    # the default finite-difference Jacobian works for a plugin that only gives transform()
    jv = model.jacobian({"pitch": 0.5})
    assert np.allclose(jv[:, 0], [0.5 * math.cos(0.5), 0.0, -0.5 * math.sin(0.5)], atol=1e-7)


def test_plugin_model_works_in_robot_fk_and_ik(plugin_dist):
    robot = chain_robot(2)
    robot.bendables["seg2"].model = segment_spec(0.3, model="pitchrod")
    kin = RobotKinematics(robot)
    cfg = {"seg1": {"kappa": 2.0, "phi": 0.4}, "seg2": {"pitch": 0.6}}
    target = kin.fk(cfg)["link2"][:3, 3]
    res = solve_ik(robot, target)
    assert res.success, res.message
    assert np.linalg.norm(kin.fk(res.config)["link2"][:3, 3] - target) <= 1e-4
    assert -1.0 <= res.config["seg2"]["pitch"] <= 1.0


def test_broken_plugin_fails_only_when_requested(plugin_dist):
    assert "broken" in models.available()  # listed without importing it
    assert models.get_model("pcc") is PCCModel  # the others still work
    assert models.get_model("pitchrod").__name__ == "PitchRod"
    with pytest.raises(ModelError, match=r"'broken' could not be loaded.*no_such_module_x"):
        models.get_model("broken")
