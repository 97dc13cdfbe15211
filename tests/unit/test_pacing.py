"""The periodic loop's pacing rule (runtime.pacing): a late sample caught up, a stall not turned into a burst."""
from __future__ import annotations

import pytest

from runtime.pacing import next_wait


def test_on_time_waits_late_by_under_a_period_catches_up_further_behind_goes_on_from_now():
    assert next_wait(1.02, 0.02, 1.005) == (pytest.approx(0.015), 1.02)  # on time: wait, the grid kept
    assert next_wait(1.02, 0.02, 1.035) == (pytest.approx(-0.015), 1.02)  # late by under a period: at once, on grid
    assert next_wait(1.02, 0.02, 1.5) == (pytest.approx(-0.48), 1.5)  # a stall: from now, no burst after it
