"""What a flood of malformed payloads costs the real-time loop (``python -m bench.flood``, ~35 s; quick ~25 s).

A ``neso up`` hover at 50 Hz (real processes, real time, the recorder on), flown in 1 s windows, quiet and flooded
in turn as the live-flight test floods it (tests/process/test_live_flight.py): in each flooded window 2000
malformed payloads per key on state, setpoint and estimate, sent from a session whose own subscribers never see
them. Per kind of window: the samples flown past the controller's deadline (on its local ESO), the estimate's
latency (estimate stamp − state stamp, one monotonic clock) and each process's CPU, and so the CPU one rejected
payload costs each service. The test judges the flight in its own samples; this is where the wall clock is judged.
Target: the flooded windows miss no more of the controller's deadlines than the quiet ones beyond 5 % of their
samples (what a machine with the flood's CPU to spare gives).
"""
from __future__ import annotations

import random
import sys
import tempfile
import time

import numpy as np

from bench.cpu import cpu_s
from runtime.schema import Keys
from tests.busutil import NesoUp, flood_windows, free_port, peer, roles_of
from tests.helpers import malformed_payloads

COLUMNS = ("flood (50 Hz hover, 1 s windows)", "samples", "past deadline", "estimate p50 ms", "p99 ms", "max ms",
           "CPU % of a core: source / estimator / controller / recorder")
PER_KEY_PER_S = 2000
TOPICS = ("state", "setpoint", "estimate")
ROLES = ("source", "estimator", "controller", "recorder")
MISS_MARGIN = 0.05  # of the flooded samples: the target


def flood_rows(windows: int, results: dict) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS` for ``windows`` 1 s windows (half of them flooded); figures into ``results``."""
    keys = Keys("uav1")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    workdir = tempfile.mkdtemp(prefix="neso-bench-flood-")
    flight = NesoUp("--scenario", "nominal_landing", "--mission", "hover", "--hub", endpoint, "--no-dashboard",
                    "--no-trainer", "--recordings-dir", f"{workdir}/recordings", bus=peer(endpoint),
                    topics=("state", "estimate", "setpoint"), workdir=workdir)
    try:
        flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > 50, 30.0)
        rng = random.Random(1)
        per_key = (windows // 2) * PER_KEY_PER_S  # every flooded window's, in all
        payloads = {t: malformed_payloads(t, flight.probe.get(t)[-1].to_bytes(), per_key, rng) for t in TOPICS}
        pids = {r: pid for r, pid in roles_of(flight.proc.pid).items() if r in ROLES}

        edges: list[tuple[float, dict[str, float]]] = []  # (monotonic s, each process's CPU s) at every window's
        # start and end, in order

        def latest_seq() -> int:  # flood_windows asks at each window's start and end: the CPU is read there too
            edges.append((time.monotonic(), {r: cpu_s([pid]) for r, pid in pids.items()}))
            states = flight.probe.get("state")
            return states[-1].seq if states else -1

        spans = flood_windows(flight.s, keys, payloads, latest_seq, windows, PER_KEY_PER_S)
        flight.probe.wait_for("estimate", lambda m: m.seq >= spans["flood"][-1][1] - 1, 5.0)
        state_s = {m.seq: m.stamp_s for m in flight.probe.get("state")}
        est_s = {m.seq: m.stamp_s for m in flight.probe.get("estimate")}
        flown = {m.seq for m in flight.probe.get("setpoint") if m.estimate_source == "estimator"}
    finally:
        flight.close()
    cpu_by_kind = _cpu_by_kind(edges)
    rows, found = [], {}
    for kind, ws in spans.items():
        seqs = [k for first, end in ws for k in range(first, end)]
        latency_ms = np.array([est_s[k] - state_s[k] for k in seqs if k in est_s and k in state_s]) * 1e3
        missed = sum(k not in flown for k in seqs)
        cpu = cpu_by_kind[kind]
        found[kind] = {"samples": len(seqs), "past_deadline": missed, "unanswered": sum(k not in est_s for k in seqs),
                       "estimate_latency_ms": {"p50": round(float(np.percentile(latency_ms, 50)), 2),
                                               "p99": round(float(np.percentile(latency_ms, 99)), 2),
                                               "max": round(float(latency_ms.max()), 2)},
                       "cpu_percent": {r: round(cpu[r] * 100, 1) for r in ROLES if r in cpu}}
        rows.append((f"{kind} windows ({len(ws)} × 1 s)", str(len(seqs)), str(missed),
                     f"{np.percentile(latency_ms, 50):.1f}", f"{np.percentile(latency_ms, 99):.1f}",
                     f"{latency_ms.max():.1f}", " / ".join(f"{cpu.get(r, 0.0) * 100:.0f}" for r in ROLES)))
    per_payload_us = {r: round((cpu_by_kind["flood"][r] - cpu_by_kind["quiet"][r]) / (PER_KEY_PER_S * _RECEIVED[r])
                               * 1e6, 1) for r in ROLES if r in cpu_by_kind["flood"]}
    target = found["quiet"]["past_deadline"] + MISS_MARGIN * found["flood"]["samples"]
    met = found["flood"]["past_deadline"] <= target
    rows.append(("CPU per rejected payload (µs)", "", "", "", "", "",
                 " / ".join(f"{per_payload_us.get(r, float('nan')):.0f}" for r in ROLES)))
    rows.append((f"target: flooded past deadline ≤ quiet + {MISS_MARGIN:.0%} of the flooded samples", "",
                 f"{found['flood']['past_deadline']} ≤ {target:.1f}", "", "", "", "met" if met else "NOT MET"))
    results["flood"] = {**found, "cpu_us_per_rejected_payload": per_payload_us, "payloads_per_key_per_s": PER_KEY_PER_S,
                        "target_met": met}
    return rows


#: how many of the flooded keys each process subscribes to (a window's payloads reach it once per key)
_RECEIVED = {"source": 1, "estimator": 2, "controller": 2, "recorder": 3}


def _cpu_by_kind(edges: list[tuple[float, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Per kind of window (quiet first, then in turn), each process's CPU as a fraction of a core over those
    windows, from (monotonic s, its CPU s) at every window's start and end (``edges``: start, end, start, end, …)."""
    cpu_s: dict[str, dict[str, float]] = {"quiet": {}, "flood": {}}
    wall_s = {"quiet": 0.0, "flood": 0.0}
    for w in range(len(edges) // 2):
        (t0, start), (t1, end) = edges[2 * w], edges[2 * w + 1]
        kind = "flood" if w % 2 else "quiet"
        wall_s[kind] += t1 - t0
        for role in end:
            cpu_s[kind][role] = cpu_s[kind].get(role, 0.0) + end[role] - start[role]
    return {kind: {role: used / wall_s[kind] for role, used in by_role.items()} for kind, by_role in cpu_s.items()}


def print_flood(quick: bool) -> None:
    """The table (20 windows; ``quick`` 10) and ``"flood"`` in ``out/bench.json``."""
    from bench.table import print_table, write_results

    found: dict = {}
    print_table(COLUMNS, flood_rows(10 if quick else 20, found))
    write_results(found)


if __name__ == "__main__":
    print_flood("--quick" in sys.argv)
