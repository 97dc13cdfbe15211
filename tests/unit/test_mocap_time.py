"""Motion-capture time (flight/mocap_time.py): Motive's frame times mapped onto this machine's clock whatever the
processing and network jitter, the stream's figures, and the mocap source stamping states with the capture."""
from __future__ import annotations

import numpy as np
import pytest

from flight.mocap_time import CaptureClock, StreamStats
from flight.source import MocapConfig, MocapSource

OFFSET_S = 1234.5  # this machine's clock minus Motive's
TRANSIT_S = 0.0003  # the shortest network transit


def frames(n: int, *, motive_jitter_s: float, network_jitter_s: float, seed: int = 0, rate_hz: float = 100.0):
    """(mid-exposure, transmit) in Motive's clock and arrival here, for ``n`` frames at ``rate_hz``."""
    rng = np.random.default_rng(seed)
    for k in range(n):
        mid = 10.0 + k / rate_hz
        transmit = mid + 0.004 + abs(rng.normal(0.0, motive_jitter_s))
        arrival = transmit + OFFSET_S + TRANSIT_S + abs(rng.normal(0.0, network_jitter_s))
        yield mid, transmit, arrival


@pytest.mark.parametrize("motive_jitter_s,network_jitter_s,error_max_s", [
    (0.0, 0.0, 1e-9), (0.2, 0.0, 1e-9),  # Motive's own delays are in its timestamps: exact
    (0.0, 0.2, 0.005), (0.05, 0.05, 0.002),  # the network's: the shortest excess transit the window saw
])
def test_a_frames_capture_time_is_its_exposure_whatever_the_jitter(motive_jitter_s, network_jitter_s, error_max_s):
    clock = CaptureClock(window_s=10.0)
    errors = [clock.capture_s(arrival, mid, transmit) - (mid + OFFSET_S + TRANSIT_S)
              for mid, transmit, arrival in frames(1000, motive_jitter_s=motive_jitter_s, network_jitter_s=network_jitter_s)]
    settled = np.array(errors[200:])  # after 2 s of frames
    assert np.all(settled >= -1e-9) and np.max(settled) < error_max_s, (settled.min(), settled.max())
    arrival_errors = [a - (m + OFFSET_S + TRANSIT_S) for m, _, a in frames(1000, motive_jitter_s=motive_jitter_s,
                                                                           network_jitter_s=network_jitter_s)]
    if motive_jitter_s or network_jitter_s:  # stamped on arrival (as the source did), each late frame moves
        assert np.mean(arrival_errors) > 0.05


def test_a_server_without_times_is_stamped_on_arrival():
    assert CaptureClock().capture_s(5.0, 0.0, 0.0) == 5.0


def test_the_stream_figures_say_rate_latency_jitter_gaps_and_late_frames():
    stats, clock = StreamStats(window_s=5.0), CaptureClock()
    kept = 0
    for k, (mid, transmit, arrival) in enumerate(frames(500, motive_jitter_s=0.0, network_jitter_s=0.0)):
        if 300 <= k < 310:  # a 100 ms gap: ten frames never sent
            continue
        kept += stats.add(clock.capture_s(arrival, mid, transmit), arrival, transmit - mid)
    s = stats.summary()
    assert s["mocap_rate_hz"] == pytest.approx(490 / 500 * 100, rel=0.01)
    assert s["mocap_latency_p50_ms"] == pytest.approx(4.0, abs=0.01) and s["motive_latency_ms"] == pytest.approx(4.0)
    assert s["mocap_jitter_ms"] < 0.01 and s["mocap_gap_max_ms"] == pytest.approx(110.0, abs=0.01)
    assert not stats.add(10.0 + OFFSET_S, 0.0, 0.0) and stats.summary()["mocap_frames_out_of_order"] == 1


def test_the_mocap_source_stamps_each_state_with_its_capture():
    source = MocapSource(MocapConfig(frame="enu"), 50.0, clock=lambda: 99.0)
    states = [source.frame(100.0 + 0.01 * k, np.array([0.01 * k, 0.0, 1.0]), (1.0, 0.0, 0.0, 0.0)) for k in range(10)]
    published = [s for s in states if s is not None]
    assert [round(s.t_s, 6) for s in published] == [0.0, 0.02, 0.04, 0.06, 0.08]
    assert [s.capture_stamp_s for s in published] == [100.0 + 0.01 * k for k in (0, 2, 4, 6, 8)]
    assert published[-1].vel_enu_mps[0] == pytest.approx(1.0, rel=0.05)  # from capture times: no arrival noise
