"""host.limits.Problems: a check of many waypoints reports every problem in one go, bounded
(new-user audit: a 500-waypoint file was fixed one error per run)."""

from __future__ import annotations

from host.limits import MAX_REPORTED_PROBLEMS, Problems


def test_one_problem_reads_as_one_line() -> None:
    p = Problems()
    assert not p
    p.add("waypoint 3: kappa 9 1/m exceeds kappa_max 3.314 1/m")
    assert p and p.count == 1
    assert p.text("wave.yaml") == "wave.yaml: waypoint 3: kappa 9 1/m exceeds kappa_max 3.314 1/m"


def test_every_problem_is_counted_and_the_first_ones_shown_in_order() -> None:
    p = Problems()
    for n in range(1, 501):
        p.add(f"waypoint {n}: bad")
    lines = p.text("wave.yaml").splitlines()
    assert lines[0] == "wave.yaml: 500 problems:"
    assert lines[1 : MAX_REPORTED_PROBLEMS + 1] == [
        f"  waypoint {n}: bad" for n in range(1, MAX_REPORTED_PROBLEMS + 1)
    ]
    assert lines[-1] == f"  ... and {500 - MAX_REPORTED_PROBLEMS} more"
    assert len(lines) == MAX_REPORTED_PROBLEMS + 2


def test_a_few_problems_are_all_shown_with_no_more_line() -> None:
    p = Problems(limit=5)
    for n in (2, 7, 9):
        p.add(f"waypoint {n}: bad")
    assert p.text("f") == "f: 3 problems:\n  waypoint 2: bad\n  waypoint 7: bad\n  waypoint 9: bad"
