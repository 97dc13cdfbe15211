"""The bus on a loaded machine: a 50 Hz loop's publisher drops at most a fifth of what Zenoh's default drops.

Reproduces the setpoints missing in CI (test_secure_bus, 4 of 751 at the probe): Zenoh's puts are express and
dropped when their priority's transmit queue is still full 1 ms later. With Zenoh's default 2 batches a sample's
puts back to back were dropped whenever the publisher's transmit thread was not scheduled within that millisecond.
The publisher and two busy loops run at nice 10 (the load is theirs, not the other tests'); Zenoh's default queue
flies beside the product's one, in the same process and loop, so the load that drops one is shown to be there: the
publisher paces until Zenoh's default has dropped puts of ``REPRODUCED`` samples (at least ``MIN_S``, at most
``MAX_S``). It paces as the product's world loop does: more than a period behind, it goes on from now. It used to
put the missed samples back to back, a burst no product loop sends, and each stall of the whole process (CI, 41a1901:
38 samples lost in runs of three, 20-22, 52-54, …) overflowed even 16 batches.
"""
from __future__ import annotations

import subprocess
import sys
import threading
import time

import pytest

from runtime.bus import BusConfig, open_session
from tests.bus_pacer import KEYS, TOPICS
from tests.busutil import REPO, free_port

pytestmark = pytest.mark.process

MIN_S, MAX_S = 5.0, 40.0
REPRODUCED = 3
ZENOH_DEFAULT_BATCHES = 2


class Listener:
    """A session listening on a free port; the sample numbers it got per topic."""

    def __init__(self):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = open_session(BusConfig(connect=(), listen=(self.endpoint,)))
        self.got: dict[str, set[int]] = {t: set() for t in TOPICS}
        self.lock = threading.Lock()
        self.sub = self.session.declare_subscriber(f"{KEYS.prefix}/**", self._on_sample)

    def _on_sample(self, sample) -> None:
        topic = str(sample.key_expr).rsplit("/", 1)[1]
        with self.lock:
            self.got[topic].add(int(sample.payload.to_bytes()[:8]))

    def lost(self, samples: int) -> dict[str, list[int]]:
        """Per topic, the sample numbers up to ``samples`` that never arrived."""
        with self.lock:
            return {t: sorted(set(range(1, samples + 1)) - got) for t, got in self.got.items()}

    def lost_samples(self) -> int:
        """Samples with a topic missing, among those before the newest one any topic brought (a live count)."""
        with self.lock:
            newest = max((max(got) for got in self.got.values() if got), default=0)
        return len(set().union(*self.lost(newest - 1).values()))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def test_a_50_hz_loop_drops_a_fifth_at_most_of_what_zenohs_default_queue_drops_beside_it_on_a_loaded_machine():
    ours, default = Listener(), Listener()
    busy = [subprocess.Popen(["nice", "-n", "10", sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    pacer = subprocess.Popen(["nice", "-n", "10", sys.executable, "-m", "tests.bus_pacer", str(MAX_S),
                              f"{ours.endpoint}:{BusConfig().tx_queue_batches}",
                              f"{default.endpoint}:{ZENOH_DEFAULT_BATCHES}"],
                             cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert pacer.stdout.readline().strip() == "ready"
        pacer.stdin.write("go\n")
        pacer.stdin.flush()
        started = time.monotonic()
        while pacer.poll() is None and not (time.monotonic() - started >= MIN_S
                                            and default.lost_samples() >= REPRODUCED):
            time.sleep(0.5)
        if pacer.poll() is None:
            pacer.stdin.write("stop\n")
            pacer.stdin.flush()
        last = pacer.stdout.readline().strip()
        assert pacer.wait(timeout=30) == 0 and last.startswith("sent "), last
    finally:
        for proc in (pacer, *busy):
            proc.kill()
            proc.wait()
        for listener in (ours, default):
            listener.close()
    samples, reanchored = int(last.split()[1]), int(last.split()[3])
    lost_ours, lost_default = ours.lost(samples), default.lost(samples)
    dropped_default = sorted(set().union(*lost_default.values()))
    print(f"{samples} samples × {len(TOPICS)} topics under load: {BusConfig().tx_queue_batches} batches lost "
          f"{sum(map(len, lost_ours.values()))} puts, Zenoh's default {ZENOH_DEFAULT_BATCHES} lost "
          f"{sum(map(len, lost_default.values()))} puts in {len(dropped_default)} samples; the loop was more than a "
          f"period behind {reanchored} times")
    assert dropped_default, "the load did not reproduce the drops: Zenoh's default queue lost nothing beside ours"
    # none in most runs, but not always: with the publisher's whole process stopped 50 ms every 0.7 s and three busy
    # cores beside it, 1 sample against Zenoh's 146 (its transmit thread starved while its loop went on)
    dropped_ours = sorted(set().union(*lost_ours.values()))
    assert len(dropped_ours) <= len(dropped_default) / 5, (dropped_ours[:10], len(dropped_default))
