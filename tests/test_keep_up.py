"""Whether a DM sweep's spot fits keep up with its camera (torchblur.identify.keep_up): the wait
after the last frame of the sweep's schedule (frequency k acquired once k - lag's fit is done, one
fit worker), worked by hand; the report's pace line and --json record from a run's fit times."""
import math

import numpy as np
import pytest

from torchblur.identify.keep_up import pace_line, pace_summary, sweep_schedule


def test_the_wait_follows_the_sweep_s_schedule():
    # fits faster than the frames: the last fit starts at the last frame, the camera never waits
    assert sweep_schedule([0.5, 0.5, 0.5], 1.0, 2) == pytest.approx((0.5, 0.0))
    # 3 s fits of 1 s acquisitions, lag 2: frames of k=2 wait for fit 0 (ends at 4), end at 5; fits end at 4, 7, 10
    assert sweep_schedule([3.0, 3.0, 3.0], 1.0, 2) == pytest.approx((5.0, 2.0))
    # lag 1: acquisitions end at 1, 5, 9 (each waits for the previous fit), fits at 4, 8, 12
    assert sweep_schedule([3.0, 3.0, 3.0], 1.0, 1) == pytest.approx((3.0, 6.0))
    # per-frequency acquisition times, one slow fit in the middle
    # (hand: fits end at 3, 14, 15, 17; frequency 3's frames wait for fit 1, from 14 to 16)
    assert sweep_schedule([1.0, 10.0, 1.0, 1.0], [2.0, 2.0, 2.0, 2.0], 2) == pytest.approx((1.0, 8.0))
    # however slow the fits, the wait stays within lag fits: the sweep waits for them instead
    wait, idle = sweep_schedule(np.full(16, 100.0), 8.0, 2)
    assert wait == pytest.approx(2 * 100.0 - 8.0) and idle == pytest.approx(14 * 100.0 + 8.0 - 15 * 8.0)
    assert all(math.isnan(v) for v in sweep_schedule([1.0, float("nan")], 1.0, 2))


def test_pace_summary_and_line():
    p = pace_summary(np.array([4.0, 6.0, 5.0]), 240, 30.0, 2)
    assert p["acquire_s"] == pytest.approx(8.0) and p["fit_median_s"] == 5.0 and p["fit_max_s"] == 6.0 and p["keeps_up"]
    assert (p["wait_s"], p["idle_s"]) == pytest.approx(sweep_schedule([4.0, 6.0, 5.0], 8.0, 2))
    line = pace_line(p)
    assert line.startswith("dm fit pace: the spot fits took 5.0 s per frequency") and "keeps up (fit/acquisition 0.62)" in line
    slow = pace_summary([12.0, 12.0], 240, 30.0, 2)
    assert not slow["keeps_up"] and "does not keep up" in pace_line(slow)
    assert pace_summary(None, 240, 30.0, 2) is None and pace_line(None) is None
    # no frame rate (an outside recording's camera): the fit times, and the line says the pace is not judged
    unknown = pace_summary([4.0, 6.0, 5.0], 240, None, 2)
    assert unknown["fit_median_s"] == 5.0 and unknown["keeps_up"] is None and unknown["wait_s"] is None
    assert "does not give its camera's frame rate" in pace_line(unknown) and "keeps up (" not in pace_line(unknown)
