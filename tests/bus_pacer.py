"""A 50 Hz publisher for tests/process/test_bus_under_load.py: ``python -m tests.bus_pacer MAX_S EP:BATCHES …``.

For each ``endpoint:batches`` pair it opens a session (``runtime.bus.BusConfig`` with that many transmit batches per
priority, connecting to the endpoint) and, every 20 ms, puts one 200-byte message on each of ``TOPICS`` — the
sample number first, as 8 ASCII digits — on every session in turn, so that the sessions see the same load.
Prints ``ready`` once its publishers are declared, paces from the first line on stdin until a second line (or
``MAX_S``), then prints ``sent N reanchored R``: samples 1…N went out; R times the loop was more than a period
behind and, like the product's world loop, went on from now rather than catching up.
"""
from __future__ import annotations

import sys
import threading
import time

from runtime.bus import BusConfig, open_session, publisher_qos
from runtime.pacing import next_wait
from runtime.schema import Keys

#: The streams one sample puts back to back: the loop's own and the ones that travel beside it.
TOPICS = ("state", "truth", "estimate", "setpoint", "reference", "telemetry")
KEYS = Keys("pacer")
PERIOD_S = 0.02


def main(seconds: float, pairs: list[str]) -> None:
    sessions, publishers = [], []
    for pair in pairs:
        endpoint, batches = pair.rsplit(":", 1)
        config = BusConfig(connect=(endpoint,), listen=(), tx_queue_batches=int(batches))
        session = open_session(config)
        sessions.append(session)
        publishers.append([session.declare_publisher(KEYS.topic(t), **publisher_qos(config, t)) for t in TOPICS])
    print("ready", flush=True)
    sys.stdin.readline()
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.readline(), stop.set()), daemon=True).start()
    next_tick, seq, reanchored = time.monotonic(), 0, 0
    while seq < int(seconds / PERIOD_S) and not stop.is_set():
        seq += 1
        payload = b"%08d" % seq + b"x" * 192
        for pubs in publishers:
            for pub in pubs:
                pub.put(payload)
        # the product's world loop's rule: more than a period behind, it goes on from now instead of putting the
        # missed samples back to back, a burst no product loop sends
        due = next_tick + PERIOD_S
        delay, next_tick = next_wait(due, PERIOD_S, time.monotonic())
        reanchored += next_tick != due
        if delay > 0:
            time.sleep(delay)
    time.sleep(0.5)
    print(f"sent {seq} reanchored {reanchored}", flush=True)
    for session in sessions:
        session.close()


if __name__ == "__main__":
    main(float(sys.argv[1]), sys.argv[2:])
