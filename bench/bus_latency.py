"""End-to-end latency of the real pipeline against the bare floor, measured side by side.

- **pipeline**: ``neso up`` (hub, source in real time, estimator, controller: real processes) on
  a free hub port; a probe session in this process subscribes ``neso/<v>/setpoint`` and takes,
  per setpoint, (monotonic time received) − ``state_stamp_s``. The first :data:`DISCARD_S` of
  flight are discarded.
- **floor**: round trips of a ~200-byte msgpack payload (a :class:`StateMsg`) to an echo
  process (:mod:`bench.echo`), over Zenoh peers (multicast off, explicit ``tcp/127.0.0.1``
  endpoints, express publishers) and over bare UDP loopback, paced at the control rates.
- **sim step**: whether the simulator source keeps up with a 2 ms period.

Functions return seconds (names end in ``_s``); the table shows µs.
"""
from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import msgpack
import numpy as np

from bench.cpu import CpuWindow
from runtime.bus import BusConfig
from runtime.schema import HealthMsg, Keys, SetpointMsg, StateMsg
from tests.busutil import REPO, free_port, neso, roles_of, session, stop

RATES_HZ = (500.0, 50.0)
DISCARD_S = 2.0  # flight seconds discarded at the start (services linking up, observer warm-up)
TARGET_P99_US = 1000.0  # pipeline p99 at 500 Hz
TARGET_RATIO = 3.0  # pipeline p99 / Zenoh floor p99 at 500 Hz
STEP_BUDGET = 0.25  # sim tick p99 under this fraction of the 2 ms period: it keeps up
COLUMNS = ("bus latency", "samples", "p50 µs", "p99 µs", "max µs", "notes")
FOOTNOTE = (
    "pipeline = setpoint received at the probe − state stamp: state→estimator, estimate→controller (the\n"
    "controller also gets the state directly), setpoint→probe = 3 bus deliveries in series plus the estimator\n"
    "and controller compute. ping-pong = round trip, 2 deliveries (there and back), no compute. A deadline\n"
    "miss (probe): setpoint not received within one control period of the state's stamp, or never. source:\n"
    "the source's own count (setpoint not taken by its next sample) over the whole run, and after the first\n"
    "health report past the discarded start. Floor rows count round trips longer than one period."
)
_SOURCE_DONE = re.compile(r"\[source\] done: (\d+) samples, .*deadline misses (\d+)")
_SOURCE_STATUS = re.compile(r"sample (-?\d+), deadline misses (\d+)")


def latency_stats(latency_s, scale: float = 1e6, fmt: str = ".0f") -> tuple[str, str, str, str]:
    """(samples, p50, p99, max) of latencies in seconds as strings, in µs (``scale`` 1e3: ms)."""
    x = np.asarray(latency_s) * scale
    if x.size == 0:
        return "0", "-", "-", "-"
    p50, p99 = np.percentile(x, [50, 99])
    return str(x.size), f"{p50:{fmt}}", f"{p99:{fmt}}", f"{x.max():{fmt}}"


def _paced(rate_hz: float, n: int, send) -> None:
    """Call ``send()`` ``n`` times on a ``rate_hz`` schedule of the monotonic clock."""
    period_s = 1.0 / rate_hz
    next_s = time.monotonic()
    for _ in range(n):
        send()
        next_s += period_s
        delay_s = next_s - time.monotonic()
        if delay_s > 0:
            time.sleep(delay_s)


def _payload() -> bytes:
    """A state message stamped now (monotonic s): the pipeline's own ~200-byte payload."""
    return StateMsg(seq=1, stamp_s=time.monotonic(), t_s=1.0, pos_enu_m=(0.1, 0.2, 1.0), vel_enu_mps=(0.01, 0.02, 0.03),
                    roll_rad=0.01, pitch_rad=0.02, yaw_rad=0.03, source="sim").to_bytes()


def _echo(*args: str) -> tuple[subprocess.Popen, str]:
    """An echo process (:mod:`bench.echo`) and its first line of output."""
    proc = subprocess.Popen([sys.executable, "-m", "bench.echo", *args], cwd=REPO, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def _end(proc: subprocess.Popen) -> None:
    """Close an echo's stdin (it then exits cleanly); kill it if it has not within 5 s."""
    proc.stdin.close()
    try:
        proc.wait(5.0)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def zenoh_round_trips_s(rate_hz: float, n: int, secure_dir: str | None = None, variant: str = "acl",
                        port: int | None = None) -> list[float]:
    """``n`` Zenoh round trips (s) paced at ``rate_hz``, after the link answers a first ping
    (``secure_dir``: on a secure bus, this side the ``source``, the echo the ``estimator``, as
    :func:`bench.echo.secure_config` ``variant`` says; ``routed`` needs the hub's ``port``)."""
    from bench.echo import PING, PONG, SECURE_PING, SECURE_PONG, secure_config

    port = port or free_port()
    echo, line = _echo("zenoh", str(port), *((secure_dir, variant) if secure_dir else ()))
    config = BusConfig(connect=(f"tcp/127.0.0.1:{port}",), listen=())
    ping_key, pong_key = PING, PONG
    if secure_dir:
        config = secure_config(port, secure_dir, variant, echo=False)
        ping_key, pong_key = SECURE_PING, SECURE_PONG
    rtts: list[float] = []

    def on_pong(sample) -> None:
        now = time.monotonic()
        rtts.append(now - msgpack.unpackb(sample.payload.to_bytes())["stamp_s"])

    try:
        if line != "ready":
            raise RuntimeError(f"Zenoh echo did not start (said {line!r})")
        with session(config) as s:
            s.declare_subscriber(pong_key, on_pong)
            ping = s.declare_publisher(ping_key, express=True)
            deadline = time.monotonic() + 10.0
            while not rtts and time.monotonic() < deadline:
                _paced(rate_hz, 10, lambda: ping.put(_payload()))
            if not rtts:
                raise RuntimeError("Zenoh echo never answered")
            time.sleep(0.1)
            rtts.clear()
            _paced(rate_hz, n, lambda: ping.put(_payload()))
            time.sleep(0.1)  # the last pongs
    finally:
        _end(echo)
    return list(rtts)


def udp_round_trips_s(rate_hz: float, n: int) -> list[float]:
    """``n`` UDP loopback round trips (s) paced at ``rate_hz`` (a lost datagram is left out)."""
    echo, port = _echo("udp")
    rtts: list[float] = []
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.connect(("127.0.0.1", int(port)))
            sock.settimeout(1.0)

            def ping() -> None:
                sock.send(_payload())
                try:
                    data = sock.recv(65536)
                except TimeoutError:
                    return
                rtts.append(time.monotonic() - msgpack.unpackb(data)["stamp_s"])

            _paced(rate_hz, 10, ping)
            rtts.clear()
            _paced(rate_hz, n, ping)
    finally:
        _end(echo)
    return rtts


def sim_step_s(rate_hz: float, n: int = 5000) -> list[float]:
    """Wall time (s) of ``n`` sim source ticks at ``rate_hz``: ``SimSource.step()`` plus encoding
    the state and the truth, the work the source does each period besides sending."""
    from flight.source import SimSource, SourceConfig

    core = SimSource(SourceConfig(rate_hz=rate_hz), clock=time.monotonic)
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        state, truth = core.step()
        state.to_bytes(), truth.to_bytes()
        out.append(time.perf_counter() - t0)
    return out


@dataclass
class PipelineRun:
    """What the probe saw of one ``neso up`` flight (the discarded start left out).

    ``latency_s``: per setpoint, received at the probe − its state's stamp. ``probe_misses``:
    setpoints later than one period, or never received. ``achieved_hz``: state samples per
    second of the source's clock. ``source_misses``: the source's own count over the whole run
    (its ``done`` line; None if missing); ``source_misses_after``: the same since its first
    health report past the discarded start (None if none came)."""

    latency_s: list[float]
    probe_misses: int
    achieved_hz: float
    source_misses: int | None
    source_misses_after: int | None
    cpu_us_per_sample: dict[str, float]  # role → µs of CPU per sample over most of the measured flight


def pipeline(rate_hz: float, flight_s: float, extra_args: tuple[str, ...] = (),
             secure_dir: str | None = None, env: dict | None = None) -> PipelineRun:
    """Fly ``neso up`` at ``rate_hz`` for ``DISCARD_S + flight_s`` on a free hub port and probe it
    (``extra_args``: more ``neso up`` options; ``secure_dir``: ``--secure`` with the credentials
    there, the probe presenting the ``operator`` certificate)."""
    hub = f"{'tls' if secure_dir else 'tcp'}/127.0.0.1:{free_port()}"
    probe_bus = BusConfig(connect=(hub,))
    if secure_dir:
        from runtime.secure import Credentials

        probe_bus = BusConfig(connect=(hub,), listen=("tls/127.0.0.1:0",), credentials=Credentials(secure_dir, "operator"))
        extra_args = (*extra_args, "--secure", "--secure-dir", secure_dir)
    keys = Keys("uav1")
    arrivals: dict[int, tuple[float, float]] = {}  # seq → (state_stamp_s, received_s)
    status: list[tuple[int, int]] = []  # (sample, deadline misses) from the source's health
    discard_n = round(DISCARD_S * rate_hz)
    measuring = threading.Event()  # past the discarded start: the CPU window opens

    def on_setpoint(sample) -> None:
        received_s = time.monotonic()
        msg = SetpointMsg.from_bytes(sample.payload.to_bytes())
        arrivals.setdefault(msg.seq, (msg.state_stamp_s, received_s))
        if msg.seq >= discard_n:
            measuring.set()

    def on_health(sample) -> None:
        match = _SOURCE_STATUS.search(HealthMsg.from_bytes(sample.payload.to_bytes()).status)
        if match:
            status.append((int(match[1]), int(match[2])))

    with session(probe_bus) as probe:
        probe.declare_subscriber(keys.topic("setpoint"), on_setpoint)
        probe.declare_subscriber(keys.health("source"), on_health)
        run_s = DISCARD_S + flight_s
        proc = neso("up", "--hub", hub, "--rate", f"{rate_hz:g}", "--duration", f"{run_s:g}",
                    "--scenario", "nominal_landing", "--mission", "hover", "--no-dashboard", *extra_args,
                    env=None if env is None else dict(os.environ, **env))
        cpu = CpuWindow(lambda: roles_of(proc.pid), 0.8 * flight_s, measuring)
        try:
            output = proc.communicate(timeout=run_s + 30.0)[0]
        except subprocess.TimeoutExpired:
            output = stop(proc)
        finally:
            if proc.poll() is None:
                stop(proc)
    done = _SOURCE_DONE.search(output)
    n_samples = int(done[1]) if done else max(arrivals, default=-1) + 1
    kept = [arrivals[s] for s in range(discard_n, n_samples) if s in arrivals]
    latency_s = [received - stamp for stamp, received in kept]
    span_s = kept[-1][0] - kept[0][0] if len(kept) > 1 else 0.0
    after = [misses for sample, misses in status if sample >= discard_n]
    return PipelineRun(
        latency_s=latency_s,
        probe_misses=sum(lat > 1.0 / rate_hz for lat in latency_s) + (n_samples - discard_n - len(kept)),
        achieved_hz=(len(kept) - 1) / span_s if span_s > 0 else 0.0,
        source_misses=int(done[2]) if done else None,
        source_misses_after=int(done[2]) - after[0] if done and after else None,
        cpu_us_per_sample=cpu.per_sample_us(rate_hz),
    )


def _verdict(met: bool) -> str:
    return "target met" if met else "target missed"


def bus_latency_rows(flight_s: float, floor_s: float) -> list[tuple[str, ...]]:
    """Rows under :data:`COLUMNS`: the sim tick's cost at 500 Hz; per rate in :data:`RATES_HZ`,
    back to back, the Zenoh and UDP floors (``floor_s`` seconds of round trips each) and the
    pipeline (``flight_s`` seconds kept); then the two targets, each with its verdict."""
    step_s = sim_step_s(500.0)
    share = float(np.percentile(step_s, 99)) * 500.0  # p99 as a fraction of the 2 ms period
    verdict = "keeps up" if share < STEP_BUDGET else f"TOO SLOW (p99 ≥ {STEP_BUDGET:.0%} of the period)"
    rows: list[tuple[str, ...]] = [("sim source tick at 500 Hz (step + encode)", *latency_stats(step_s),
                                    f"p99 = {share:.1%} of the 2 ms period: {verdict}")]
    p99_us: dict[str, float] = {}
    for rate_hz in RATES_HZ:
        period_s = 1.0 / rate_hz
        n = round(floor_s * rate_hz)
        for name, measure in (("Zenoh", zenoh_round_trips_s), ("UDP", udp_round_trips_s)):
            rtt_s = measure(rate_hz, n)
            rows.append((f"{name} ping-pong {rate_hz:g} Hz (round trip)", *latency_stats(rtt_s),
                         f"> 1 period: {sum(r > period_s for r in rtt_s)}; lost: {n - len(rtt_s)}"))
            if rtt_s:
                p99_us[f"{name} {rate_hz:g}"] = float(np.percentile(rtt_s, 99) * 1e6)
        run = pipeline(rate_hz, flight_s, ("--no-record", "--no-trainer"))  # the control loop alone
        if run.latency_s:
            p99_us[f"pipeline {rate_hz:g}"] = float(np.percentile(run.latency_s, 99) * 1e6)
        source = "?" if run.source_misses is None else str(run.source_misses)
        if run.source_misses_after is not None:
            source += f" ({run.source_misses_after} after start)"
        rows.append((f"pipeline {rate_hz:g} Hz (state → setpoint at probe)", *latency_stats(run.latency_s),
                     f"misses: probe {run.probe_misses}, source {source}; rate {run.achieved_hz:.1f} Hz"))
    pipe, floor = p99_us.get("pipeline 500"), p99_us.get("Zenoh 500")
    rows.append(("target: pipeline p99 at 500 Hz ≤ 1 ms", "", "", "", "",
                 "no setpoints received: target missed" if pipe is None
                 else f"{pipe:.0f} µs: {_verdict(pipe <= TARGET_P99_US)}"))
    if pipe is not None and floor is not None:
        ratio = pipe / floor
        rows.append(("target: pipeline p99 / Zenoh ping-pong p99 at 500 Hz ≤ 3×", "", "", "", "",
                     f"{pipe:.0f} / {floor:.0f} µs = {ratio:.2f}×: {_verdict(ratio <= TARGET_RATIO)}"))
    return rows
