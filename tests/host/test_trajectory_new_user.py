"""New-user audit (trajectories): waypoints are counted from 1 wherever a user reads them, as
segment positions are (tests/host/test_positions_one_based.py), and a check reports every bad
waypoint at once (the first host.limits.MAX_REPORTED_PROBLEMS in full, then how many more), so a
long file is fixed in one run, not one waypoint per run."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from host.controllers.base import ControllerError
from host.controllers.waypoints import parse_waypoints
from host.limits import MAX_REPORTED_PROBLEMS, BendableLimits

REPO = Path(__file__).resolve().parents[2]
LIMITS = {n: BendableLimits(n, 0.3, kappa_max=3.0, kappa_rate_max=5.0) for n in ("s1", "s2")}


def _parse(points: list) -> None:
    parse_waypoints(points, np.zeros((2, 2)), ["s1", "s2"], LIMITS, "jtc")


def test_the_daemon_names_the_first_waypoint_one() -> None:
    with pytest.raises(ControllerError) as info:
        _parse([{"time_from_start": 1.0, "segments": {"s1": {"kappa": 4.0}}}])
    assert str(info.value).startswith("trajectory point 1.s1: kappa 4 1/m exceeds kappa_max 3")


def test_the_daemon_reports_every_bad_waypoint_of_a_goal_in_one_reason() -> None:
    """25 bad waypoints among 500: one refusal names the first MAX_REPORTED_PROBLEMS (in order,
    counted from 1) and how many more; nothing of the goal is built."""
    points = [{"time_from_start": 0.01 * (i + 1), "segments": {"s1": {"kappa": 1.0}}}
              for i in range(500)]  # fmt: skip
    bad = list(range(9, 500, 20))  # waypoints 10, 30, 50, ... (0-based 9, 29, ...)
    for i in bad:
        points[i]["segments"] = {"s2": {"kappa": 7.0}}
    points[250]["time_from_start"] = points[249]["time_from_start"]  # and one timing mistake
    with pytest.raises(ControllerError) as info:
        _parse(points)
    text = str(info.value)
    assert f"{len(bad) + 1} problems" in text, text
    assert text.count("\n") == MAX_REPORTED_PROBLEMS + 1, text  # head, 20 problems, "... more"
    assert f"... and {len(bad) + 1 - MAX_REPORTED_PROBLEMS} more" in text, text
    assert "trajectory point 10.s2: kappa 7 1/m exceeds" in text, text
    assert "trajectory point 251: time_from_start 2.5 s must be > 2.5 s" in text, text
    assert "trajectory point 9." not in text and "trajectory point 0" not in text, text


def test_a_timing_typo_is_one_problem_not_one_per_later_waypoint() -> None:
    times = [1.0, 2.0, 30.0, 4.0, 5.0]  # 30 for 3.0: only waypoint 4 comes before its predecessor
    with pytest.raises(ControllerError) as info:
        _parse([{"time_from_start": t, "segments": {"s1": {"kappa": 1.0}}} for t in times])
    assert str(info.value).startswith("trajectory point 4: time_from_start 4.0 s must be > 30")


def test_a_trajectory_file_names_every_bad_waypoint_by_line_and_number(tmp_path, capsys) -> None:
    """`ucr trajectory FILE --check`: every problem of the file in one go, each as
    FILE:LINE: waypoint N (counted from 1), like `ucr check`'s path:line diagnostics."""
    from tools.cli import main

    f = tmp_path / "wave.yaml"
    f.write_text(
        "waypoints:\n"
        "  - {t: 1, segments: {s1: {kappa: 1}}}\n"
        "  - {t: 2, segments: {s1: {kappa: -2}}}\n"
        "  - {t: 3, segments: {s1: {kappa: 1}}}\n"
        "  - t: 2.5\n"
        "    segments: {s1: {kappa: 1, phi: 0, phi_deg: 3}}\n"
        "  - {t: 4, segments: {s1: {kappa: x}}}\n"
    )
    rc = main(["trajectory", str(f), "--check"])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert f"{f}: 4 problems" in err, err
    assert f"{f}:3: waypoint 2.segments.s1.kappa: must be >= 0" in err, err
    assert f"{f}:5: waypoint 4: s1: give phi (rad) or phi_deg, not both" in err, err
    assert f"{f}:5: waypoint 4.time_from_start: times must increase strictly (2.5 s after" in err
    assert f"{f}:7: waypoint 5.segments.s1.kappa: expected a number" in err, err


# -- a lint: a waypoint number in a message is never a bare 0-based enumerate() index ---------
_WORDS = ("point", "waypoint", "goal", "sample")


def _zero_based_indices(tree: ast.AST) -> set[str]:
    """Names bound as the index of ``for i, x in enumerate(...)`` without ``start``."""
    out = set()
    for node in ast.walk(tree):
        if (isinstance(node, ast.For | ast.comprehension) and isinstance(node.iter, ast.Call)
                and getattr(node.iter.func, "id", "") == "enumerate"
                and len(node.iter.args) == 1 and not node.iter.keywords
                and isinstance(node.target, ast.Tuple)
                and isinstance(node.target.elts[0], ast.Name)):  # fmt: skip
            out.add(node.target.elts[0].id)
    return out


def test_no_message_numbers_a_waypoint_by_its_zero_based_index() -> None:
    """``f"trajectory point {n}"`` with ``n`` from a bare ``enumerate()`` shows the first
    waypoint as 0 (the audit's finding in host.controllers.waypoints and ``ucr trajectory``):
    count from 1 (``enumerate(..., start=1)`` or ``n + 1``)."""
    offenders = []
    for root in ("host", "interop"):
        for path in (REPO / root).rglob("*.py"):
            tree = ast.parse(path.read_text())
            zero = _zero_based_indices(tree)
            for node in ast.walk(tree):
                if not isinstance(node, ast.JoinedStr):
                    continue
                for a, b in zip(node.values, node.values[1:], strict=False):
                    if (isinstance(a, ast.Constant)
                            and str(a.value).rstrip().lower().endswith(_WORDS)
                            and isinstance(b, ast.FormattedValue)
                            and isinstance(b.value, ast.Name) and b.value.id in zero):  # fmt: skip
                        offenders.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert not offenders, f"number waypoints from 1: {offenders}"


def test_a_goal_of_many_bad_waypoints_stops_its_check_at_the_count_bound() -> None:
    # review: every problem of 10,000 points x 64 unknown segments was formatted (0.57 s in the
    # daemon's process, 9x a good goal's check); the check now stops at MAX_COUNTED_PROBLEMS
    from host.limits import MAX_COUNTED_PROBLEMS

    segs = {f"bogus_{j}": {"kappa": 1.0} for j in range(64)}
    points = [{"time_from_start": 0.01 * (i + 1), "segments": segs} for i in range(10_000)]
    with pytest.raises(ControllerError) as info:
        _parse(points)
    text = str(info.value)
    assert f"at least {MAX_COUNTED_PROBLEMS} problems" in text, text[:200]
    assert f"(the check stops at {MAX_COUNTED_PROBLEMS})" in text.splitlines()[-1], text[-200:]


def test_a_phi_deg_problem_still_checks_the_waypoints_time(tmp_path) -> None:
    # review: a waypoint with a phi_deg problem was skipped before its time was kept, so the next
    # waypoint's order was judged against the wrong time (its problem showed only after a fix)
    from host.client_common import CliError
    from host.client_motion import load_trajectory_file

    f = tmp_path / "w.yaml"
    f.write_text(
        "- {t: 1, segments: {s1: {kappa: 1}}}\n"
        "- {t: 5, segments: {s1: {kappa: 1, phi_deg: 30, phi: 0.5}}}\n"
        "- {t: 3, segments: {s1: {kappa: 1}}}\n"
    )
    with pytest.raises(CliError) as info:
        load_trajectory_file(str(f))
    text = str(info.value)
    assert "2 problems" in text, text
    assert f"{f}:2: waypoint 2: s1: give phi (rad) or phi_deg, not both" in text, text
    assert f"{f}:3: waypoint 3.time_from_start: times must increase strictly (3 s after 5 s)" in (
        text
    ), text


def test_the_file_check_refuses_points_closer_than_the_daemon_accepts(tmp_path, capsys) -> None:
    # review: `ucr trajectory --check` passed waypoints 0.5 ms apart that the daemon always
    # refuses (at least 1 ms between points); the API's schema now holds that rule too
    from tools.cli import main as ucr

    f = tmp_path / "close.yaml"
    f.write_text(
        "- {t: 1, segments: {s1: {kappa: 1}}}\n"
        "- {t: 1.0005, segments: {s1: {kappa: 2}}}\n"
        "- {t: 2, segments: {s1: {kappa: 1}}}\n"
    )
    assert ucr(["trajectory", str(f), "--check"]) == 1
    err = capsys.readouterr().err
    said = f"{f}:2: waypoint 2.time_from_start: 1.0005 s is 0.5 ms after the point before (1 s)"
    assert said in err, err
    f.write_text("- {t: 0.0005, segments: {s1: {kappa: 1}}}\n")
    assert ucr(["trajectory", str(f), "--check"]) == 1
    assert "0.5 ms after the start; at least 1 ms between points" in capsys.readouterr().err


def test_points_exactly_1_ms_apart_in_decimals_are_accepted() -> None:
    # code review: 1.0 then 1.001 is 0.99999... ms in floats and was refused by the schema and
    # the cJTC alike ("1 ms after the point before; at least 1 ms between points")
    from host.api.schema import validate_points

    pts = [
        {"t": 1.0 + i * 0.001, "segments": {"s1": {"kappa": 1.0 + i * 0.001}}} for i in range(50)
    ]
    assert len(validate_points(pts)) == 50
    _parse(pts)  # the daemon's own check: no ControllerError
