"""What the secure bus costs: plain beside secure, side by side in one run.

Per rate (500 and 50 Hz):

- **ping-pong**: Zenoh round trips between two processes (:mod:`bench.echo`), plain TCP beside
  mutual TLS with the graph's ACL on both sessions (this side the ``source``, the echo the
  ``estimator``): the transport's own cost, 2 deliveries, no compute.
- **pipeline**: ``neso up`` beside ``neso up --secure`` (every link mutual TLS, every session
  running the ACL on what it receives; the probe presents the ``operator`` certificate),
  measured as :func:`bench.bus_latency.pipeline` does (setpoint received at a probe − its
  state's stamp: 3 bus deliveries plus the estimator's and controller's compute).

Each measurement is repeated ``rounds`` times with the order alternating (plain first, then
secure first) and pooled, so neither mode always runs on a warmer or quieter machine. The
credentials come from a real ``neso secure init`` in a temporary directory.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile

import numpy as np

from bench.bus_latency import latency_stats, pipeline, zenoh_round_trips_s
from tests.busutil import secure_init

RATES_HZ = (500.0, 50.0)
MODES = ("plain", "secure")
COLUMNS = ("secure bus", "samples", "p50 µs", "p99 µs", "max µs", "notes")
LABELS = {"plain": "plain TCP", "secure": "TLS + ACL"}


def _summary(latency_s: list[float], bad: int, bad_name: str) -> dict:
    x = np.asarray(latency_s) * 1e6
    if x.size == 0:
        return {"p50_us": None, "p99_us": None, bad_name: bad, "samples": 0}
    p50, p99 = np.percentile(x, [50, 99])
    return {"p50_us": round(float(p50), 1), "p99_us": round(float(p99), 1), bad_name: bad, "samples": int(x.size)}


def _ratio_row(what: str, rate_hz: float, plain: dict, secure: dict) -> tuple[tuple[str, ...], dict]:
    if not plain["samples"] or not secure["samples"]:
        return (f"  {what} secure / plain at {rate_hz:g} Hz", "", "", "", "", "no samples"), {}
    ratios = {k: round(secure[k] / plain[k], 3) for k in ("p50_us", "p99_us")}
    return (f"  {what} secure / plain at {rate_hz:g} Hz", "", "", "", "",
            f"p50 {ratios['p50_us']:.2f}×, p99 {ratios['p99_us']:.2f}×"), ratios


def secure_rows(flight_s: float, floor_s: float, rounds: int, results: dict | None = None) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`. Per rate: Zenoh ping-pongs between two processes over TCP and
    over mutual TLS with the ACL (``floor_s`` each, ``rounds`` times, alternating which goes
    first), then the pipeline plain and ``--secure`` (``flight_s`` kept per flight, the same way),
    pooled over the rounds. ``results`` gets ``pingpong_<rate>hz[_secure]`` (``p50_us``,
    ``p99_us``, ``lost``, ``samples``), ``pipeline_<rate>hz[_secure]`` (… ``misses`` …) and the
    secure/plain ratios (``<what>_<rate>hz_ratio``)."""
    workdir = tempfile.mkdtemp(prefix="neso-bench-secure-")
    rows: list[tuple[str, ...]] = []
    out = results if results is not None else {}
    try:
        directory = secure_init(os.path.join(workdir, "secure"))
        for i, rate_hz in enumerate(RATES_HZ):
            n = round(floor_s * rate_hz)
            rtt = {m: [] for m in MODES}
            lost = {m: 0 for m in MODES}
            lat = {m: [] for m in MODES}
            misses = {m: 0 for m in MODES}
            for r in range(rounds):
                for mode in (MODES if (i + r) % 2 == 0 else MODES[::-1]):
                    got = zenoh_round_trips_s(rate_hz, n, secure_dir=directory if mode == "secure" else None)
                    rtt[mode] += got
                    lost[mode] += n - len(got)
            for r in range(rounds):
                for mode in (MODES if (i + r) % 2 == 0 else MODES[::-1]):
                    run = pipeline(rate_hz, flight_s, ("--no-record", "--no-trainer"),
                                   secure_dir=directory if mode == "secure" else None)
                    lat[mode] += run.latency_s
                    misses[mode] += run.probe_misses
            for what, data, bad, note in (("pingpong", rtt, lost, "lost"), ("pipeline", lat, misses, "misses")):
                summaries = {}
                for mode in MODES:
                    summaries[mode] = _summary(data[mode], bad[mode], note)
                    out[f"{what}_{rate_hz:g}hz" + ("_secure" if mode == "secure" else "")] = summaries[mode]
                    title = "Zenoh ping-pong (round trip)" if what == "pingpong" else "pipeline (state → setpoint)"
                    rows.append((f"{title} {rate_hz:g} Hz, {LABELS[mode]}", *latency_stats(data[mode]),
                                 f"{note} {bad[mode]}; {rounds} run(s)"))
                row, ratios = _ratio_row(what, rate_hz, summaries["plain"], summaries["secure"])
                rows.append(row)
                out[f"{what}_{rate_hz:g}hz_ratio"] = ratios
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    return rows


def record(section: str, data: dict, path: str = "out/bench.json") -> None:
    """Put ``data`` under ``section`` in ``path`` (a JSON object; other sections kept)."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    try:
        with open(path) as f:
            everything = json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        everything = {}
    everything[section] = data
    with open(path, "w") as f:
        json.dump(everything, f, indent=2)
        f.write("\n")
