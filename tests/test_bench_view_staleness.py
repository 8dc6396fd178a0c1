"""bench_view's overload figure measures what it names (docs/view.md "A page on an overloaded
machine"): how long the page went on showing one sample, counted to the next sample shown or to
the end of the window, from the shown sample's own daemon time."""

from __future__ import annotations

import math

from benchmarks.bench_view import staleness


def test_a_sample_is_shown_until_the_next_one_from_its_daemon_time() -> None:
    # [wall ms shown, daemon sample wall ms]: the second sample is shown 50 ms after it was taken
    # and stays on the page until the third appears at 5000: 5000 - 1000 = 4000 ms on one sample
    samples = [[100.0, 50.0], [1050.0, 1000.0], [5000.0, 4980.0]]
    assert staleness(samples, end_ms=5100.0) == 4000.0
    # the last sample counts to the end of the window
    assert staleness(samples, end_ms=20000.0) == 20000.0 - 4980.0


def test_no_sample_shown_has_no_figure() -> None:
    assert math.isnan(staleness([], end_ms=1000.0))
