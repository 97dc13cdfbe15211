"""A watcher of every vehicle on the bus (the dashboard's presence): raw samples in, one-shot
queries out. Unlike :class:`runtime.node.Node` it belongs to no vehicle and publishes nothing;
its callbacks only enqueue (the caller decodes on its own thread, off Zenoh's)."""
from __future__ import annotations

import time
from collections import deque
from typing import Any

from runtime.bus import BusConfig, close_session, open_session
from runtime.schema import any_vehicle


class Observer:
    """Subscribes key expressions of every vehicle; samples land in :attr:`inbox` as
    ``(kind, key, payload_bytes, received_monotonic_s)``; liveliness changes as
    ``("alive", key, b"1" or b"", t)``. The inbox is bounded: when full the oldest go and
    :attr:`dropped` counts them (a watcher never holds the bus back)."""

    def __init__(self, bus: BusConfig, *, max_queued: int = 20000) -> None:
        self.session = open_session(bus)
        self.inbox: deque[tuple[str, str, bytes, float]] = deque(maxlen=max_queued)
        self.dropped = 0
        self._declared: list[Any] = []

    def _put(self, item) -> None:
        if len(self.inbox) == self.inbox.maxlen:
            self.dropped += 1
        self.inbox.append(item)

    def watch(self, suffix: str, kind: str) -> None:
        """Enqueue every sample on ``neso/*/<suffix>`` as ``kind``."""
        def on_sample(sample) -> None:
            self._put((kind, str(sample.key_expr), sample.payload.to_bytes(), time.monotonic()))
        self._declared.append(self.session.declare_subscriber(any_vehicle(suffix), on_sample))

    def watch_alive(self) -> None:
        """Enqueue liveliness tokens of every service of every vehicle (present ones first)."""
        import zenoh

        def on_sample(sample) -> None:
            alive = sample.kind == zenoh.SampleKind.PUT
            self._put(("alive", str(sample.key_expr), b"1" if alive else b"", time.monotonic()))
        self._declared.append(self.session.liveliness().declare_subscriber(any_vehicle("alive/*"), on_sample,
                                                                           history=True))

    def drain(self, limit: int = 100000) -> list[tuple[str, str, bytes, float]]:
        out = []
        while self.inbox and len(out) < limit:
            out.append(self.inbox.popleft())
        return out

    def close(self) -> None:
        close_session(self.session, self._declared)
