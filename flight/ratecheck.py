"""Does the source sample at the rate this service was started for? Checked from the samples' own times.

The estimator's ESO and the controller's rate limiter are discretised for their ``--rate``; a source
started at another rate makes both wrong without anything failing loudly. :class:`RateCheck` takes the
median step of the source's ``t_s`` over the first samples of each flight and says once whether it
matches, whatever the source is: simulator, mocap or a replay; a mismatch is an error event for the operator.
"""
from __future__ import annotations

import statistics


class RateCheck:
    """Feed :meth:`observe` every state sample. After ``samples`` steps of a flight :attr:`verdict` says
    whether the source's rate is within ``tolerance`` (fraction) of ``1 / period_s``; when it is not,
    :meth:`observe` returns ``("error", text)`` once per flight."""

    def __init__(self, service: str, period_s: float, *, samples: int = 25, tolerance: float = 0.02) -> None:
        self.service, self.period_s, self.samples, self.tolerance = service, period_s, samples, tolerance
        self._last: tuple[int, float] | None = None
        self._steps: list[float] = []
        self._said = False
        self.verdict = "not checked yet"

    def observe(self, seq: int, t_s: float) -> tuple[str, str] | None:
        if self._last is not None and seq < self._last[0]:  # a new flight: check again
            self._steps, self._said = [], False
        if self._last is not None and seq == self._last[0] + 1 and t_s > self._last[1]:
            self._steps.append(t_s - self._last[1])
        self._last = (seq, t_s)
        if self._said or len(self._steps) < self.samples:
            return None
        self._said = True
        source_hz, own_hz = 1.0 / statistics.median(self._steps), 1.0 / self.period_s
        if abs(source_hz / own_hz - 1.0) <= self.tolerance:
            self.verdict = f"rate {own_hz:.4g} Hz matches the source's ({source_hz:.4g} Hz from its sample times)"
            return None
        self.verdict = (f"the source samples at {source_hz:.4g} Hz (median step of {len(self._steps)} sample times) "
                        f"but the {self.service} runs at {own_hz:.4g} Hz: its discretisation is wrong; start both "
                        "with the same --rate")
        return "error", self.verdict
