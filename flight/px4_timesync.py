"""PX4's time sync with the gateway, as PX4 counts it, from the requests PX4 sends: whether PX4 dates external vision
by the capture time in ODOMETRY's ``time_usec`` or on arrival. Pure: no clock, no I/O.

PX4 v1.16 (``src/lib/timesync/Timesync.cpp``) filters the offset between its clock and ours from every answer to its
TIMESYNC requests with a round trip under 10 ms. It counts them; from the 500th on (``CONVERGENCE_WINDOW``) it has
converged and dates a sample by the capture time (``sync_stamp``), before that on arrival. Once converged, an answer
more than 100 ms (``MAX_DEVIATION_SAMPLE``) off its estimate counts as high deviation; more than 10 in a row
(``MAX_CONSECUTIVE_HIGH_DEVIATION``) and PX4 warns "time jump detected" and resets its filter to no samples: it dates
on arrival again until 500 more. A PX4 SITL in lockstep takes its clock from the world, so a stall of the world (or
of PX4) moves that offset by the stall: loaded run 57 measured such a reset in PX4's ULog (dated by the capture from
9.4 s on, then on arrival again) while the gateway still said PX4 took the capture time.

The same offset, seen from here: each request carries PX4's clock when it was sent (``ts1``); less our clock when it
arrived, that is the offset less the link's one-way delay (milliseconds; the threshold is 100 ms). Before
convergence PX4's filter follows fast (its gain starts at 0.05), after it slowly (0.003); the reference here follows
likewise. The round trip PX4 measures is the link's: this model counts a request only while the gateway's own round
trips (median) are under 10 ms — PX4's answers to the gateway's requests, on the same link.
"""
from __future__ import annotations

from dataclasses import dataclass

CONVERGENCE_WINDOW = 500  # PX4's Timesync: samples before it has converged
MAX_RTT_US = 10_000  # PX4's MAX_RTT_SAMPLE: a sample with a slower round trip does not count
MAX_DEVIATION_US = 100_000  # PX4's MAX_DEVIATION_SAMPLE
MAX_CONSECUTIVE_HIGH_DEVIATION = 10  # PX4 resets after more than this many in a row
ALPHA_INITIAL, ALPHA_FINAL = 0.05, 0.003  # PX4's ALPHA_GAIN_INITIAL / _FINAL


@dataclass
class Px4Timesync:
    """PX4's Timesync state, followed from its requests: :meth:`request` with each one's ``ts1`` (PX4's clock, µs)
    and our clock when it arrived (µs); ``rtt_ok``: whether the link's round trip is under PX4's 10 ms now."""

    samples: int = 0  # PX4's _sequence: counted samples since its last reset
    resets: int = 0
    offset_us: float | None = None  # PX4's clock less ours, less the one-way delay (the reference, filtered)
    high_deviation: int = 0
    last_jump_us: float = 0.0  # the deviation that made the last reset

    @property
    def converged(self) -> bool:
        """PX4 dates external vision by its capture time (``sync_stamp``)."""
        return self.samples >= CONVERGENCE_WINDOW

    def request(self, px4_ts1_us: float, our_now_us: float, *, rtt_ok: bool) -> bool:
        """One TIMESYNC request from PX4; True when PX4 resets its time sync at this one (a time jump)."""
        if not rtt_ok:
            return False
        observed = px4_ts1_us - our_now_us
        if self.converged and abs(observed - self.offset_us) > MAX_DEVIATION_US:
            self.high_deviation += 1
            if self.high_deviation > MAX_CONSECUTIVE_HIGH_DEVIATION:
                self.last_jump_us = observed - self.offset_us
                self.samples, self.offset_us, self.high_deviation = 0, None, 0
                self.resets += 1
                return True
            return False
        alpha = ALPHA_FINAL if self.converged else ALPHA_INITIAL
        self.offset_us = observed if self.offset_us is None else alpha * observed + (1 - alpha) * self.offset_us
        self.samples += 1
        self.high_deviation = 0
        return False
