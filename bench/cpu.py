"""CPU time of benchmarked processes, from ``/proc`` (Linux)."""
from __future__ import annotations

import os
import threading
import time
from typing import Callable, Iterable


def cpu_s(pids: Iterable[int]) -> float:
    """User + system CPU seconds so far of ``pids``, summed (a process that is gone counts 0)."""
    total = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            pass
    return total


class CpuWindow:
    """Each named process's CPU over one window of a run, measured on a thread of its own: once
    ``start`` is set (given up after ``start_timeout_s``) it asks ``processes()`` for ``{name: pid}``
    and reads their CPU then and ``seconds`` later. :meth:`per_sample_us`: µs of CPU per sample of a
    ``rate_hz`` loop."""

    def __init__(self, processes: Callable[[], dict[str, int]], seconds: float, start: threading.Event,
                 start_timeout_s: float = 60.0) -> None:
        self._processes, self._seconds, self._start, self._start_timeout_s = processes, seconds, start, start_timeout_s
        self._cpu_fraction: dict[str, float] = {}
        self._thread = threading.Thread(target=self._measure, name="cpu-window", daemon=True)
        self._thread.start()

    def _measure(self) -> None:
        if not self._start.wait(self._start_timeout_s):
            return
        pids = self._processes()
        before, t0 = {name: cpu_s([pid]) for name, pid in pids.items()}, time.monotonic()
        time.sleep(self._seconds)
        span_s = time.monotonic() - t0
        self._cpu_fraction = {name: (cpu_s([pid]) - before[name]) / span_s for name, pid in pids.items()}

    def per_sample_us(self, rate_hz: float, timeout_s: float = 5.0) -> dict[str, float]:
        """``{name: µs of CPU per sample}`` once the window ended (waits up to ``timeout_s``; empty if it
        did not finish)."""
        self._thread.join(timeout_s)
        return {name: round(fraction / rate_hz * 1e6, 1) for name, fraction in self._cpu_fraction.items()}
