"""Watching one vehicle's streams from outside the graph (tools, demos, tests): every valid
message of some topics, in arrival order, with arrival times."""
from __future__ import annotations

import threading
import time

from runtime.schema import TOPICS, Keys, SchemaError


class Probe:
    """Subscribes ``topics`` of ``vehicle`` on ``session``; invalid payloads are ignored.
    ``messages[topic]`` and ``arrivals[topic]`` (``time.monotonic()`` s) grow together."""

    def __init__(self, session, vehicle: str = "uav1",
                 topics=("state", "truth", "estimate", "setpoint", "reference")) -> None:
        self.keys = Keys(vehicle)
        self.lock = threading.Lock()
        self.messages: dict[str, list] = {t: [] for t in topics}
        self.arrivals: dict[str, list[float]] = {t: [] for t in topics}
        self.subs = [session.declare_subscriber(self.keys.topic(t), self._handler(t)) for t in topics]

    def _handler(self, topic):
        cls = TOPICS[topic]

        def on_sample(sample):
            now = time.monotonic()
            try:
                msg = cls.from_bytes(sample.payload.to_bytes())
            except SchemaError:
                return
            with self.lock:
                self.messages[topic].append(msg)
                self.arrivals[topic].append(now)
        return on_sample

    def get(self, topic: str) -> list:
        with self.lock:
            return list(self.messages[topic])

    def wait_for(self, topic: str, predicate, timeout_s: float):
        """The newest message of ``topic`` (already there or arriving within ``timeout_s``)
        satisfying ``predicate``; :class:`TimeoutError` if none does."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for msg in reversed(self.get(topic)):
                if predicate(msg):
                    return msg
            time.sleep(0.01)
        raise TimeoutError(f"no {topic} message satisfying the condition within {timeout_s:g} s")

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
