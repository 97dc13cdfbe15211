"""Does the source sample at the rate this service was started for? Checked from the samples' own times.

The estimator's ESO and the controller's rate limiter are discretised for their ``--rate``; a source
started at another rate makes both wrong without anything failing loudly. :class:`RateCheck` takes the
source's period as the least-squares slope of ``t_s`` over ``seq`` in the first samples of each flight and says
once whether it matches, whatever the source is: simulator, mocap or a replay; a mismatch is an error event for
the operator. A slope, not a median step: motion capture at 120 or 360 Hz gives the state of each period the time
of the frame that opens it, so single steps are whole frame intervals (360 Hz: 19.4 and 22.2 ms for a 20 ms
period, median 19.4) while their trend is the period.
"""
from __future__ import annotations

import numpy as np


class RateCheck:
    """Feed :meth:`observe` every state sample. After ``samples`` steps of a flight :attr:`verdict` says
    whether the source's rate is within ``tolerance`` (fraction) of ``1 / period_s``; when it is not,
    :meth:`observe` returns ``("error", text)`` once per flight."""

    def __init__(self, service: str, period_s: float, *, samples: int = 25, tolerance: float = 0.02) -> None:
        self.service, self.period_s, self.samples, self.tolerance = service, period_s, samples, tolerance
        self._last: tuple[int, float] | None = None
        self._times: list[tuple[int, float]] = []  # (seq, t_s) of this flight's samples, in order
        self._said = False
        self.verdict = "not checked yet"

    def observe(self, seq: int, t_s: float) -> tuple[str, str] | None:
        if self._last is not None and seq < self._last[0]:  # a new flight: check again
            self._times, self._said = [], False
        if self._last is None or (seq > self._last[0] and t_s > self._last[1]):
            self._times.append((seq, t_s))
        self._last = (seq, t_s)
        if self._said or len(self._times) <= self.samples:
            return None
        self._said = True
        seqs, times = (np.array(c, dtype=float) for c in zip(*self._times))
        source_hz, own_hz = 1.0 / float(np.polyfit(seqs - seqs[0], times - times[0], 1)[0]), 1.0 / self.period_s
        if abs(source_hz / own_hz - 1.0) <= self.tolerance:
            self.verdict = f"rate {own_hz:.4g} Hz matches the source's ({source_hz:.4g} Hz from its sample times)"
            return None
        self.verdict = (f"the source samples at {source_hz:.4g} Hz (trend of {len(self._times)} sample times) "
                        f"but the {self.service} runs at {own_hz:.4g} Hz: its discretisation is wrong; start both "
                        "with the same --rate")
        return "error", self.verdict
