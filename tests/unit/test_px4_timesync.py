"""flight.px4_timesync: PX4 v1.16's Timesync, followed from its requests (src/lib/timesync/Timesync.cpp)."""
import pytest

from flight.px4_timesync import CONVERGENCE_WINDOW, MAX_CONSECUTIVE_HIGH_DEVIATION, MAX_DEVIATION_US, Px4Timesync

OFFSET_US = 7_000_000.0  # PX4's clock less ours
PERIOD_US = 20_000.0  # PX4 asks at 50 Hz


def feed(sync: Px4Timesync, n: int, *, start: int = 0, jump_us: float = 0.0, rtt_ok: bool = True) -> list[int]:
    """``n`` requests from request number ``start`` on, PX4's clock ``jump_us`` off; the numbers at which it reset."""
    resets = []
    for k in range(start, start + n):
        ours = k * PERIOD_US
        if sync.request(ours + OFFSET_US + jump_us + 300.0 * (k % 3), ours, rtt_ok=rtt_ok):
            resets.append(k)
    return resets


def test_it_converges_at_the_500th_sample_counting_only_round_trips_under_10_ms():
    sync = Px4Timesync()
    feed(sync, 100, rtt_ok=False)
    assert sync.samples == 0 and not sync.converged
    feed(sync, CONVERGENCE_WINDOW - 1, start=100)
    assert not sync.converged
    feed(sync, 1, start=CONVERGENCE_WINDOW + 99)
    assert sync.converged and abs(sync.offset_us - OFFSET_US) < 1_000


def test_a_jump_of_over_100_ms_resets_after_more_than_10_in_a_row_and_counting_starts_again():
    sync = Px4Timesync()
    feed(sync, CONVERGENCE_WINDOW)
    jump = MAX_DEVIATION_US + 50_000  # a 150 ms stall of PX4's clock against ours
    assert feed(sync, MAX_CONSECUTIVE_HIGH_DEVIATION, start=CONVERGENCE_WINDOW, jump_us=-jump) == []
    assert sync.converged, "10 in a row: PX4 still keeps its estimate"
    resets = feed(sync, 1, start=CONVERGENCE_WINDOW + 10, jump_us=-jump)
    assert resets and not sync.converged and sync.samples == 0 and sync.resets == 1
    assert sync.last_jump_us == pytest.approx(-jump, abs=1_000)
    feed(sync, CONVERGENCE_WINDOW, start=CONVERGENCE_WINDOW + 11, jump_us=-jump)
    assert sync.converged and abs(sync.offset_us - (OFFSET_US - jump)) < 1_000, "converged on the new offset"


def test_fewer_deviant_samples_in_a_row_or_small_jumps_or_jumps_before_convergence_do_not_reset():
    sync = Px4Timesync()
    feed(sync, 300)
    assert feed(sync, 50, start=300, jump_us=500_000) == [], "before convergence the filter follows"
    feed(sync, CONVERGENCE_WINDOW, start=350, jump_us=500_000)
    assert sync.converged
    start = 850
    for _ in range(5):  # 10 deviant, then one near the estimate: the count starts over
        assert feed(sync, MAX_CONSECUTIVE_HIGH_DEVIATION, start=start, jump_us=800_000) == []
        assert feed(sync, 1, start=start + 10, jump_us=500_000) == []
        start += 11
    assert feed(sync, 200, start=start, jump_us=500_000 + 0.8 * MAX_DEVIATION_US) == []
    assert sync.converged and sync.resets == 0
