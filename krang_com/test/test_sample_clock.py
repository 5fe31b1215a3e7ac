"""DMU sample times from the sequence counter (krang_can_bridge.sample_clock), against arrival
times."""

import pytest

from krang_can_bridge.sample_clock import SampleClock

P = 0.005


def test_jittered_arrivals_give_the_sampling_grid():
    clock = SampleClock(P)
    arrivals = [0.0, 0.0071, 0.0093, 0.0172, 0.0201]  # up to 2 ms of jitter either way
    times = [clock.time_of(k, t) for k, t in enumerate(arrivals)]
    assert times == pytest.approx([0.0, P, 2 * P, 3 * P, 4 * P], abs=1e-12)
    assert clock.time_of(4, 0.0205) == pytest.approx(4 * P)  # the second frame of the same sample


def test_burst_after_a_stall_keeps_the_spacing_within_the_lag_bound():
    clock = SampleClock(P, lag_max_s=0.04)
    clock.time_of(0, 0.0)
    # 6 samples queued during a 30 ms stall arrive at once: by arrival they would be one instant
    times = [clock.time_of(k, 0.030) for k in range(1, 7)]
    assert times == pytest.approx([k * P for k in range(1, 7)], abs=1e-12)
    # a longer stall: the samples are never kept more than lag_max behind the clock
    assert clock.time_of(7, 1.0) == pytest.approx(1.0 - 0.04)
    assert clock.time_of(8, 1.0) == pytest.approx(1.0 - 0.04 + P)


def test_counter_wrap_and_re_anchoring():
    clock = SampleClock(P, lead_max_s=0.5)
    clock.time_of(254, 10.0)
    assert clock.time_of(1, 10.015) == pytest.approx(10.0 + 3 * P)  # 254 -> 255 -> 0 -> 1
    # 1.0 s ahead: a restart, re-anchored
    assert clock.time_of(200, 10.02) == pytest.approx(10.02)
    with pytest.raises(ValueError):
        SampleClock(0.0)
