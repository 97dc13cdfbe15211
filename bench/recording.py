"""What recording costs and what a recording costs to use.

- **loop latency, recorder off beside on**: ``neso up`` at 50 Hz (real processes, real time) with
  ``--no-record`` and with the recorder writing into a temporary folder, probed as in
  :mod:`bench.bus_latency` (state stamp → setpoint received), in alternating rounds.
- **writer cost**: CPU seconds the recorder's writer spends per second of flight, on a synthetic
  flight written exactly as live (every topic at 50 Hz, a flush every 0.1 s).
- **.rrd → dataset for a 60 s flight**: a real 60 s flight (``neso up --lockstep``, the recorder
  on), its file as the recorder left it → :func:`recordings.dataset.load_training_set`; then the
  compaction the recorder does when a flight closes (``rerun rrd optimize``) and the same
  extraction from the compacted file.
"""
from __future__ import annotations

import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.bus_latency import latency_stats, pipeline
from tests.busutil import free_port, neso, stop

COLUMNS = ("recording", "samples", "p50 µs", "p99 µs", "max µs", "notes")


def latency_rows(flight_s: float, rounds: int, workdir: Path) -> list[tuple[str, ...]]:
    rows = []
    for r in range(rounds):
        for name, extra in (("off", ("--no-record",)), ("on", ("--recordings-dir", str(workdir / f"latency{r}")))):
            run = pipeline(50.0, flight_s, extra)
            rows.append((f"loop 50 Hz, recorder {name} (round {r + 1})", *latency_stats(run.latency_s),
                         f"misses: probe {run.probe_misses}, source {run.source_misses}; rate {run.achieved_hz:.1f} Hz"))
    return rows


def writer_cpu_s_per_flight_s(flight_s: float, workdir: Path) -> tuple[float, float]:
    """(CPU s per flight s, MB per flight s as written live) for a synthetic flight."""
    from recordings.writer import FlightWriter
    from tests.helpers import flight_messages

    msgs = flight_messages(round(flight_s * 50))
    per_flush = 25  # 5 topics × 5 samples: 0.1 s at 50 Hz
    path = workdir / "writer.rrd"
    w = FlightWriter(path, vehicle="uav1", flight="bench")
    started = time.process_time()
    for i, (channel, msg) in enumerate(msgs):
        w.add(channel, msg)
        if i % per_flush == per_flush - 1:
            w.flush()
    w.close()
    cpu = time.process_time() - started
    return cpu / flight_s, path.stat().st_size / 1e6 / flight_s


def real_flight(flight_s: float, workdir: Path) -> Path:
    """A real lockstep flight of ``flight_s`` recorded by the recorder; the file it wrote."""
    directory = workdir / "flight"
    proc = neso("up", "--hub", f"tcp/127.0.0.1:{free_port()}", "--lockstep", "--no-dashboard",
                "--duration", f"{flight_s:g}", "--mission", "hover", "--pathway", "neural_eso",
                "--recordings-dir", str(directory))
    try:
        out = proc.communicate(timeout=flight_s + 120)[0]
    except subprocess.TimeoutExpired:
        out = stop(proc)
    files = sorted(p for p in directory.glob("*.rrd") if not p.name.startswith("."))
    if proc.returncode != 0 or not files:
        raise RuntimeError(f"the recorded flight failed:\n{out[-3000:]}")
    return files[0]


def dataset_rows(flight_s: float, workdir: Path) -> list[tuple[str, ...]]:
    from recordings.dataset import load_training_set
    from recordings.reader import repair

    path = real_flight(flight_s, workdir)
    rows = []
    size_mb = path.stat().st_size / 1e6
    t0 = time.perf_counter()
    ts = load_training_set(path, "tdr")
    t_raw = time.perf_counter() - t0
    rows.append((f".rrd → TrainingSet, {flight_s:g} s flight, file as written", str(len(ts)), "", "", "",
                 f"{t_raw:.2f} s ({size_mb:.1f} MB)"))
    t0 = time.perf_counter()
    repair(path)
    t_compact = time.perf_counter() - t0
    rows.append(("compaction at flight end (rerun rrd optimize)", "", "", "", "",
                 f"{t_compact:.2f} s: {size_mb:.1f} → {path.stat().st_size / 1e6:.1f} MB"))
    t0 = time.perf_counter()
    ts2 = load_training_set(path, "tdr")
    t_compacted = time.perf_counter() - t0
    assert np.array_equal(ts.z, ts2.z) and np.array_equal(ts.y_mps2, ts2.y_mps2), "compaction changed the data"
    rows.append((f".rrd → TrainingSet, {flight_s:g} s flight, compacted", str(len(ts2)), "", "", "",
                 f"{t_compacted:.2f} s (same pairs, bit for bit)"))
    return rows


def recording_rows(quick: bool = False) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS` (~85 s; ``quick`` ~35 s)."""
    workdir = Path(tempfile.mkdtemp(prefix="neso-bench-rec-"))
    try:
        rows = latency_rows(flight_s=6.0 if quick else 10.0, rounds=1 if quick else 2, workdir=workdir)
        cpu, mb = writer_cpu_s_per_flight_s(10.0 if quick else 30.0, workdir)
        rows.append(("recorder writer cost (synthetic flight, flush every 0.1 s)", "", "", "", "",
                     f"{cpu * 100:.1f} % of a core; {mb:.2f} MB per flight second before compaction"))
        rows += dataset_rows(20.0 if quick else 60.0, workdir)
        return rows
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
