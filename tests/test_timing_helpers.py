"""The helpers real-time tests use instead of timing assertions (afmctl.testing): samples on
the device's clock with the skipped ticks counted, and a bounded underrun count."""
from __future__ import annotations

import pytest

from afmctl.testing import MAX_UNDERRUN_FRACTION, assert_few_underruns, ticks_on_the_device_clock


def test_ticks_on_the_device_clock_counts_skipped_ticks_and_refuses_jitter():
    t0, rate = 12.5, 1000.0
    ticks = [0, 1, 2, 5, 6, 9]
    assert ticks_on_the_device_clock([t0 + k / rate for k in ticks], t0, rate) == 4
    assert ticks_on_the_device_clock([t0 + k / rate for k in range(100)], t0, rate) == 0
    with pytest.raises(AssertionError, match="off the device clock"):
        ticks_on_the_device_clock([t0, t0 + 0.0015], t0, rate)         # half a period late
    with pytest.raises(AssertionError, match="off the device clock"):
        ticks_on_the_device_clock([t0 + 0.001, t0 + 0.001], t0, rate)  # two samples on one tick


def test_assert_few_underruns_bounds_the_count():
    assert_few_underruns(0, 1000)
    assert_few_underruns(int(MAX_UNDERRUN_FRACTION * 1000), 1000)
    with pytest.raises(AssertionError, match="underruns in 1000 samples"):
        assert_few_underruns(int(MAX_UNDERRUN_FRACTION * 1000) + 1, 1000)
