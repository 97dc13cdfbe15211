"""The pacing rule of a periodic loop that can fall behind (the simulated world's, the bus test's publisher)."""
from __future__ import annotations


def next_wait(tick_s: float, period_s: float, now_s: float) -> tuple[float, float]:
    """For a loop whose next sample is due at ``tick_s`` (s, monotonic): (the wait until then, s, ≤ 0 when late;
    the tick to count the next period from). More than ``period_s`` behind, the loop goes on from ``now_s`` instead
    of catching up: a late sample is caught up, a stall is not turned into a burst of samples back to back."""
    delay_s = tick_s - now_s
    return delay_s, (now_s if delay_s < -period_s else tick_s)
