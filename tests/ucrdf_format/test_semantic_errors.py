"""Each semantic error kind is reported with a clear message at the line of the culprit, and all
errors of a file are reported together."""

from __future__ import annotations

import pytest

from ucrdf.parser import parse_string

from .conftest import VALID, diagnostics_of, edit, line_of

EXTRA_JOINT = """  <joint name="{name}" type="fixed">
    <parent link="{parent}"/>
    <child link="{child}"/>
  </joint>
  <bendable name="seg">"""

EXTRA_BENDABLE = """  <bendable name="{name}">
    <parent link="tip"/>
    <child link="tip2"/>
    <curvature><model type="pcc"><limits kappa_max="1"/><backbone length="0.1"/></model></curvature>
  </bendable>
  <ros2_control"""

INVERTED_STATE = (
    '<state_interface name="kappa"><param name="min">1</param><param name="max">0.5</param>'
    "</state_interface>"
)

# (id, old, new, expected message fragment, text on the expected line, occurrence of that text)
CASES = [
    (
        "unknown-parent-link",
        '<parent link="arm"/>',
        '<parent link="nowhere"/>',
        "bendable 'seg': parent link 'nowhere' is not defined (links: arm, base, tip)",
        '<parent link="nowhere"/>',
        1,
    ),
    (
        "unknown-child-link",
        '<child link="arm"/>',
        '<child link="elbow"/>',
        "joint 'j1': child link 'elbow' is not defined",
        '<child link="elbow"/>',
        1,
    ),
    (
        "duplicate-link",
        '  <link name="tip"/>\n',
        '  <link name="tip"/>\n  <link name="arm"/>\n',
        "duplicate link name 'arm' (first defined on line 4)",
        '<link name="arm"/>',
        2,
    ),
    (
        "duplicate-joint",
        '  <bendable name="seg">',
        EXTRA_JOINT.format(name="j1", parent="base", child="tip"),
        "duplicate name 'j1': this joint has the same name as the joint on line 6",
        '<joint name="j1" type="fixed">',
        1,
    ),
    (
        "duplicate-bendable",
        "  <ros2_control",
        EXTRA_BENDABLE.format(name="seg"),
        "duplicate name 'seg': this bendable has the same name as the bendable on line 12",
        '<bendable name="seg">',
        2,
    ),
    (
        "bendable-named-like-a-joint",
        "  <ros2_control",
        EXTRA_BENDABLE.format(name="j1"),
        "duplicate name 'j1': this bendable has the same name as the joint on line 6",
        '<bendable name="j1">',
        1,
    ),
    (
        "cycle",
        '  <bendable name="seg">',
        EXTRA_JOINT.format(name="back", parent="tip", child="base"),
        "kinematic cycle base -> arm -> tip -> base (through joint 'j1', bendable 'seg', joint",
        '<joint name="j1"',
        1,
    ),
    (
        "two-parents",
        '  <bendable name="seg">',
        EXTRA_JOINT.format(name="j2", parent="base", child="tip"),
        "link 'tip' has two parents: bendable 'seg' and joint 'j2'",
        '<child link="tip"/>',
        2,
    ),
    (
        "two-roots",
        '  <link name="tip"/>\n',
        '  <link name="tip"/>\n  <link name="orphan"/>\n',
        "robot has 2 root links (base, orphan)",
        '<link name="orphan"/>',
        1,
    ),
    (
        "control-joint-names-nothing",
        '<joint name="j1">',
        '<joint name="j9">',
        "ros2_control joint 'j9' names neither a bendable nor a joint (bendables: seg; joints: j1)",
        '<joint name="j9">',
        1,
    ),
    (
        "interface-not-a-model-variable",
        '<state_interface name="kappa"/>',
        '<state_interface name="curl"/>',
        "state_interface 'curl' is not a variable of model 'pcc' (variables: kappa, phi)",
        '<state_interface name="curl"/>',
        1,
    ),
    (
        "unknown-model-type",
        '<model type="pcc">',
        '<model type="spline9">',
        "unknown model type 'spline9' (available: pcc",
        '<model type="spline9">',
        1,
    ),
    (
        "kappa-max-not-positive",
        'kappa_max="3.0"',
        'kappa_max="0"',
        "bendable 'seg': kappa_max must be > 0 1/m, got 0.0",
        "<limits",
        1,
    ),
    (
        "kappa-max-times-length-beyond-model",
        '<backbone length="0.3"',
        '<backbone length="1.2"',
        "model 'pcc': kappa_max*length = 3.6 rad",
        "<limits",
        1,
    ),
    (
        "negative-length",
        '<backbone length="0.3"',
        '<backbone length="-0.3"',
        "bendable 'seg': backbone length must be > 0 m, got -0.3",
        "<backbone",
        1,
    ),
    (
        "zero-length",
        '<backbone length="0.3"',
        '<backbone length="0"',
        "backbone length must be > 0 m, got 0.0",
        "<backbone",
        1,
    ),
    (
        "interface-max-beyond-model-limit",
        '<param name="max">3.0</param>',
        '<param name="max">4.5</param>',
        "command_interface 'kappa': max 4.5 exceeds the model limits of 'kappa' [0, 3]",
        '<command_interface name="kappa">',
        1,
    ),
    (
        # host/limits.py refuses it ("must be > 0"): ucr check must too (review of issue 11)
        "kappa-command-max-zero",
        '<param name="max">3.0</param>',
        '<param name="max">0</param>',
        "command_interface 'kappa': param max must be > 0 1/m, got 0",
        '<command_interface name="kappa">',
        1,
    ),
    (
        # below one wire unit (1e-4 1/m): the segment would run it as 0
        "kappa-command-max-below-resolution",
        '<param name="max">3.0</param>',
        '<param name="max">4e-05</param>',
        "command_interface 'kappa': param max 4e-05 1/m rounds to 0",
        '<command_interface name="kappa">',
        1,
    ),
    (
        "kappa-max-below-resolution",
        'kappa_max="3.0"',
        'kappa_max="4e-05"',
        "kappa_max 4e-05 1/m rounds to 0 in the segment's fixed point",
        "<limits",
        1,
    ),
    (
        "kappa-rate-max-below-resolution",
        'kappa_rate_max="5.0"',
        'kappa_rate_max="4e-05"',
        "kappa_rate_max 4e-05 1/m/s rounds to 0 in the segment's fixed point",
        "<limits",
        1,
    ),
    (
        "interface-min-above-max",
        '<param name="min">0</param>',
        '<param name="min">2.5</param><param name="initial_value">0</param>',
        "command_interface 'kappa': initial_value 0.0 lies outside [2.5, 3]",
        '<command_interface name="kappa">',
        1,
    ),
    (
        "interface-min-greater-than-max",
        '<state_interface name="kappa"/>',
        INVERTED_STATE,
        "state_interface 'kappa': min 1.0 > max 0.5",
        '<state_interface name="kappa">',
        1,
    ),
    (
        "tendon-count-attribute-mismatch",
        'count="3"',
        'count="4"',
        "declares count=4 but has 3 <tendon> elements",
        "<actuation",
        1,
    ),
    (
        "tendon-servo-count-mismatch",
        '      <servo index="2" id="3"/>\n',
        "",
        "actuation: 3 tendons but 2 servos (give one servo per tendon, or none)",
        "<actuation",
        1,
    ),
    (
        "servo-direction-not-unit",
        '<servo index="1" id="2"/>',
        '<servo index="1" id="2" direction="2"/>',
        "servo 1 direction must be 1 or -1, got 2",
        '<servo index="1"',
        1,
    ),
    (
        "servo-duplicate-bus-id",
        '<servo index="1" id="2"/>',
        '<servo index="1" id="1"/>',
        "servo 1 has the same bus id 1 as servo 0",
        '<servo index="1"',
        1,
    ),
    (
        "servo-travel-too-small",
        '<servo index="0" id="1"/>',
        '<servo index="0" id="1" min_angle="-1" max_angle="1"/>',
        "servo 0 travel [-1, 1] rad cannot reach kappa_max: the spool must turn ±2.25 rad",
        '<servo index="0"',
        1,
    ),
    (
        "tendon-radius-times-kappa-reaches-one",
        'radius="0.05" spool_radius="0.02"',
        'radius="0.5" spool_radius="1.0"',
        "the inner tendon would reach zero length before the bend limit",
        "<actuation",
        1,
    ),
    (
        "tendons-at-the-same-angle",
        '<tendon index="2" angle="4.1887902047863905"/>',
        '<tendon index="2" angle="6.283185307179586"/>',
        "tendon 2 sits at the same angle as tendon 0",
        '<tendon index="2"',
        1,
    ),
    (
        "revolute-without-limit",
        '    <limit lower="-1" upper="1" effort="1" velocity="1"/>\n',
        "",
        "joint 'j1': a revolute joint needs <limit lower upper effort velocity>",
        '<joint name="j1"',
        1,
    ),
    (
        "rigid-position-interface-beyond-limit",
        '<command_interface name="position"/>',
        '<command_interface name="position"><param name="max">2</param></command_interface>',
        "max 2.0 exceeds the <limit> of joint 'j1' [-1, 1]",
        '<command_interface name="position">',
        1,
    ),
    (
        "phi-range-inverted",
        'kappa_rate_max="5.0"',
        'kappa_rate_max="5.0" phi_min="1" phi_max="0"',
        "phi_min 1.0 must be < phi_max 0.0",
        "<limits",
        1,
    ),
    (
        "unknown-hardware-model",
        '<param name="model">pcc</param>',
        '<param name="model">banana</param>',
        "hardware param model='banana' is not a known model",
        '<param name="model">',
        1,
    ),
    (
        "hardware-param-for-unknown-bendable",
        '<param name="model">pcc</param>',
        '<param name="model">pcc</param>\n      <param name="sag/uid">a4cf</param>',
        "hardware param 'sag/uid' names 'sag', which is neither a bendable nor a joint",
        '<param name="sag/uid">',
        1,
    ),
    (
        "negative-mass",
        '  <link name="arm"/>',
        '  <link name="arm">\n    <inertial><mass value="-2"/></inertial>\n  </link>',
        "link 'arm': mass must be a finite value >= 0 kg, got -2.0",
        "<inertial>",
        1,
    ),
    (
        "non-finite-inertia",
        '  <link name="arm"/>',
        '  <link name="arm">\n  <inertial><inertia ixx="INF"/><mass value="1"/></inertial></link>',
        "link 'arm': <inertial> has a non-finite origin or inertia value",
        "<inertial>",
        1,
    ),
    (
        "model-without-backbone",
        '        <backbone length="0.3" radius="0.002"/>\n',
        "",
        "bendable 'seg': <model> has no <backbone> (required)",
        '<model type="pcc">',
        1,
    ),
    (
        "model-with-two-limits",
        '<limits kappa_max="3.0" kappa_rate_max="5.0"/>',
        '<limits kappa_max="3.0" kappa_rate_max="5.0"/>\n<limits kappa_max="2"/>',
        "bendable 'seg': <model> has more than one <limits>",
        '<limits kappa_max="2"/>',
        1,
    ),
    (
        "duplicate-interface",
        '<state_interface name="kappa"/>',
        '<state_interface name="kappa"/><state_interface name="kappa"/>',
        "ros2_control joint 'seg' has two <state_interface name='kappa'>",
        '<state_interface name="kappa"/>',
        1,
    ),
]


def test_the_base_document_is_valid():
    robot = parse_string(VALID)
    assert list(robot.bendables) == ["seg"] and list(robot.joints) == ["j1"]


@pytest.mark.parametrize(
    ("old", "new", "message", "marker", "occurrence"),
    [c[1:] for c in CASES],
    ids=[c[0] for c in CASES],
)
def test_error_is_reported_with_message_and_line(old, new, message, marker, occurrence):
    text = edit(old, new)
    diagnostics = diagnostics_of(text)
    expected_line = line_of(text, marker, occurrence)
    matching = [d for d in diagnostics if message in d.message]
    assert matching, f"no diagnostic contains {message!r}; got:\n" + "\n".join(
        map(str, diagnostics)
    )
    assert matching[0].line == expected_line, str(matching[0])
    assert str(matching[0]).startswith(f"test.ucrdf:{expected_line}: ")


def test_all_semantic_errors_are_collected_not_just_the_first():
    text = edit('<parent link="arm"/>', '<parent link="nowhere"/>')
    text = edit('<backbone length="0.3"', '<backbone length="-1"', text)
    text = edit('<joint name="j1">', '<joint name="j9">', text)
    diagnostics = diagnostics_of(text)
    lines = {d.line for d in diagnostics}
    assert {
        line_of(text, '<parent link="nowhere"/>'),
        line_of(text, "<backbone"),
        line_of(text, '<joint name="j9">'),
    } <= lines
    assert [d.line for d in diagnostics] == sorted(d.line for d in diagnostics)


def test_an_unknown_model_type_is_reported_once():
    # it was named again by the hardware model param check ("model='pcc' but ... use 'spline9'")
    diagnostics = diagnostics_of(edit('<model type="pcc">', '<model type="spline9">'))
    assert [d.message for d in diagnostics if "spline9" in d.message] == [
        d.message for d in diagnostics
    ]
    assert len(diagnostics) == 1, "\n".join(map(str, diagnostics))


PPC = edit(
    '<model type="pcc">\n        <limits kappa_max="3.0" kappa_rate_max="5.0"/>',
    '<model type="ppc">\n        <param name="steps" value="32"/>\n'
    '        <limits kappa_max="3.0" kappa_rate_max="5.0" kappa_slope_max="4.0"/>',
).replace('<param name="model">pcc</param>', '<param name="model">ppc</param>')


def test_model_params_extra_limits_and_extra_variables_reach_the_plugin():
    text = edit(
        '<state_interface name="kappa"/>',
        '<state_interface name="kappa"/><command_interface name="kappa_x_slope"/>',
        PPC,
    )
    robot = parse_string(text)
    spec = robot.bendables["seg"].model
    assert spec.params == {"steps": 32.0} and spec.limits.extra == {"kappa_slope_max": 4.0}


def test_a_parameter_the_model_rejects_is_reported_at_its_line():
    text = edit(
        '<param name="steps" value="32"/>',
        '<param name="steps" value="32"/>\n        <param name="wobble" value="1"/>',
        PPC,
    )
    diagnostics = diagnostics_of(text)
    (diag,) = [d for d in diagnostics if "wobble" in d.message]
    assert diag.line == line_of(text, '<param name="wobble"')
    assert diag.message.startswith("bendable 'seg': model 'ppc': ")
