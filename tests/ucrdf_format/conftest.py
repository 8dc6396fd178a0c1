"""Shared helpers of the U(C)RDF format tests: the example robots and a small valid document that
each error test breaks in one place."""

from __future__ import annotations

from pathlib import Path

import pytest

from ucrdf.errors import Diagnostic, UcrdfError
from ucrdf.parser import parse_string

REPO = Path(__file__).resolve().parents[2]
ROBOTS = REPO / "robots"
EXAMPLES = sorted(ROBOTS.glob("*.ucrdf"))

# A valid robot: rigid joint base -> arm, bendable arm -> tip, ros2_control for both.
VALID = """<?xml version="1.0"?>
<robot name="t">
  <link name="base"/>
  <link name="arm"/>
  <link name="tip"/>
  <joint name="j1" type="revolute">
    <parent link="base"/>
    <child link="arm"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <bendable name="seg">
    <parent link="arm"/>
    <child link="tip"/>
    <curvature>
      <model type="pcc">
        <limits kappa_max="3.0" kappa_rate_max="5.0"/>
        <backbone length="0.3" radius="0.002"/>
      </model>
    </curvature>
    <actuation type="tendon" count="3" radius="0.05" spool_radius="0.02" driver="pwm">
      <tendon index="0" angle="0"/>
      <tendon index="1" angle="2.0943951023931953"/>
      <tendon index="2" angle="4.1887902047863905"/>
      <servo index="0" id="1"/>
      <servo index="1" id="2"/>
      <servo index="2" id="3"/>
      <pwm_pulse min_us="500" max_us="2500" range="6.283185307179586"/>
    </actuation>
  </bendable>
  <ros2_control name="hw" type="system">
    <hardware>
      <plugin>SoftRobotInterface</plugin>
      <param name="model">pcc</param>
    </hardware>
    <joint name="seg">
      <command_interface name="kappa">
        <param name="min">0</param>
        <param name="max">3.0</param>
      </command_interface>
      <command_interface name="phi"/>
      <state_interface name="kappa"/>
    </joint>
    <joint name="j1">
      <command_interface name="position"/>
    </joint>
  </ros2_control>
</robot>
"""


def line_of(text: str, needle: str, occurrence: int = 1) -> int:
    """1-based line of the ``occurrence``-th line containing ``needle``."""
    hits = [i for i, line in enumerate(text.splitlines(), start=1) if needle in line]
    assert len(hits) >= occurrence, f"{needle!r} not in document"
    return hits[occurrence - 1]


def edit(old: str, new: str, text: str = VALID) -> str:
    """``text`` with the single occurrence of ``old`` replaced (fails if ambiguous)."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times"
    return text.replace(old, new)


def diagnostics_of(text: str, source: str = "test.ucrdf") -> list[Diagnostic]:
    """The diagnostics a document produces (fails if it parses clean)."""
    with pytest.raises(UcrdfError) as info:
        parse_string(text, source=source)
    return info.value.diagnostics
