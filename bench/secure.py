"""What the secure bus costs the loop: ``neso up`` plain beside ``neso up --secure``, one run.

Per rate (50 and 500 Hz), two flights back to back on free hub ports, measured exactly as
:func:`bench.bus_latency.pipeline` does (setpoint received at a probe − its state's stamp; 3
bus deliveries plus the estimator's and controller's compute; the first seconds discarded):
plain TCP peers, and the secure bus (every link mutual TLS, every session running the graph's
ACL on what it receives; the probe presents the ``operator`` certificate). The order alternates
between the rates (plain first at 500 Hz, secure first at 50 Hz) so neither always runs on a
warmer machine. Credentials come from a real ``neso secure init`` in a temporary directory.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile

import numpy as np

from bench.bus_latency import latency_stats, pipeline
from tests.busutil import secure_init

RATES_HZ = (500.0, 50.0)
COLUMNS = ("secure bus", "samples", "p50 µs", "p99 µs", "max µs", "notes")


def secure_rows(flight_s: float, results: dict | None = None) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`; ``results`` (if given) gets ``pipeline_<rate>hz[_secure]`` →
    ``{p50_us, p99_us, misses, samples}`` and ``p99_ratio_<rate>hz``."""
    workdir = tempfile.mkdtemp(prefix="neso-bench-secure-")
    rows: list[tuple[str, ...]] = []
    try:
        directory = secure_init(os.path.join(workdir, "secure"))
        for i, rate_hz in enumerate(RATES_HZ):
            order = ("plain", "secure") if i % 2 == 0 else ("secure", "plain")
            p99: dict[str, float] = {}
            for mode in order:
                run = pipeline(rate_hz, flight_s, ("--no-record", "--no-trainer"),
                               secure_dir=directory if mode == "secure" else None)
                name = f"pipeline_{rate_hz:g}hz" + ("_secure" if mode == "secure" else "")
                lat_us = np.asarray(run.latency_s) * 1e6
                if lat_us.size:
                    p99[mode] = float(np.percentile(lat_us, 99))
                    if results is not None:
                        results[name] = {"p50_us": round(float(np.percentile(lat_us, 50)), 1),
                                         "p99_us": round(p99[mode], 1), "misses": run.probe_misses,
                                         "samples": int(lat_us.size)}
                label = "TLS + ACL" if mode == "secure" else "plain TCP"
                rows.append((f"pipeline {rate_hz:g} Hz, {label}", *latency_stats(run.latency_s),
                             f"misses {run.probe_misses}; rate {run.achieved_hz:.1f} Hz"))
            if len(p99) == 2:
                ratio = p99["secure"] / p99["plain"]
                if results is not None:
                    results[f"p99_ratio_{rate_hz:g}hz"] = round(ratio, 3)
                rows.append((f"  secure / plain p99 at {rate_hz:g} Hz", "", "", "", "",
                             f"{p99['secure']:.0f} / {p99['plain']:.0f} µs = {ratio:.2f}×"))
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
