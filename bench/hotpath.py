"""The hot path: the loop over Zenoh against the bare bus, side by side in one run (``python -m bench.hotpath``).

- **bare chain** (:func:`bare_chain`): the pipeline's three hops with nothing else — this process puts a
  state-sized payload on ``bench/chain/state`` at the rate, an ``estimator`` hop answers each with an
  estimate-sized one, a ``controller`` hop (also subscribed to the state) answers each estimate with a
  setpoint-sized one, which this process takes (:mod:`bench.echo` ``chain``). All peers of a ``neso run
  hub``, exactly like the services; no decoding and no compute.
- **pipeline** (:func:`bench.bus_latency.pipeline`): ``neso up`` (hub, source, estimator, controller,
  recorder on) probed the same way: setpoint received − its state's stamp.
- **with the dashboard and 3 Chromium pages** (:func:`bench.dashboard.fly`) at 50 Hz.
- **fleet**: 1, 2, 4, 8 simulated vehicles on one bus at 50 Hz (each with its source, estimator, controller and
  recorder; isolated, shared, and shared with one estimator, controller and recorder process for all vehicles,
  ``--process-per-role``): loop p99 and misses over all vehicles, CPU per vehicle.

The chain and pipeline rows also give each process's CPU per sample (``cpu_us_per_sample``, over 80 % of the
measured time, :class:`bench.cpu.CpuWindow`): what the loop's CPU spends on each sample besides waiting.

A miss: a setpoint not received within one period of its state's stamp, or never (at the probe, a
process of its own); the dashboard rows also give the source's own count (a setpoint not there by its
next sample: what the vehicle sees). The figures go to
``out/bench.json`` under ``"bus"``, ``"fleet"``, ``"fleet_no_isolation"`` and ``"fleet_process_per_role"``
(p50/p99 in µs).
"""
from __future__ import annotations

import os
import struct
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from bench.cpu import CpuWindow, cpu_s
from bench.echo import CHAIN
from bench.payloads import payload
from cli.up import LOOP_ROLES, cpu_sets
from runtime.bus import BusConfig
from runtime.schema import SetpointMsg
from tests.busutil import REPO, children_of, free_port, neso, session, stop

COLUMNS = ("hot path", "samples", "p50 µs", "p99 µs", "max µs", "misses", "notes")
# fleets: how `neso up` runs them → their key in out/bench.json
# (a process per vehicle and role in the first two, explicitly: `neso up` shares processes from 3 vehicles on)
FLEET_VARIANTS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("--isolate", "--no-process-per-role"), "fleet"), (("--no-isolate", "--no-process-per-role"), "fleet_no_isolation"),
    (("--no-isolate", "--process-per-role"), "fleet_process_per_role"))


def summary(latency_s: list[float], misses: int, samples: int | None = None) -> dict:
    """``{"p50_us", "p99_us", "max_us", "misses", "samples"}`` of latencies in seconds."""
    x = np.asarray(latency_s, dtype=float) * 1e6
    if x.size == 0:
        return {"p50_us": None, "p99_us": None, "max_us": None, "misses": misses, "samples": samples or 0}
    return {"p50_us": round(float(np.percentile(x, 50)), 1), "p99_us": round(float(np.percentile(x, 99)), 1),
            "max_us": round(float(x.max()), 1), "misses": int(misses), "samples": int(samples or x.size)}


def row(name: str, s: dict, notes: str = "") -> tuple[str, ...]:
    def us(v):
        return "-" if v is None else f"{v:.0f}"
    return (name, str(s["samples"]), us(s["p50_us"]), us(s["p99_us"]), us(s["max_us"]), str(s["misses"]), notes)


def cpu_note(s: dict) -> str:
    """``CPU µs/sample: source 410, estimator 420, …`` of a row's ``cpu_us_per_sample`` (loop roles first)."""
    cpu = s.get("cpu_us_per_sample") or {}
    order = sorted(cpu, key=lambda name: (name not in LOOP_ROLES, name))
    return ("CPU µs/sample: " + ", ".join(f"{name} {cpu[name]:.0f}" for name in order)) if cpu else ""


def bare_chain(rate_hz: float, seconds: float, *, env: dict | None = None, warmup_s: float = 1.0,
               keep_samples: bool = False) -> dict:
    """The bare three-hop chain at ``rate_hz`` for ``seconds`` (after ``warmup_s``): :func:`summary`
    (with ``keep_samples``, also every latency in s under ``"latency_s"``)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, **(env or {}))
    hub_proc = neso("run", "hub", "--listen", hub, env=env)
    hops = {role: subprocess.Popen([sys.executable, "-m", "bench.echo", "chain", role, hub], cwd=REPO, env=env,
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            for role in ("estimator", "controller")}
    period_s = 1.0 / rate_hz
    received: dict[float, float] = {}  # state stamp → received
    lock, measuring = threading.Lock(), threading.Event()
    cpu = CpuWindow(lambda: {role: hop.pid for role, hop in hops.items()}, 0.8 * seconds, measuring)

    def on_setpoint(sample) -> None:
        now = time.monotonic()
        stamp = struct.unpack_from("<d", sample.payload.to_bytes())[0]
        with lock:
            received.setdefault(stamp, now)

    try:
        for hop in hops.values():
            if hop.stdout.readline().strip() != "ready":
                raise RuntimeError("a chain hop did not start")
        with session(BusConfig(connect=(hub,))) as s:
            s.declare_subscriber(CHAIN + "setpoint", on_setpoint)
            s.declare_subscriber(CHAIN + "estimate", lambda sample: None)  # as the recorder would
            pub = s.declare_publisher(CHAIN + "state", express=True)
            body = payload("state")[8:]
            sent: list[float] = []
            t_end = time.monotonic() + warmup_s + seconds
            next_s, t_measure = time.monotonic(), time.monotonic() + warmup_s
            while next_s < t_end:
                now = time.monotonic()
                if now >= t_measure:
                    sent.append(now)
                    measuring.set()
                pub.put(struct.pack("<d", now) + body)
                next_s += period_s
                delay = next_s - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            time.sleep(0.2)  # the last answers
    finally:
        for hop in hops.values():
            hop.stdin.close()
        for hop in hops.values():
            try:
                hop.wait(5.0)
            except subprocess.TimeoutExpired:
                hop.kill()
        stop(hub_proc)
    with lock:
        latency = [received[t] - t for t in sent if t in received]
    lost = len(sent) - len(latency)
    out = summary(latency, sum(x > period_s for x in latency) + lost, len(sent))
    out["cpu_us_per_sample"] = cpu.per_sample_us(rate_hz)
    return dict(out, latency_s=latency) if keep_samples else out


def pipeline(rate_hz: float, seconds: float, extra_args: tuple[str, ...] = (), env: dict | None = None,
             keep_samples: bool = False) -> dict:
    """``neso up`` at ``rate_hz`` with the recorder on (into a temporary folder), no trainer, no dashboard:
    :func:`summary` (with ``keep_samples``, also every latency in s under ``"latency_s"``)."""
    from bench.bus_latency import pipeline as fly

    with tempfile.TemporaryDirectory(prefix="neso-bench-rec-") as rec:
        run = fly(rate_hz, seconds, ("--no-trainer", "--recordings-dir", rec, *extra_args), env=env)
    out = summary(run.latency_s, run.probe_misses, len(run.latency_s) + run.probe_misses
                  - sum(x > 1.0 / rate_hz for x in run.latency_s))
    out["cpu_us_per_sample"] = run.cpu_us_per_sample
    return dict(out, latency_s=list(run.latency_s)) if keep_samples else out


def fleet(n_vehicles: int, seconds: float, rate_hz: float = 50.0, warmup_s: float = 4.0,
          extra_args: tuple[str, ...] = ()) -> dict:
    """``n_vehicles`` on one bus (``neso up --name …``: each its source, estimator, controller, recorder;
    no trainer, no dashboard) at ``rate_hz``: :func:`summary` over every vehicle's setpoints, plus
    ``cpu_per_vehicle`` (fraction of one CPU, every process of ``neso up`` but the launcher, over the
    measured ``seconds``)."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    period_s = 1.0 / rate_hz
    names = [f"v{i + 1}" for i in range(n_vehicles)]
    seen: dict[tuple[str, int], float] = {}  # (vehicle, seq) → latency
    lock, measuring = threading.Lock(), threading.Event()

    def on_setpoint(sample) -> None:
        received = time.monotonic()
        if measuring.is_set():
            msg = SetpointMsg.from_bytes(sample.payload.to_bytes())
            with lock:
                seen.setdefault((str(sample.key_expr).split("/")[1], msg.seq), received - msg.state_stamp_s)

    with tempfile.TemporaryDirectory(prefix="neso-bench-fleet-") as rec, session(BusConfig(connect=(hub,))) as s:
        s.declare_subscriber("neso/*/setpoint", on_setpoint)
        args = ["up", "--hub", hub, "--rate", f"{rate_hz:g}", "--scenario", "nominal_landing", "--mission", "hover",
                "--no-dashboard", "--no-trainer", "--recordings-dir", rec, *extra_args]
        for name in names:
            args += ["--name", name]
        proc = neso(*args)
        threading.Thread(target=lambda: proc.stdout.read(), daemon=True).start()
        try:
            time.sleep(warmup_s + 0.5 * n_vehicles)
            pids = children_of(proc.pid)
            cpu0, t0 = cpu_s(pids), time.monotonic()
            measuring.set()
            time.sleep(seconds)
            measuring.clear()
            cpu = (cpu_s(pids) - cpu0) / (time.monotonic() - t0)
        finally:
            stop(proc, timeout_s=20)
    with lock:
        by_vehicle: dict[str, list[int]] = {}
        for vehicle, seq in seen:
            by_vehicle.setdefault(vehicle, []).append(seq)
        latency = list(seen.values())
    expected = sum(max(seqs) - min(seqs) + 1 for seqs in by_vehicle.values())
    lost = expected - len(latency) + (n_vehicles - len(by_vehicle)) * round(seconds * rate_hz)
    out = summary(latency, sum(x > period_s for x in latency) + lost, expected)
    out.update(cpu_per_vehicle=round(cpu / n_vehicles, 3), vehicles_heard=len(by_vehicle))
    return out


def hotpath_rows(seconds: float, results: dict, fleet_sizes: tuple[int, ...] = (1, 2, 4, 8),
                 fleet_s: float = 20.0, pages: bool = True) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`, measured in this order in one run; ``results`` gets ``"bus"`` and ``"fleet"``."""
    from bench.dashboard import BROWSERS, fly

    bus = results.setdefault("bus", {})
    rows = []
    bus["bare_chain_500hz"] = bare_chain(500.0, seconds)
    rows.append(row("bare chain 500 Hz (3 hops, pipeline's payload sizes)", bus["bare_chain_500hz"],
                    "the floor; " + cpu_note(bus["bare_chain_500hz"])))
    for isolate in ("--no-isolate", "--isolate"):
        key = "pipeline_500hz" + ("" if isolate == "--isolate" else "_no_isolation")
        bus[key] = pipeline(500.0, seconds, (isolate,))
        rows.append(row(f"pipeline 500 Hz, recorder on, {isolate}", bus[key],
                        "state → setpoint at the probe; " + cpu_note(bus[key])))
    pipe, bare = bus["pipeline_500hz"]["p99_us"], bus["bare_chain_500hz"]["p99_us"]
    if pipe and bare:
        bus["pipeline_500hz"]["p99_over_bare_chain"] = round(pipe / bare, 2)
        rows.append(("target: pipeline p99 ≤ 1.5 × bare chain p99 (500 Hz)", "", "", "", "", "",
                     f"{pipe:.0f} / {bare:.0f} µs = {pipe / bare:.2f}×: {'met' if pipe <= 1.5 * bare else 'NOT met'}"))
    bus["pipeline_50hz"] = pipeline(50.0, seconds, ("--isolate",))
    rows.append(row("pipeline 50 Hz, recorder on, --isolate", bus["pipeline_50hz"]))
    if pages:
        _loop, other = cpu_sets(True)
        for isolate, browser_cpus, suffix in (("--no-isolate", (), "_no_isolation"), ("--isolate", (), "_browser_free"),
                                              ("--isolate", other, "")):
            key = "pipeline_50hz_dashboard_pages" + suffix
            where = f"Chromium on CPUs {list(browser_cpus)}" if browser_cpus else "Chromium on any CPU"
            try:
                try:
                    run = fly(seconds, browsers=BROWSERS, extra_args=(isolate,), browser_cpus=browser_cpus)
                except Exception:  # pages that did not load in 40 s on the busy machine: once more
                    run = fly(seconds, browsers=BROWSERS, extra_args=(isolate,), browser_cpus=browser_cpus)
            except Exception as exc:  # a page that never loaded: say so in the table, measure the rest
                bus[key] = {"failed": f"{type(exc).__name__}: {str(exc)[:160]}"}
                rows.append((f"pipeline 50 Hz + dashboard + {BROWSERS} pages, {isolate}, {where}", "", "", "", "", "",
                             f"FAILED: {bus[key]['failed']}"))
                continue
            lat = run["pipeline_s"]
            bus[key] = summary(lat, run["misses"], len(lat) + run["misses"] - sum(x > 0.02 for x in lat))
            bus[key]["source_misses"] = run["source_misses"]
            rows.append(row(f"pipeline 50 Hz + dashboard + {BROWSERS} pages, {isolate}, {where}", bus[key],
                            f"the source's own misses {run['source_misses']}; dashboard CPU "
                            f"{run.get('dashboard_cpu', float('nan')) * 100:.0f} % of a core"))
    for how, key in FLEET_VARIANTS:
        fleet_out = results.setdefault(key, {})
        for n in fleet_sizes:
            fleet_out[str(n)] = f = fleet(n, fleet_s, extra_args=how)
            rows.append(row(f"fleet of {n} at 50 Hz (one bus, {' '.join(how)})", f, f"CPU per vehicle "
                            f"{f['cpu_per_vehicle'] * 100:.0f} % of a core; heard {f['vehicles_heard']}/{n}"))
        zero = [n for n in fleet_sizes if fleet_out[str(n)]["misses"] == 0]
        fleet_out["largest_with_zero_misses"] = max(zero) if zero else 0
    return rows


def main(argv: list[str]) -> int:
    from bench.table import print_table, write_results

    quick = "--quick" in argv
    results: dict = {}
    rows = hotpath_rows(10.0 if quick else 60.0, results, fleet_s=10.0 if quick else 30.0)
    print_table(COLUMNS, rows)
    from bench.handlers import COLUMNS as HANDLER_COLUMNS, handler_rows

    print_table(HANDLER_COLUMNS, handler_rows(10.0 if quick else 20.0, results))  # into results["bus"]
    write_results(results)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
