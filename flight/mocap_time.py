"""Motion-capture time: when each frame was captured, on this machine's clock, and how the stream is doing.

:class:`CaptureClock` maps Motive's clock onto this machine's monotonic clock. Each NatNet frame (3.0+) carries the
cameras' mid-exposure and its transmission in Motive's high-resolution ticks; ``arrival - transmit`` is the clock
offset plus the network's transit, so its minimum over the last ``window_s`` is the offset plus the shortest
transit (sub-millisecond on a wired link, unmeasurable without a synchronised clock and left in), and a frame's
capture here is ``mid_exposure + that minimum``. Neither Motive's processing time nor the network's jitter moves
it: a frame late by 200 ms keeps its capture time. The window follows a slow drift between the two clocks.

:class:`StreamStats` summarises the last ``window_s`` of frames: the frame rate (by Motive's frame times), the
latency from capture to arrival here (p50, p99), its jitter (p99 − p50), Motive's own latency (transmit −
mid-exposure), the longest gap between consecutive frames, and the frames that came out of order (overtaken by a
newer one: not used for a state; with 200 ms of jitter at 100 Hz three in four). The source puts
them in its health (``counters``), where preflight reads them. Pure: times in, numbers out (s unless named ms).
"""
from __future__ import annotations

import math
from collections import deque


class CaptureClock:
    """Motive's clock (s) → this machine's monotonic clock (s); see the module docstring."""

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self._offsets: deque[tuple[float, float]] = deque()  # (arrival_s, arrival - transmit), increasing offsets

    def capture_s(self, arrival_s: float, mid_exposure_s: float, transmit_s: float) -> float:
        """The frame's capture on this machine's clock; its arrival when the server gives no times (zeros)."""
        if mid_exposure_s <= 0.0 or transmit_s <= 0.0:
            return arrival_s
        offset = arrival_s - transmit_s
        while self._offsets and self._offsets[-1][1] >= offset:  # a later, smaller offset makes them irrelevant
            self._offsets.pop()
        self._offsets.append((arrival_s, offset))
        while self._offsets[0][0] < arrival_s - self.window_s:
            self._offsets.popleft()
        return mid_exposure_s + self._offsets[0][1]


class StreamStats:
    """The last ``window_s`` of a motion-capture stream (module docstring). Every frame counts in the figures; one
    not newer than the newest already seen (it came late, overtaken) is not to be used for a state."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._frames: deque[tuple[float, float, float, bool]] = deque()  # (capture, arrival, motive latency, in order)
        self.out_of_order = 0
        self._last_capture_s = -math.inf

    def add(self, capture_s: float, arrival_s: float, motive_latency_s: float) -> bool:
        """Count one frame; False for a frame not newer than the newest one (late, out of order: not to be used)."""
        in_order = capture_s > self._last_capture_s
        if in_order:
            self._last_capture_s = capture_s
        else:
            self.out_of_order += 1
        self._frames.append((capture_s, arrival_s, motive_latency_s, in_order))
        while self._frames and self._frames[0][1] < arrival_s - self.window_s:
            self._frames.popleft()
        return in_order

    def summary(self) -> dict[str, float]:
        """``mocap_rate_hz`` (every frame), ``mocap_in_order_share`` (of them, newer than all before: usable),
        ``mocap_latency_p50_ms``, ``mocap_latency_p99_ms``, ``mocap_jitter_ms``, ``motive_latency_ms``,
        ``mocap_gap_max_ms`` (between frames by capture), ``mocap_frames_out_of_order`` (since start); empty before
        two frames."""
        if len(self._frames) < 2:
            return {}
        captures = sorted(f[0] for f in self._frames)
        latency_ms = sorted((a - c) * 1e3 for c, a, _, _ in self._frames)
        motive_ms = sorted(m * 1e3 for _, _, m, _ in self._frames)
        span = captures[-1] - captures[0]
        p50, p99 = _quantile(latency_ms, 0.5), _quantile(latency_ms, 0.99)
        return {"mocap_rate_hz": (len(captures) - 1) / span if span > 0 else 0.0,
                "mocap_in_order_share": sum(f[3] for f in self._frames) / len(self._frames),
                "mocap_latency_p50_ms": p50, "mocap_latency_p99_ms": p99, "mocap_jitter_ms": p99 - p50,
                "motive_latency_ms": _quantile(motive_ms, 0.5),
                "mocap_gap_max_ms": max(b - a for a, b in zip(captures, captures[1:])) * 1e3,
                "mocap_frames_out_of_order": float(self.out_of_order)}


def _quantile(sorted_values: list[float], q: float) -> float:
    """The ``q`` quantile of an ascending list (nearest rank)."""
    return sorted_values[min(len(sorted_values) - 1, max(0, math.ceil(q * len(sorted_values)) - 1))]
