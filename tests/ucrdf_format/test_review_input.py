"""Regression tests of a review of what the parser reads: whole numbers of any length, DTDs and
entity references, lengths that overflow, number text only Python reads, and text handed to
``parse_string`` with an encoding declaration. Each is a ``path:line: message`` diagnostic (or
the right result), never a traceback or a silently changed value."""

from __future__ import annotations

import pytest

from ucrdf.errors import UcrdfError
from ucrdf.parser import parse_bytes, parse_string
from ucrdf.writer import dumps

from .conftest import diagnostics_of, edit, line_of

HUGE = "1" + "0" * 5000  # int() refuses more than 4300 digits with a ValueError


def only(text: str) -> tuple[int, str]:
    """(line, message) of the one diagnostic ``text`` produces."""
    diags = diagnostics_of(text)
    assert len(diags) == 1, [str(d)[:300] for d in diags]
    return diags[0].line, diags[0].message


# -- 1: whole numbers longer than int() reads -----------------------------------------------------
SERVO = '<servo index="1" id="2"/>'
PULSE = '<pwm_pulse min_us="500"'


@pytest.mark.parametrize(
    "old,new,element",
    [
        ('count="3"', f'count="{HUGE}"', "<actuation count="),
        ('<tendon index="1"', f'<tendon index="{HUGE}"', "<tendon index="),
        (SERVO, f'<servo index="{HUGE}" id="2"/>', "<servo index="),
        (SERVO, f'<servo index="1" id="{HUGE}"/>', "<servo id="),
        (SERVO, f'<servo index="1" id="2" direction="-{HUGE}"/>', "<servo direction="),
        (PULSE, f'<pwm index="0" pin="{HUGE}"/>\n      {PULSE}', "<pwm pin="),
        (PULSE, f'<uart role="upstream" id="{HUGE}" tx="1" rx="3"/>\n {PULSE}', "<uart id="),
        (PULSE, f'<uart role="upstream" id="0" tx="1" rx="3" baud="{HUGE}"/>\n {PULSE}', "baud="),
    ],
)
def test_a_whole_number_of_thousands_of_digits_is_a_diagnostic_at_its_line(old, new, element):
    text = edit(old, new)
    diags = diagnostics_of(text)
    assert all(len(d.message) < 250 for d in diags)  # the value is named, not echoed
    (diag,) = [d for d in diags if "is out of range: a whole number" in d.message]
    assert diag.line == line_of(text, HUGE) and element in diag.message
    assert "at most 18 digits" in diag.message and "characters)" in diag.message
    if element != "<tendon index=":  # (a tendon left out is also one missing: as for index=7)
        assert len(diags) == 1, [str(d) for d in diags]


def test_a_long_value_in_a_schema_message_is_cut():
    text = edit('kappa_max="3.0"', f'kappa_max="{HUGE}x"')
    line, message = only(text)
    assert line == line_of(text, HUGE) and "(5002 characters)" in message and len(message) < 300


def test_a_short_bad_value_keeps_the_whole_schema_message():
    """The cut of long values took the text *between* two quoted values for one ("… '0.3m' is
    not a valid value of'… (41 characters)xs:double'"): every bad number's message was garbled."""
    text = edit('kappa_max="3.0"', 'kappa_max="3.0m"')
    _, message = only(text)
    assert message.endswith("'3.0m' is not a valid value of the atomic type 'xs:double'"), message


# -- 3: DTDs and entity references ----------------------------------------------------------------
DECLARATION = '<?xml version="1.0"?>'


@pytest.mark.parametrize(
    "doctype,named",
    [
        ('<!DOCTYPE robot SYSTEM "robot.dtd">', "'robot.dtd'"),
        ('<!DOCTYPE robot PUBLIC "-//x//robot" "http://x/robot.dtd">', "'-//x//robot'"),
    ],
)
def test_an_external_dtd_and_the_entities_it_would_define_are_refused(doctype, named):
    text = edit(DECLARATION, f"{DECLARATION}\n{doctype}")
    text = edit('<link name="tip"/>', '<link name="tip&vendor;"/>', text)
    text = edit("<plugin>SoftRobotInterface</plugin>", "<plugin>Soft&suffix;</plugin>", text)
    diags = diagnostics_of(text)
    assert [d.line for d in diags] == [
        line_of(text, "<!DOCTYPE"),
        line_of(text, "&vendor;"),
        line_of(text, "&suffix;"),
    ]
    assert f"external DTD {named}" in diags[0].message and "never read" in diags[0].message
    assert "entity 'vendor' is not defined" in diags[1].message
    assert "entity 'suffix' is not defined" in diags[2].message  # was an XSD "internal error"


def test_attribute_list_declarations_are_refused_not_ignored():
    text = edit(
        DECLARATION,
        f"{DECLARATION}\n<!DOCTYPE robot [\n  <!-- <!ATTLIST in a comment> -->\n"
        '  <!ATTLIST servo direction CDATA "-1">\n]>',
    )
    line, message = only(text)
    assert line == line_of(text, "<!ATTLIST servo")
    assert "<!ATTLIST servo …> is not supported" in message and "never applied" in message


def test_a_bare_doctype_naming_the_root_is_still_accepted():
    assert parse_string(edit(DECLARATION, f"{DECLARATION}\n<!DOCTYPE robot>")).name == "t"


def test_an_entity_declared_in_a_utf16_file_is_refused_at_its_line():
    text = edit(DECLARATION, '<?xml version="1.0" encoding="UTF-16"?>\n<!DOCTYPE robot [\n'
                '<!ENTITY e "x">\n]>')  # fmt: skip
    with pytest.raises(UcrdfError) as info:
        parse_bytes(text.encode("utf-16"))
    (diag,) = info.value.diagnostics
    assert diag.line == line_of(text, "<!ENTITY e") and "entity 'e'" in diag.message


# -- 4: lengths and axes that overflow ------------------------------------------------------------
@pytest.mark.parametrize(
    "old,new,what",
    [
        ('<axis xyz="0 0 1"/>', '<origin xyz="1e308 0 0"/>\n    <axis xyz="0 0 1"/>', "origin xyz"),
        ('<backbone length="0.3"', '<backbone length="2e6"', "backbone length"),
        ('radius="0.002"', 'radius="1e300"', "backbone radius"),
        ('spool_radius="0.02"', 'spool_radius="1e7"', "spool radius"),
    ],
)
def test_a_length_beyond_a_thousand_km_is_refused(old, new, what):
    text = edit(old, new)
    _, message = only(text)
    assert f"{what} " in message and "is beyond ±1e+06 m" in message


def test_a_length_of_a_thousand_km_passes():
    parse_string(edit('<axis xyz="0 0 1"/>', '<origin xyz="1e6 0 -1e6"/>\n    <axis xyz="0 0 1"/>'))


@pytest.mark.parametrize(
    "axis,fragment",
    [
        ("1e308 1e308 0", "is too long to normalise (its squared length overflows)"),
        ("NaN 0 1", "axis (nan 0 1) is not finite"),
        ("0 0 0", "has no direction (zero length)"),
    ],
)  # fmt: skip
def test_axis_messages_say_what_is_wrong(axis, fragment):
    text = edit('<axis xyz="0 0 1"/>', f'<axis xyz="{axis}"/>')
    line, message = only(text)
    assert line == line_of(text, "<axis") and fragment in message
    if "too long" in message:
        assert message.endswith("write the unit vector (0.707107 0.707107 0)")


def test_a_huge_axis_that_normalises_passes():
    parse_string(edit('<axis xyz="0 0 1"/>', '<axis xyz="0 0 1e150"/>'))


# -- 6: parse_string with an encoding declaration -------------------------------------------------
@pytest.mark.parametrize("encoding", ["ISO-8859-1", "UTF-16", "latin-1"])
def test_parse_string_reads_text_whatever_encoding_it_declares(encoding):
    robot = parse_string(
        f'<?xml version="1.0" encoding="{encoding}"?><robot name="rö"><link name="bö"/></robot>'
    )
    assert robot.name == "rö" and list(robot.links) == ["bö"]


def test_parse_string_refuses_a_lone_surrogate_with_a_diagnostic():
    (diag,) = diagnostics_of('<robot name="\ud800"><link name="b"/></robot>')
    assert diag.line == 1 and "XML syntax error" in diag.message


# -- 7: number text only Python reads -------------------------------------------------------------
@pytest.mark.parametrize("value", ["1_5", "١٥", "infinity"])
def test_an_interface_bound_python_would_read_is_refused(value):
    text = edit('<param name="max">3.0</param>', f'<param name="max">{value}</param>')
    line, message = only(text)
    assert line == line_of(text, '<command_interface name="kappa">')
    assert f"param max must be a finite number, got {value!r}" in message


@pytest.mark.parametrize("value", ["921_600", "９２１６００"])
def test_a_baudrate_python_would_read_is_refused(value):
    text = edit('<param name="model">pcc</param>', f'<param name="baudrate">{value}</param>')
    _, message = only(text)
    assert f"baudrate must be a whole number of bit/s >= 1200, got {value!r}" in message


def test_a_watchdog_with_an_underscore_is_refused():
    text = edit('<param name="model">pcc</param>', '<param name="watchdog_ms">2_00</param>')
    _, message = only(text)
    assert "watchdog_ms must be a number of ms, got '2_00'" in message


def test_a_model_limit_with_an_underscore_is_not_a_number():
    text = edit('kappa_rate_max="5.0"', 'kappa_rate_max="5.0" kappa_slope_max="1_5"')
    assert any("<limits kappa_slope_max='1_5'> is not a number" in d.message
               for d in diagnostics_of(text))  # fmt: skip


def test_numbers_in_the_schema_spelling_still_read():
    text = edit('<param name="max">3.0</param>', '<param name="max"> +.3E1 </param>')
    robot = parse_string(text)
    kappa = robot.ros2_control[0].joints[0].command_interfaces[0]
    assert kappa.params["max"] == 3.0


def test_a_pass_through_interface_param_keeps_its_text():
    code = '<param name="code">007</param>'
    text = edit('<param name="max">3.0</param>', f'<param name="max">3.0</param>\n{code}')
    robot = parse_string(text)
    kappa = robot.ros2_control[0].joints[0].command_interfaces[0]
    assert kappa.params == {"min": 0.0, "max": 3.0, "code": "007"}
    assert code in dumps(robot)
