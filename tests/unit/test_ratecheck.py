"""A service started at another rate than its source's says so, from the samples' own times."""
from __future__ import annotations

import math
from dataclasses import replace

from flight.controller import ControllerConfig, ControllerCore
from flight.ratecheck import RateCheck
from neso.control import ControlConfig
from tests.helpers import fixed_clock, flight_messages


def states(n: int, seq0: int = 0):
    return [m for topic, m in flight_messages(n, seq0=seq0) if topic == "state"]  # 50 Hz sample times


def test_a_matching_rate_is_silent_and_recorded():
    check = RateCheck("estimator", 0.02)
    assert [check.observe(s.seq, s.t_s) for s in states(40)] == [None] * 40
    assert check.verdict.startswith("rate 50 Hz matches the source's (50 Hz")


def test_a_wrong_rate_is_an_error_once_per_flight():
    check = RateCheck("estimator", 0.01)
    said = [v for s in states(60) if (v := check.observe(s.seq, s.t_s))]
    assert said == [("error", "the source samples at 50 Hz (trend of 26 sample times) but the estimator runs "
                              "at 100 Hz: its discretisation is wrong; start both with the same --rate")]
    again = [v for s in states(60) if (v := check.observe(s.seq, s.t_s))]  # seq from 0: a new flight
    assert len(again) == 1


def test_the_controller_tells_the_operator():
    core = ControllerCore(replace(ControllerConfig(), control=ControlConfig(dt_s=1 / 200)), clock=fixed_clock)
    for s in states(30):
        core.on_state(s, s.stamp_s)
    assert [e for e in core.events if "runs at 200 Hz" in e[1]][0][0] == "error"


def test_motion_capture_frames_at_120_and_360_hz_on_a_50_hz_grid_match():
    """Each period's state has the time of the frame that opens it: steps of whole frame intervals (360 Hz:
    19.4 and 22.2 ms), whose trend is the period; 48 Hz is still told apart."""
    for frame_hz in (120.0, 360.0):
        check = RateCheck("estimator", 0.02)
        times = [math.ceil(k * 0.02 * frame_hz - 1e-9) / frame_hz for k in range(40)]
        assert [check.observe(k, t) for k, t in enumerate(times)] == [None] * 40, (frame_hz, check.verdict)
    check = RateCheck("estimator", 0.02)
    times = [math.ceil(k / 48.0 * 360.0 - 1e-9) / 360.0 for k in range(40)]
    assert [v[0] for k, t in enumerate(times) if (v := check.observe(k, t))] == ["error"]
