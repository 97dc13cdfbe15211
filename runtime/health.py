"""A service's health figures: output rate, in-service latency, rejected input, staleness, counters."""
from __future__ import annotations

import os
import threading
import time
from collections import Counter, deque

import numpy as np

from runtime.schema import HealthMsg

_WINDOW = 2000  # latency samples kept (40 s at 50 Hz, 4 s at 500 Hz)


class HealthStats:
    """Thread-safe counters a node updates and a 1 Hz timer turns into :class:`HealthMsg`."""

    def __init__(self, service: str, inputs: tuple[str, ...]) -> None:
        self.service = service
        self._lock = threading.Lock()
        self._started = time.monotonic()
        self._ticks = 0
        self._ticks_at_last = 0
        self._last_report = self._started
        self._latency_s: deque[float] = deque(maxlen=_WINDOW)
        self.rejected: Counter[str] = Counter({name: 0 for name in inputs})
        self._last_valid: dict[str, float] = {name: -1.0 for name in inputs}
        self.last_rejection = ""
        self.status = "ok"
        self.counters: Counter[str] = Counter()  # what the service counts since start (HealthMsg.counters)

    def valid(self, name: str, now_s: float) -> None:
        self._last_valid[name] = now_s

    def reject(self, name: str, reason: str) -> None:
        with self._lock:
            self.rejected[name] += 1
            self.last_rejection = f"{name}: {reason}"

    def count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def set_counter(self, name: str, value: int) -> None:
        with self._lock:
            self.counters[name] = value

    def output(self, latency_s: float) -> None:
        with self._lock:
            self._ticks += 1
            self._latency_s.append(latency_s)

    @property
    def ticks(self) -> int:
        return self._ticks

    def report(self) -> HealthMsg:
        now = time.monotonic()
        with self._lock:
            span = max(now - self._last_report, 1e-9)
            rate = (self._ticks - self._ticks_at_last) / span
            self._ticks_at_last, self._last_report = self._ticks, now
            lat = np.array(self._latency_s) * 1e3 if self._latency_s else np.zeros(1)
            rejected = {k: float(v) for k, v in self.rejected.items()}
            counters = {k: float(v) for k, v in self.counters.items()}
        staleness = {k: (round(now - t, 4) if t >= 0 else -1.0) for k, t in self._last_valid.items()}
        return HealthMsg(
            stamp_s=now, service=self.service, pid=os.getpid(), uptime_s=now - self._started, ticks=self._ticks,
            rate_hz=rate, latency_p50_ms=float(np.percentile(lat, 50)), latency_p99_ms=float(np.percentile(lat, 99)),
            rejected=rejected, staleness_s=staleness, status=self.status[:1024], counters=counters,
        )
