"""Zenoh subscriber handlers side by side: which one stalls every 256 messages (``python -m bench.handlers``).

One publisher puts a 206-byte payload (stamp, index) at 500 Hz; a subscriber in another process, both peers of
a ``neso run hub`` like the services, takes it with one of:

- ``callback``: a Python function (what :class:`runtime.node.Node` does) — zenoh-python runs it on a Python
  thread of its own fed by Zenoh's default FIFO channel (256 deep);
- ``zenoh_thread``: ``zenoh.handlers.Callback(fn, indirect=False)`` — on Zenoh's own receiving thread;
- ``fifo``: ``FifoChannel(256)``, a thread of ours calling ``recv()``;
- ``ring``: ``RingChannel(1)`` (latest value only), a thread of ours calling ``recv()``.

Latency = received − the publisher's stamp (one monotonic clock). ``phase_ratio``: the mean latency at the
worst index mod 256 over the median of those 256 means (≈ 1: no every-256 pattern).
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
import time

import numpy as np

KEY = "bench/handlers"
VARIANTS = ("callback", "zenoh_thread", "fifo", "ring")
COLUMNS = ("subscriber handler (500 Hz)", "samples", "p50 µs", "p99 µs", "p99.9 µs", "max µs", "every-256 phase")


def _subscribe(hub: str, variant: str, n: int) -> None:
    """The subscriber process: prints the latencies (µs, NaN for a lost one) as one line when done."""
    import zenoh

    from runtime.bus import BusConfig, open_session

    latency = np.full(n, np.nan)
    done = threading.Event()

    def on_sample(sample) -> None:
        now = time.monotonic()
        stamp, i = struct.unpack_from("<dq", sample.payload.to_bytes())
        if 0 <= i < n:
            latency[i] = (now - stamp) * 1e6
        if i == n - 1:
            done.set()

    with open_session(BusConfig(connect=(hub,))) as session:
        if variant == "callback":
            session.declare_subscriber(KEY, on_sample)
        elif variant == "zenoh_thread":
            session.declare_subscriber(KEY, zenoh.handlers.Callback(on_sample, indirect=False))
        else:
            channel = zenoh.handlers.FifoChannel(256) if variant == "fifo" else zenoh.handlers.RingChannel(1)
            handler = session.declare_subscriber(KEY, channel)
            threading.Thread(target=lambda: [on_sample(handler.recv()) for _ in iter(done.is_set, True)],
                             daemon=True).start()
        print("ready", flush=True)
        done.wait(n / 500.0 + 20.0)
    print(" ".join(f"{x:.1f}" for x in latency), flush=True)


def measure(variant: str, seconds: float, rate_hz: float = 500.0) -> dict:
    """One handler: ``{"p50_us", "p99_us", "p999_us", "max_us", "lost", "samples", "phase_ratio"}``."""
    from runtime.bus import BusConfig, open_session
    from tests.busutil import REPO, free_port, neso, stop

    n = int(seconds * rate_hz)
    hub = f"tcp/127.0.0.1:{free_port()}"
    hub_proc = neso("run", "hub", "--listen", hub)
    sub = subprocess.Popen([sys.executable, "-m", "bench.handlers", "subscribe", hub, variant, str(n)], cwd=REPO,
                           stdout=subprocess.PIPE, text=True, env=dict(os.environ))
    try:
        if sub.stdout.readline().strip() != "ready":
            raise RuntimeError(f"the {variant} subscriber did not start")
        with open_session(BusConfig(connect=(hub,))) as session:
            pub = session.declare_publisher(KEY, express=True)
            time.sleep(0.5)
            body, next_s = b"\0" * 190, time.monotonic()
            for i in range(-100, n):  # 100 to warm up
                pub.put(struct.pack("<dq", time.monotonic(), i) + body)
                next_s += 1.0 / rate_hz
                delay = next_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            out = sub.communicate(timeout=30.0)[0]
    finally:
        if sub.poll() is None:
            sub.kill()
        stop(hub_proc)
    x = np.array([float(v) for v in out.split()])
    got = x[~np.isnan(x)]
    by_phase = np.array([np.nanmean(x[k::256]) for k in range(256)])
    return {"p50_us": round(float(np.percentile(got, 50)), 1), "p99_us": round(float(np.percentile(got, 99)), 1),
            "p999_us": round(float(np.percentile(got, 99.9)), 1), "max_us": round(float(got.max()), 1),
            "lost": int(n - got.size), "samples": n,
            "phase_ratio": round(float(by_phase.max() / np.median(by_phase)), 2)}


def handler_rows(seconds: float, results: dict) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`; ``results["bus"]["subscriber_handlers"]`` gets each variant."""
    out = results.setdefault("bus", {}).setdefault("subscriber_handlers", {})
    rows = []
    for variant in VARIANTS:
        out[variant] = s = measure(variant, seconds)
        rows.append((variant, str(s["samples"] - s["lost"]), f"{s['p50_us']:.0f}", f"{s['p99_us']:.0f}",
                     f"{s['p999_us']:.0f}", f"{s['max_us']:.0f}", f"{s['phase_ratio']:.2f}×"))
    return rows


def main(argv: list[str]) -> int:
    from bench.table import print_table, write_results

    if argv[:1] == ["subscribe"]:
        _subscribe(argv[1], argv[2], int(argv[3]))
        return 0
    results: dict = {}
    print_table(COLUMNS, handler_rows(10.0 if "--quick" in argv else 20.0, results))
    write_results(results)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
