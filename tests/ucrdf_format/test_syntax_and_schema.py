"""Malformed XML and schema violations become ``path:line: message`` diagnostics; unknown URDF
extension elements are tolerated while the continuum elements are strict."""

from __future__ import annotations

import pytest

from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string

from .conftest import VALID, diagnostics_of, edit, line_of


def test_malformed_xml_reports_path_and_line():
    text = edit('  <link name="tip"/>\n', '  <link name="tip"/> & broken\n')
    (diag,) = diagnostics_of(text, source="robots/bad.ucrdf")
    assert diag.line == line_of(text, "& broken")
    assert str(diag).startswith(f"robots/bad.ucrdf:{diag.line}: XML syntax error:")


def test_unclosed_tag_as_printed_in_the_paper_is_a_syntax_error():
    # Listing 1 prints <parent link="base"> without "/>": not well-formed XML.
    text = edit('<parent link="arm"/>', '<parent link="arm">')
    (diag,) = diagnostics_of(text)
    assert diag.message.startswith("XML syntax error: Opening and ending tag mismatch: parent")
    assert diag.line == line_of(text, "</bendable>")


def test_empty_document():
    (diag,) = diagnostics_of("")
    assert "XML syntax error" in diag.message or "empty" in diag.message


def test_root_must_be_robot():
    (diag,) = diagnostics_of('<?xml version="1.0"?>\n<link name="a"/>\n')
    assert diag.line == 2 and "expected <robot>" in diag.message


def test_missing_required_attribute_is_a_schema_error_with_line():
    text = edit('<joint name="j1" type="revolute">', '<joint name="j1">')
    (diag,) = diagnostics_of(text)
    assert diag.line == line_of(text, '<joint name="j1">')
    assert "attribute 'type' is required" in diag.message


def test_unknown_element_inside_bendable_is_rejected():
    text = edit("    <curvature>", "    <wobble/>\n    <curvature>")
    diags = diagnostics_of(text)
    assert diags[0].line == line_of(text, "<wobble/>")
    assert "wobble" in diags[0].message


def test_non_numeric_limit_is_rejected_with_line():
    text = edit('kappa_max="3.0"', 'kappa_max="lots"')
    (diag,) = diagnostics_of(text)
    assert diag.line == line_of(text, "<limits") and "kappa_max" in diag.message


def test_origin_needs_three_numbers():
    text = edit('    <axis xyz="0 0 1"/>', '    <origin xyz="0 0"/>\n    <axis xyz="0 0 1"/>')
    diags = diagnostics_of(text)
    assert {d.line for d in diags} == {line_of(text, '<origin xyz="0 0"/>')}
    assert "has a length of '2'" in diags[0].message


def test_every_schema_error_is_reported():
    text = edit('<joint name="j1" type="revolute">', '<joint name="j1">')
    text = edit('<tendon index="1" angle="2.0943951023931953"/>', '<tendon index="1"/>', text)
    lines = [d.line for d in diagnostics_of(text)]
    assert lines == [line_of(text, '<joint name="j1">'), line_of(text, '<tendon index="1"/>')]


def test_unknown_extension_elements_and_xacro_attributes_are_tolerated_and_kept():
    text = edit('<robot name="t">', '<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="t">')
    text = edit(
        "  <ros2_control",
        '  <gazebo reference="arm"><mu1>0.2</mu1></gazebo>\n'
        '  <transmission name="tr"><joint name="j1"><hardwareInterface>x</hardwareInterface>'
        "</joint></transmission>\n"
        "  <my_vendor_tag answer='42'/>\n"
        "  <ros2_control",
        text,
    )
    text = edit(
        '<link name="tip"/>', '<link name="tip" xacro:note="x"><vendor:stuff xmlns:vendor="urn:v"/>'
        "</link>", text
    )  # fmt: skip
    robot = parse_string(text)
    assert len(robot.extensions) == 3
    assert robot.extensions[0] == '<gazebo reference="arm"><mu1>0.2</mu1></gazebo>'
    assert robot.links["tip"].extensions == ['<vendor:stuff xmlns:vendor="urn:v"></vendor:stuff>']


def test_xacro_elements_are_refused_each_at_its_line():
    """<xacro:…> elements mean the file was not expanded (docs/ucrdf.md): an error, not kept."""
    text = edit('<robot name="t">', '<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="t">')
    text = edit(
        "  <ros2_control", '  <xacro:property name="l" value="0.3"/>\n  <ros2_control', text
    )
    text = edit('<link name="tip"/>', '<link name="tip"><xacro:stuff/></link>', text)
    diags = diagnostics_of(text)
    assert [d.line for d in diags] == [line_of(text, "xacro:stuff"), line_of(text, "xacro:prop")]
    assert all("unexpanded xacro" in d.message for d in diags)


def test_comments_are_ignored():
    text = edit("    <curvature>", "    <!-- a note -->\n    <curvature>")
    assert parse_string(text).bendables["seg"].model.type == "pcc"


def test_missing_file_is_one_diagnostic(tmp_path):
    with pytest.raises(UcrdfError) as info:
        load(tmp_path / "absent.ucrdf")
    (diag,) = info.value.diagnostics
    assert str(diag) == f"{tmp_path / 'absent.ucrdf'}: cannot read file: No such file or directory"


def test_valid_document_still_parses():
    assert parse_string(VALID).name == "t"
