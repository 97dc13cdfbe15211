"""A loop that stood still, and where it stood: a thread beside the loop notes the loop thread's innermost frames
once the loop has not beaten for ``threshold_s``; the loop's next beat reports how long it stood and where, or that
the watch itself was held as long (the whole process had no CPU: stopped, or starved by the machine).

A world that stops for a second is a fault a lab must hear about (PX4's simulator link times out, the gateway
commands hold), and the frames say whether the loop waited on something (a lock, a socket, a write) or the
process got no CPU at all (then the watch did not run either, and says so).
"""
from __future__ import annotations

import sys
import threading
import time
import traceback
from typing import Callable


class StallWatch:
    """Call :meth:`beat` once per loop iteration from the loop's thread; :meth:`close` when the loop ends."""

    def __init__(self, threshold_s: float, *, clock: Callable[[], float] = time.monotonic, frames: int = 3) -> None:
        self.threshold_s = threshold_s
        self.clock = clock
        self.frames = frames
        self._thread_id = threading.get_ident()
        self._beat_s = clock()
        self._where: str | None = None
        self._stop = threading.Event()
        threading.Thread(target=self._watch, name="stall-watch", daemon=True).start()

    def beat(self) -> tuple[float, str] | None:
        """(seconds since the last beat, where the loop was) if that exceeded ``threshold_s``, else None."""
        now = self.clock()
        stood_s, self._beat_s = now - self._beat_s, now
        where, self._where = self._where, None
        if stood_s <= self.threshold_s:
            return None
        return stood_s, where or "unknown: the watch beside it did not run either (the process had no CPU)"

    @property
    def noted(self) -> str | None:
        """Where the loop stands, once the watch has noted it standing still (None until then)."""
        return self._where

    def close(self) -> None:
        self._stop.set()

    def _watch(self) -> None:
        every_s = self.threshold_s / 4
        woke_s = self._beat_s  # from the watch's creation: a thread that starts late was held too (loaded run 42)
        while not self._stop.wait(every_s):
            now = self.clock()
            late_s, woke_s = now - woke_s - every_s, now
            if late_s > self.threshold_s / 2:  # this thread had no CPU either: where the loop is now says nothing
                if self._where is None:
                    self._where = f"unknown: the process had no CPU (the watch beside it woke {late_s:.2f} s late too)"
            elif self._where is None and now - self._beat_s > self.threshold_s:
                frame = sys._current_frames().get(self._thread_id)
                if frame is not None:
                    stack = traceback.extract_stack(frame)[-self.frames:]
                    self._where = " ← ".join(f"{f.name} ({f.filename.rsplit('/', 1)[-1]}:{f.lineno})"
                                             for f in reversed(stack))


class LateWake:
    """A periodic watchdog's guard against blaming others for its own process's lack of CPU: a wake more than
    ``late_periods`` periods after the one before means the process was held (stopped, or starved by the machine), and
    what the watchdog waits for may be queued behind it. :meth:`may_judge` says no to that one wake, so the queued
    callbacks run first, and yes to the next whatever its timing (a process starved for good still judges)."""

    def __init__(self, period_s: float, now_s: float, late_periods: float = 2.0) -> None:
        self.period_s = period_s
        self.late_periods = late_periods
        self._woke_s = now_s
        self._skipped = False

    def may_judge(self, now_s: float) -> bool:
        """Called at each wake, with the time (s, the clock ``now_s`` was of) it woke."""
        late = now_s - self._woke_s > self.late_periods * self.period_s
        self._woke_s = now_s
        self._skipped = late and not self._skipped
        return not self._skipped
