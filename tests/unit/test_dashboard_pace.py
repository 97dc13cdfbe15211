"""The dashboard's UI loop pacing: on time it waits for the due time; late, it still idles (viser
sends nothing to the pages while a render is inside ``server.atomic()``, so a loop running back to
back would freeze the page)."""
from __future__ import annotations

import pytest

from dashboard.service import MIN_IDLE_SHARE, pace

PERIOD_S = 0.05


def test_on_time_waits_until_the_step_is_due():
    delay, due = pace(10.05, 10.01, PERIOD_S)
    assert delay == pytest.approx(0.04)
    assert due == 10.05


@pytest.mark.parametrize("now_s", [10.04, 10.05, 10.2, 13.0])
def test_late_or_nearly_late_idles_a_share_of_a_period_and_starts_counting_again(now_s):
    delay, due = pace(10.05, now_s, PERIOD_S)
    assert delay == pytest.approx(MIN_IDLE_SHARE * PERIOD_S)
    assert due == pytest.approx(now_s + MIN_IDLE_SHARE * PERIOD_S)


def test_a_slow_loop_never_runs_back_to_back():
    """Steps that take 1.5 periods each: every gap between them is at least the minimum idle."""
    now, due, gaps = 0.0, 0.0, []
    for _ in range(100):
        now += 1.5 * PERIOD_S  # the step
        delay, due = pace(due + PERIOD_S, now, PERIOD_S)
        gaps.append(delay)
        now += delay
    assert min(gaps) >= MIN_IDLE_SHARE * PERIOD_S - 1e-12
