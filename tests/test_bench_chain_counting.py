"""bench_chain counts what it claims to (issue 14 audit): the round-trip deadline is the 10 ms
period wherever the store-and-forward floor fits in it, and the paced cycle median counts the
misses instead of the survivors."""

from __future__ import annotations

import math

from benchmarks.bench_chain import RTT_PERIOD_S, median_counting_misses, rtt_deadline_s
from host import floors


def test_the_round_trip_deadline_is_the_period_where_the_floor_fits() -> None:
    # 8 segments @ 921600: the store-and-forward floor (~8.3 ms) fits in 10 ms, so 10 ms it is
    # (it was twice that floor, 16.7 ms, which let 14 ms round trips count as on time)
    assert floors.store_and_forward_floor_s(8, 921600) <= RTT_PERIOD_S
    assert rtt_deadline_s(8, 921600) == RTT_PERIOD_S
    assert rtt_deadline_s(1, 115200) == RTT_PERIOD_S
    # 8 segments @ 115200: the floor alone is longer than the period: twice the floor
    sf = floors.store_and_forward_floor_s(8, 115200)
    assert sf > RTT_PERIOD_S and rtt_deadline_s(8, 115200) == 2 * sf


def test_the_paced_median_counts_misses_as_at_least_their_deadline() -> None:
    assert median_counting_misses([0.004, 0.005, 0.006], 0, 0.01) == (0.005, False)
    # one complete cycle and 199 misses: the median is a miss, not the one survivor
    assert median_counting_misses([0.009], 199, 0.01) == (0.01, True)
    value, bound = median_counting_misses([], 0, 0.01)
    assert math.isnan(value) and not bound
