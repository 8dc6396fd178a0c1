"""Tendon angles are radians: a file giving them in degrees (0, 120, 240) is refused by
`ucr check` with path:line, instead of being silently taken modulo 2*pi (120 rad = 1.1 rad)."""

from __future__ import annotations

import pytest

from tools.cli import main
from ucrdf.parser import parse_string

from .conftest import VALID, diagnostics_of, line_of


def _degrees_file() -> str:
    text = VALID.replace('angle="2.0943951023931953"', 'angle="120"')
    return text.replace('angle="4.1887902047863905"', 'angle="240"')


def test_tendon_angles_in_degrees_are_refused_with_their_line():
    text = _degrees_file()
    assert 'angle="120"' in text
    diags = diagnostics_of(text)
    msgs = [d for d in diags if "beyond 2*pi" in d.message]
    assert msgs, diags
    d = msgs[0]
    assert d.line == line_of(text, 'angle="120"')
    assert "angles are radians" in d.message and "2.094395102" in d.message


def test_ucr_check_prints_path_line_and_exits_1(tmp_path, capsys):
    path = tmp_path / "degrees.ucrdf"
    text = _degrees_file()
    path.write_text(text)
    assert main(["check", str(path)]) == 1
    err = capsys.readouterr().err
    line = line_of(text, 'angle="120"')
    assert f"{path}:{line}:" in err and "beyond 2*pi" in err


@pytest.mark.parametrize("angle", ["6.283185307179586", "-3.14159", "0"])
def test_angles_within_two_pi_stay_accepted(angle):
    import re

    first = re.search(r'<tendon index="0" angle="([^"]+)"', VALID).group(1)
    text = VALID.replace(f'<tendon index="0" angle="{first}"', f'<tendon index="0" angle="{angle}"')
    parse_string(text, source="ok.ucrdf")  # no error
