"""Whatever the input, the parser either returns a Robot or raises UcrdfError with located
diagnostics: no other exception (a user never sees a traceback)."""

from __future__ import annotations

import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ucrdf.errors import UcrdfError
from ucrdf.parser import parse_string

from .conftest import VALID, line_of

LINES = VALID.splitlines()
ATTRS = list(re.finditer(r'="([^"]*)"', VALID))
NASTY = st.sampled_from(
    [
        "",
        "-1",
        "0",
        "NaN",
        "INF",
        "-INF",
        "1e308",
        "abc",
        "0 0",
        "1 2 3 4",
        "seg",
        "base",
        "j1",
        "  ",
        "+3",
        "99999999999999999999",
        "pcc",
        "kappa",
        "&amp;",
        "3.0",
    ]
)


def _parse(text: str) -> None:
    try:
        parse_string(text, source="fuzz.ucrdf")
    except UcrdfError as exc:
        assert exc.diagnostics
        for d in exc.diagnostics:
            assert str(d).startswith("fuzz.ucrdf")
            assert d.line >= 0 and d.message


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_mutated_attribute_values_never_crash(data):
    picks = data.draw(st.lists(st.integers(0, len(ATTRS) - 1), min_size=1, max_size=3))
    text = VALID
    for i in sorted(set(picks), reverse=True):
        m = ATTRS[i]
        text = text[: m.start(1)] + data.draw(NASTY) + text[m.end(1) :]
    _parse(text)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_deleted_or_duplicated_lines_never_crash(data):
    lines = list(LINES)
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(lines) - 1))
        if data.draw(st.booleans()):
            del lines[i]
        else:
            lines.insert(i, lines[i])
        if not lines:
            break
    _parse("\n".join(lines))


@settings(max_examples=50, deadline=None)
@given(st.text(max_size=200))
def test_arbitrary_text_never_crashes(text):
    _parse(text)


def test_external_entities_are_not_resolved(tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOPSECRET")
    text = VALID.replace(
        '<?xml version="1.0"?>',
        f'<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x SYSTEM "file://{secret}">]>',
    ).replace("<plugin>SoftRobotInterface</plugin>", "<plugin>&x;</plugin>")
    with pytest.raises(UcrdfError) as info:
        parse_string(text)
    (diag,) = info.value.diagnostics
    assert diag.line == line_of(text, "<!ENTITY x")
    assert diag.message.startswith(
        "DTD entity declarations are not supported in U(C)RDF (external entity 'x' "
    )
    assert "TOPSECRET" not in str(info.value)


def test_internal_entities_are_refused_too():
    text = VALID.replace(
        '<?xml version="1.0"?>',
        '<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY plug "SoftRobotInterface">]>',
    ).replace("<plugin>SoftRobotInterface</plugin>", "<plugin>&plug;</plugin>")
    with pytest.raises(UcrdfError, match="entity 'plug'"):
        parse_string(text)
