"""What the secure bus costs: plain beside secure, side by side in one run.

Per rate (500 and 50 Hz):

- **ping-pong**: Zenoh round trips between two processes (:mod:`bench.echo`; this side the
  ``source``, the echo the ``estimator``), 2 deliveries, no compute: plain TCP; mutual TLS
  without the ACL; mutual TLS with the ACL in both sessions (what ``--secure`` does); and both
  as clients of a real secure hub (the design not chosen: every message through the hub's ACL,
  two links each way).
- **pipeline**: ``neso up`` beside ``neso up --secure`` (every link mutual TLS, every session
  running the ACL on what it receives; the probe presents the ``operator`` certificate),
  measured as :func:`bench.bus_latency.pipeline` does (setpoint received at a probe − its
  state's stamp: 3 bus deliveries plus the estimator's and controller's compute).

Each measurement is repeated ``rounds`` times with the order alternating (plain first, then
secure first) and pooled, so neither mode always runs on a warmer or quieter machine. The
credentials come from a real ``neso secure init`` in a temporary directory.
"""
from __future__ import annotations

import os
import shutil
import tempfile

import numpy as np

from bench.bus_latency import latency_stats, pipeline, zenoh_round_trips_s
from tests.busutil import free_port, neso, secure_init, stop

RATES_HZ = (500.0, 50.0)
PINGPONG_MODES = ("plain", "tls", "acl", "routed")
PIPELINE_MODES = ("plain", "secure")
COLUMNS = ("secure bus", "samples", "p50 µs", "p99 µs", "max µs", "notes")
LABELS = {"plain": "plain TCP", "tls": "mutual TLS, no ACL", "acl": "mutual TLS + ACL (--secure)",
          "routed": "both clients of a secure hub", "secure": "--secure (TLS + ACL)"}


def _summary(latency_s: list[float], bad: int, bad_name: str) -> dict:
    x = np.asarray(latency_s) * 1e6
    if x.size == 0:
        return {"p50_us": None, "p99_us": None, bad_name: bad, "samples": 0}
    p50, p99 = np.percentile(x, [50, 99])
    return {"p50_us": round(float(p50), 1), "p99_us": round(float(p99), 1), bad_name: bad, "samples": int(x.size)}


def _rotated(modes: tuple[str, ...], k: int) -> tuple[str, ...]:
    return modes[k % len(modes):] + modes[:k % len(modes)]


def _routed_round_trips_s(rate_hz: float, n: int, directory: str) -> list[float]:
    """Round trips between two clients of a real secure hub (``neso run hub --secure``)."""
    port = free_port()
    hub = neso("run", "hub", "--secure", "--secure-dir", directory, "--listen", f"tls/127.0.0.1:{port}")
    try:
        line = hub.stdout.readline()
        if "[hub] Zenoh router" not in line:
            raise RuntimeError(f"the hub did not start: {line!r}")
        return zenoh_round_trips_s(rate_hz, n, directory, "routed", port=port)
    finally:
        stop(hub)


def secure_rows(flight_s: float, floor_s: float, rounds: int, results: dict | None = None) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`. Per rate: Zenoh ping-pongs between two processes in each of
    :data:`PINGPONG_MODES` (``floor_s`` each, ``rounds`` times, the order rotated every round),
    then the pipeline plain and ``--secure`` (``flight_s`` kept per flight, the same way), pooled
    over the rounds. ``results`` gets ``pingpong_<rate>hz_<mode>`` (``p50_us``, ``p99_us``,
    ``lost``, ``samples``), ``pipeline_<rate>hz_<mode>`` (… ``misses`` …) and each mode's ratio to
    plain (``…_ratio``: p50 and p99)."""
    workdir = tempfile.mkdtemp(prefix="neso-bench-secure-")
    rows: list[tuple[str, ...]] = []
    out = results if results is not None else {}
    try:
        directory = secure_init(os.path.join(workdir, "secure"))
        for i, rate_hz in enumerate(RATES_HZ):
            n = round(floor_s * rate_hz)
            data = {("pingpong", m): [] for m in PINGPONG_MODES} | {("pipeline", m): [] for m in PIPELINE_MODES}
            bad = {key: 0 for key in data}
            for r in range(rounds):
                for mode in _rotated(PINGPONG_MODES, i + r):
                    if mode == "routed":
                        got = _routed_round_trips_s(rate_hz, n, directory)
                    else:
                        got = zenoh_round_trips_s(rate_hz, n, secure_dir=None if mode == "plain" else directory,
                                                  variant=mode)
                    data["pingpong", mode] += got
                    bad["pingpong", mode] += n - len(got)
            for r in range(rounds):
                for mode in _rotated(PIPELINE_MODES, i + r):
                    run = pipeline(rate_hz, flight_s, ("--no-record", "--no-trainer"),
                                   secure_dir=directory if mode == "secure" else None)
                    data["pipeline", mode] += run.latency_s
                    bad["pipeline", mode] += run.probe_misses
            for what, modes, bad_name in (("pingpong", PINGPONG_MODES, "lost"), ("pipeline", PIPELINE_MODES, "misses")):
                title = "Zenoh ping-pong (round trip)" if what == "pingpong" else "pipeline (state → setpoint)"
                plain = _summary(data[what, "plain"], bad[what, "plain"], bad_name)
                for mode in modes:
                    summary = _summary(data[what, mode], bad[what, mode], bad_name)
                    key = f"{what}_{rate_hz:g}hz_{mode}"
                    out[key] = summary
                    note = f"{bad_name} {bad[what, mode]}; {rounds} run(s)"
                    if mode != "plain" and summary["samples"] and plain["samples"]:
                        ratio = {k: round(summary[k] / plain[k], 3) for k in ("p50_us", "p99_us")}
                        out[f"{key}_ratio"] = ratio
                        note += f"; / plain: p50 {ratio['p50_us']:.2f}×, p99 {ratio['p99_us']:.2f}×"
                    rows.append((f"{title} {rate_hz:g} Hz, {LABELS[mode]}", *latency_stats(data[what, mode]), note))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return rows


def record(section: str, data: dict) -> None:
    """Put ``data`` under ``section`` in out/bench.json beside the run's other figures."""
    from bench.table import write_results

    write_results({section: data})