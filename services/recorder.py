"""``recorder``: every message of one vehicle into one ``.rrd`` per flight (see ``recordings/``).

Zenoh callbacks only enqueue the raw payload (a bounded queue: when full, messages are counted
as ``dropped``, never waited for); one writer thread decodes, decides flights and writes with
:class:`recordings.writer.FlightWriter`, flushing every ``flush_period_s`` (0.1 s) so a crash
loses at most that much. The control loop never waits for the recorder.

Flights (:class:`FlightTracker`, pure): a flight is the time the vehicle *flies*, decided on one
signal at a time and debounced, so it never flaps. With vehicle telemetry on the bus (a PX4
through the gateway, heard within ``telemetry_timeout_s``) the vehicle's own word decides:
flying = armed *and* in the air. Without it (the direct simulator, mocap without a gateway) the
controller's does: flying = thrust commanded (it commands none while idle or landed). A flight
starts when the signal has said "flying" for ``start_after_s`` without a break and ends when it
has said "not flying" for ``idle_end_s``; also when the source restarts (``seq`` goes back) or
falls silent for ``silence_end_s``. The operator can ``start`` and ``stop`` a recording by
command (``neso cmd recorder start|stop``); after a ``stop`` in the air, the next flight starts
after the next landing. The last ``preroll_s`` before the start is written too (it covers the
take-off the debounce waited through).

A recorder restarted during a flight (after a crash) continues it: it finds the flight it was
writing in ``<dir>/.<vehicle>.active.json`` and writes the next segment (``<flight>.seg<k>.rrd``,
same Rerun recording id) if that file was written within ``resume_window_s`` and the source's
samples carry on from it.
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import subprocess
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from recordings.layout import RECORDINGS_DIR
from runtime.graph import role as graph_role
from runtime.options import add_options, config_from_options, option
from runtime.schema import Message, RecordingMsg, SchemaError

# at a stop, the writer's time to finish the flight's file: the launcher's grace for this role less 2 s for the rest
WRITER_FINISH_S = graph_role("recorder").stop_grace_s - 2.0


@dataclass(frozen=True)
class RecorderConfig:
    directory: str = option(RECORDINGS_DIR, flag="--recordings-dir", help="where flights are written")
    flush_period_s: float = option(0.1, flag="--flush-period", unit="s", help="between flushes to disk (≤ 0.2)")
    params_timeout_s: float = 1.0  # per service, all asked at once at a flight's start (answers take ~1 ms)
    preroll_s: float = 2.0  # > start_after_s: the take-off the debounce waited through is in the file
    # flying this long without a break starts a flight, not flying this long ends it: on the wall clock (arrival) or
    # the flight's own (its states' t_s), whichever is further on: a lockstep world runs faster than the wall (a 3 s
    # flight once ended before 0.5 s of the wall had passed, and nothing was recorded)
    start_after_s: float = 0.5
    idle_end_s: float = 2.0
    telemetry_timeout_s: float = 2.0  # vehicle telemetry younger than this decides "flying" (else the setpoints)
    silence_end_s: float = 2.0
    resume_window_s: float = 10.0
    auto: bool = option(True, flag="--manual", help="record only between `neso cmd recorder start` and stop "
                                                    "(default: flights start and end by themselves)")
    queue_size: int = 50_000
    status_period_s: float = 1.0
    compact: bool = True  # rewrite a closed file with `rerun rrd optimize` (merged chunks, footer)
    nice: int = option(5, help="scheduling niceness added to the recorder (0: none)")


@dataclass
class Decision:
    start: str = ""  # reason to start a flight now
    stop: str = ""  # reason to end the current one (before a start, when both)


@dataclass
class FlightTracker:
    """Pure flight-boundary logic: feed it messages in arrival order (and :meth:`tick` it), act on
    its decisions. Times are the caller's monotonic seconds (arrival), and the flight's own from its states' ``t_s``."""

    config: RecorderConfig
    recording: bool = False
    manual: bool = False
    suppressed: bool = False  # the operator stopped in the air: wait for a landing
    last_seq: int = -1
    last_state_s: float = -1.0
    first_seq: int = -1
    flying: bool = False  # the signal's current value ...
    since_s: float | None = None  # ... and since when it has had it without a break (arrival) ...
    since_flight_t_s: float | None = None  # ... and in the flight's time
    flight_t_s: float | None = None  # the newest state's t_s
    why: str = ""  # what the signal is ("armed and in the air (telemetry)", ...)
    telemetry_s: float | None = None  # arrival of the newest telemetry

    def on_message(self, channel: str, msg: Message, now_s: float) -> Decision:
        d = Decision()
        if channel == "state":
            if self.recording and not self.manual and 0 <= msg.seq < self.last_seq:
                d.stop = f"the source restarted (sample {msg.seq} after {self.last_seq})"
                self._stopped()
            self.last_seq, self.last_state_s = msg.seq, now_s
            if self.since_s is not None and (self.since_flight_t_s is None or msg.t_s < self.flight_t_s):
                self.since_flight_t_s = msg.t_s  # the first state since the signal, or the flight's clock restarted
            self.flight_t_s = msg.t_s
        elif channel == "telemetry":
            self.telemetry_s = now_s
            flying = msg.armed and msg.in_air
            self._signal(flying, "armed and in the air (telemetry)" if flying else
                         f"{'armed' if msg.armed else 'disarmed'}, {'in the air' if msg.in_air else 'on the ground'} "
                         "(telemetry)", now_s)
        elif channel == "setpoint" and not self._telemetry_decides(now_s):
            self._signal(msg.thrust_n > 0, "thrust commanded (controller)" if msg.thrust_n > 0 else
                         "no thrust commanded (controller)", now_s)
        return self._decide(d, now_s)

    def _telemetry_decides(self, now_s: float) -> bool:
        return self.telemetry_s is not None and now_s - self.telemetry_s <= self.config.telemetry_timeout_s

    def _signal(self, flying: bool, why: str, now_s: float) -> None:
        if flying != self.flying or self.since_s is None:
            self.flying, self.since_s, self.since_flight_t_s = flying, now_s, self.flight_t_s
        self.why = why

    def _decide(self, d: Decision, now_s: float) -> Decision:
        held_s = now_s - self.since_s if self.since_s is not None else 0.0
        if self.since_flight_t_s is not None:
            held_s = max(held_s, self.flight_t_s - self.since_flight_t_s)
        if not self.flying and held_s >= self.config.idle_end_s:
            self.suppressed = False  # landed: the next take-off is a new flight
            if self.recording and not self.manual:
                d.stop = f"landed: not flying for {self.config.idle_end_s:g} s ({self.why})"
                self._stopped()
        elif (self.flying and held_s >= self.config.start_after_s and not self.recording and self.config.auto
              and not self.suppressed and not d.stop and self.last_seq >= 0):
            d.start = f"flying for {self.config.start_after_s:g} s: {self.why}"
            self.recording, self.manual, self.first_seq = True, False, self.last_seq
        return d

    def tick(self, now_s: float) -> Decision:
        """Periodic check: the debounce timers, and a source that fell silent."""
        if (self.recording and not self.manual and self.last_state_s >= 0
                and now_s - self.last_state_s >= self.config.silence_end_s):
            self._stopped()
            return Decision(stop=f"no state samples for {self.config.silence_end_s:g} s")
        return self._decide(Decision(), now_s)

    def command(self, name: str) -> tuple[Decision, str]:
        if name == "start":
            if self.recording:
                return Decision(), "already recording"
            self.recording, self.manual, self.first_seq = True, True, self.last_seq
            return Decision(start="operator start"), "recording started"
        if name == "stop":
            if not self.recording:
                return Decision(), "not recording"
            self._stopped()
            self.suppressed = self.flying  # in the air: no automatic restart until landed
            return Decision(stop="operator stop"), "recording stopped"
        raise ValueError(f"unknown recorder command {name!r}; choose start or stop")

    def _stopped(self) -> None:
        self.recording, self.manual = False, False


def new_flight_id(vehicle: str, directory: Path, now_unix_s: float | None = None) -> str:
    base = f"{vehicle}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime(now_unix_s or time.time()))}"
    flight, n = base, 1
    while any(directory.glob(f"{flight}.seg*.rrd")):
        n += 1
        flight = f"{base}-{n}"
    return flight


class ActiveFlight:
    """The sidecar that lets a restarted recorder continue the flight it was writing."""

    def __init__(self, directory: Path, vehicle: str) -> None:
        self.path = directory / f".{vehicle}.active.json"

    def load(self) -> dict | None:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return None

    def save(self, data: dict) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data))
        os.replace(tmp, self.path)

    def clear(self) -> None:
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass


class PendingCompactions:
    """Files closed at a shutdown, compacted by the next recorder start (a small JSON list)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()

    def paths(self) -> list[Path]:
        try:
            return [Path(p) for p in json.loads(self.path.read_text()) if Path(p).exists()]
        except (OSError, ValueError):
            return []

    def _write(self, paths: list[Path]) -> None:
        if paths:
            self.path.write_text(json.dumps(sorted({str(p) for p in paths})))
        else:
            self.path.unlink(missing_ok=True)

    def add(self, path: Path) -> None:
        with self._lock:
            self._write(self.paths() + [path])

    def discard(self, path: Path) -> None:
        with self._lock:
            self._write([p for p in self.paths() if p != path])


class Recorder:
    """The writer thread's work: decode, track flights, write, report (no Zenoh in here)."""

    def __init__(self, config: RecorderConfig, vehicle: str, publish_status=None, query_params=None, log=print,
                 report=None) -> None:
        from recordings.layout import message_type

        self._message_type = message_type
        self.config = config
        self.vehicle = vehicle
        self.directory = Path(config.directory)
        self.pending = PendingCompactions(self.directory / f".{vehicle}.to-compact.json")
        self.tracker = FlightTracker(config)
        self.active = ActiveFlight(self.directory, vehicle)
        self.publish_status = publish_status or (lambda msg: None)
        self.query_params = query_params or (lambda: {})
        self.log = log
        self.report = report or (lambda level, text: log(f"{level}: {text}"))
        self.errors = 0
        self.last_error = ""
        self.queue: queue.Queue = queue.Queue(maxsize=config.queue_size)
        self.preroll: deque = deque()
        self.writer = None
        self.dropped = 0
        self.rejected = 0
        self.last_reject = ""
        self.flight, self.segment, self.last_end = "", 0, ""
        self._seen: dict[str, set] = {}
        self.missed: dict[str, int] = {}  # samples the bus never delivered here (seq gaps) per topic
        self._last_seq: dict[str, int] = {}
        self._last_status = 0.0
        self._stop = threading.Event()
        self._compactions: list[threading.Thread] = []
        self._compacting: set[Path] = set()  # files a compaction is rewriting now: one at a time per file
        self._compacting_lock = threading.Lock()
        self._repaired: set[Path] = set()

    # -- called from Zenoh threads: enqueue only ------------------------------------------
    def offer(self, channel: str, payload: bytes, received_s: float) -> None:
        try:
            self.queue.put_nowait(("msg", channel, payload, received_s))
        except queue.Full:
            self.dropped += 1

    def command(self, name: str) -> None:
        self.queue.put(("cmd", name, None, time.monotonic()))

    # -- the writer thread --------------------------------------------------------------
    def _repair_crashed(self, previous: dict | None) -> None:
        """The file a crashed recorder was writing has no footer: rewrite it (once)."""
        path = Path(previous["path"]) if previous and previous.get("path") else None
        if path is not None and path.exists() and path not in self._repaired:
            self._repaired.add(path)
            self._compact(path, "repaired after a crash")

    def prepare(self) -> None:
        """Create the folder, clear scratch files, compact what a shutdown or a crash left."""
        self.directory.mkdir(parents=True, exist_ok=True)
        for stale in self.directory.glob(".*.compacting.rrd"):  # a compaction cut short
            stale.unlink(missing_ok=True)
        self._repair_crashed(self.active.load())
        if self.config.compact:
            for path in self.pending.paths():
                self._compact(path, "closed at a shutdown")

    def _guarded(self, fn, *args) -> None:
        """A failure to write (disk full, folder gone, ...) ends the recording, never the recorder:
        a recorder that crash-looped would make the launcher give up on the whole system."""
        try:
            fn(*args)
        except Exception as exc:  # whatever the file system or the native writer raise
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            if self.errors <= 5 or self.errors % 100 == 0:
                self.report("error", f"recording failed ({self.errors} failures): {self.last_error}")
            if self.writer is not None:
                writer, self.writer = self.writer, None
                try:
                    writer.close()
                except Exception:
                    pass
            if self.tracker.recording:
                self.tracker.command("stop")  # and no automatic restart before the next arming

    def _flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()
            self._touch()

    def run(self) -> None:
        self._guarded(self.prepare)
        next_flush = time.monotonic() + self.config.flush_period_s
        try:
            while not self._stop.is_set():
                timeout = max(0.0, next_flush - time.monotonic())
                try:
                    self._guarded(self._handle, self.queue.get(timeout=timeout))
                except queue.Empty:
                    pass
                now = time.monotonic()
                if now >= next_flush:
                    next_flush = now + self.config.flush_period_s
                    if self.queue.empty():  # with a backlog, newer samples are waiting: not silent
                        self._guarded(self._apply, self.tracker.tick(now), now)
                    self._guarded(self._flush)
                    if now - self._last_status >= self.config.status_period_s:
                        self._guarded(self._status)
        finally:
            drain_until = time.monotonic() + 0.3  # what arrived before the stop, within the launcher's patience
            while time.monotonic() < drain_until:
                try:
                    self._guarded(self._handle, self.queue.get_nowait())
                except queue.Empty:
                    break
            self._guarded(lambda: self._end("recorder stopped", keep_active=False))

    def stop(self) -> None:
        self._stop.set()

    def join_compactions(self, timeout_s: float = 30.0) -> None:
        """Wait for the background compactions, ``timeout_s`` in all (not each: at a shutdown the
        launcher's grace is for the flight's file). One still running is finished by the next recorder start."""
        deadline = time.monotonic() + timeout_s
        for thread in self._compactions:
            thread.join(max(0.0, deadline - time.monotonic()))

    def _handle(self, item) -> None:
        kind, channel, payload, received = item
        if kind == "cmd":
            self._apply(self.tracker.command(channel)[0], received)
            return
        try:
            msg = self._message_type(channel).from_bytes(payload)
        except SchemaError as exc:
            self.rejected += 1
            self.last_reject = f"{channel}: {exc}"
            return
        self._apply(self.tracker.on_message(channel, msg, received), received)
        if self.writer is not None:
            self.writer.add(channel, msg)
            self._note(channel, msg)
        else:
            self.preroll.append((received, channel, msg))
            while self.preroll and received - self.preroll[0][0] > self.config.preroll_s:
                self.preroll.popleft()

    def _apply(self, d, now_s: float) -> None:
        if d.stop:
            self._end(d.stop, keep_active=False)
        if d.start:
            self._begin(d.start)

    def _note(self, channel: str, msg: Message) -> None:
        seq = getattr(msg, "seq", None)
        if channel in ("state", "estimate", "setpoint") and seq is not None:
            last = self._last_seq.get(channel)
            if last is not None and seq > last + 1:
                self.missed[channel] = self.missed.get(channel, 0) + seq - last - 1
            self._last_seq[channel] = seq if last is None or seq > last or seq < last - 1000 else last
        if channel == "estimate":
            self._seen.setdefault("pathways", set()).add(msg.pathway)
            self._seen.setdefault("networks", set()).add(msg.network_id)
        elif channel == "truth":
            self._seen.setdefault("scenarios", set()).add(msg.scenario)
        elif channel == "telemetry" and msg.autopilot:
            self._seen.setdefault("autopilots", set()).add(msg.autopilot)
        elif channel == "params/estimator" and "lipschitz_bound" in msg.values:
            self._seen.setdefault("lipschitz_bounds", set()).add(msg.values["lipschitz_bound"])

    def _begin(self, why: str) -> None:
        from recordings.writer import FlightWriter, segment_path

        previous = self.active.load()
        resumed = False
        self._repair_crashed(previous)
        if (previous and previous.get("vehicle") == self.vehicle
                and time.time() - previous.get("touched_unix_s", 0) <= self.config.resume_window_s
                and self.tracker.last_seq >= previous.get("last_seq", 0)):
            flight, segment, resumed = previous["flight"], previous["segment"] + 1, True
        else:
            flight, segment = new_flight_id(self.vehicle, self.directory), 0
        path = segment_path(self.directory, flight, segment)
        props = {"start": {"reason": why, "resumed": resumed, "first_seq": self.tracker.last_seq}}
        try:
            params = self.query_params()
        except Exception as exc:  # a service not up: record without its parameters
            params = {"error": f"{type(exc).__name__}: {exc}"}
        props["params"] = {k: v for k, v in params.items()}
        self.writer = FlightWriter(path, vehicle=self.vehicle, flight=flight, segment=segment, properties=props)
        self.flight, self.segment = flight, segment
        self._seen, self.missed, self._last_seq = {}, {}, {}
        for _, channel, msg in self.preroll:
            self.writer.add(channel, msg)
            self._note(channel, msg)
        self.preroll.clear()
        self.writer.flush()
        self._touch()
        self.log(f"flight {flight} segment {segment} → {path} ({why}{', resumed' if resumed else ''})")
        self._status(force=True)

    def _touch(self) -> None:
        self.active.save({"vehicle": self.vehicle, "flight": self.flight, "segment": self.segment,
                          "path": str(self.writer.path), "last_seq": self.tracker.last_seq,
                          "touched_unix_s": time.time()})

    def _compact(self, path: Path, what: str) -> None:
        """Rewrite a closed (or crashed) file with merged chunks, in the background."""
        from recordings.reader import RecordingError, repair

        with self._compacting_lock:
            if path in self._compacting:
                return  # two rewrites of one file at once share its scratch file and corrupt it
            self._compacting.add(path)
        self.pending.add(path)  # until it is done: a recorder stopped meanwhile compacts it at its next start

        def work() -> None:
            try:
                repair(path)
                self.pending.discard(path)
                self.log(f"{path}: compacted ({what}), {path.stat().st_size / 1e3:.0f} kB")
            except (RecordingError, OSError, subprocess.SubprocessError) as exc:
                self.log(f"{path}: left as written, could not compact it: {exc}")
            finally:
                with self._compacting_lock:
                    self._compacting.discard(path)

        thread = threading.Thread(target=work, name="recorder-compact", daemon=True)
        thread.start()
        self._compactions.append(thread)

    def _end(self, why: str, *, keep_active: bool) -> None:
        if self.writer is None:
            return
        w = self.writer
        w.set_properties({"summary": {
            "end_reason": why, "duration_s": round(w.stats.duration_s, 3), "messages": w.stats.messages,
            "dropped": self.dropped, "rejected": self.rejected, "missed_samples": dict(self.missed),
            **{k: sorted(v) for k, v in self._seen.items()}}})
        w.close()
        self.writer = None
        self.last_end = why
        if not keep_active:
            self.active.clear()
        self.log(f"flight {self.flight} segment {self.segment} closed: {why}; {w.stats.messages} messages, "
                 f"{w.stats.duration_s:.1f} s, {w.path.stat().st_size / 1e3:.0f} kB"
                 + (f"; samples never delivered here: {self.missed}" if self.missed else ""))
        self._status(force=True)
        if self.config.compact and not self._stop.is_set():
            self._compact(w.path, "flight closed")
        elif self.config.compact:  # shutting down: a prompt exit, the next start compacts it
            self.pending.add(w.path)

    def status(self) -> RecordingMsg:
        w = self.writer
        size = w.path.stat().st_size if w is not None and w.path.exists() else 0
        return RecordingMsg(stamp_s=time.monotonic(), recording=w is not None, flight=self.flight if w else "",
                            segment=self.segment if w else 0, path=str(w.path) if w else "",
                            duration_s=w.stats.duration_s if w else 0.0, size_bytes=size, dropped=self.dropped)

    def _status(self, force: bool = False) -> None:
        self._last_status = time.monotonic()
        self.publish_status(self.status())


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, RecorderConfig)


def config_from_args(args) -> RecorderConfig:
    config = config_from_options(RecorderConfig, args)
    if not 0.0 < config.flush_period_s <= 0.2:
        raise SystemExit("--flush-period must be in (0, 0.2] s: a crash may lose at most 0.2 s")
    return config


def run(args, bus) -> int:
    from recordings.layout import channel_of
    from runtime.client import ServiceUnavailable, read_params
    from runtime.graph import ROLES
    from runtime.node import Node, run_node

    config = config_from_args(args)
    if config.nice:
        os.nice(config.nice)  # below the control loop's services: on a busy CPU the loop runs first, the queue waits
    node = Node("recorder", vehicle=args.vehicle, bus=bus, config=config)
    put_status = node.publisher("recording")
    services = [r.name for r in ROLES if r.per_vehicle and r.bus_role != "router" and r.name != "recorder"]

    def read(service: str) -> dict | None:
        try:
            return read_params(node.session, node.keys, service, timeout_s=config.params_timeout_s).values
        except ServiceUnavailable:
            return None  # not running (no trainer, no gateway): recorded without its parameters

    def query_params() -> dict:
        with ThreadPoolExecutor(len(services)) as pool:  # all at once: an absent service costs one timeout
            return {s: v for s, v in zip(services, pool.map(read, services)) if v is not None}

    recorder = Recorder(config, args.vehicle, publish_status=put_status, query_params=query_params, log=node.log,
                        report=node.event)

    def on_sample(sample) -> None:
        found = channel_of(str(sample.key_expr))
        if found is None or found[0] != args.vehicle or found[1] == "recording":
            return
        received = time.monotonic()
        recorder.offer(found[1], sample.payload.to_bytes(), received)
        if found[1] in node.role.subscribes:
            node.stats.valid(found[1], received)

    def on_command(name: str, _args: dict) -> tuple[bool, str]:
        if name not in ("start", "stop"):
            return False, f"unknown command {name!r}; the recorder takes start and stop"
        recorder.command(name)
        return True, f"{name} queued"

    node.on_command(on_command)
    node.status_hook = lambda: ((f"recording {recorder.flight} segment {recorder.segment}" if recorder.writer else "idle")
                                + (f", dropped {recorder.dropped}" if recorder.dropped else "")
                                + (f", {recorder.errors} write failures, last: {recorder.last_error}" if recorder.errors
                                   else ""))
    writer_thread = threading.Thread(target=recorder.run, name="recorder-writer", daemon=True)

    # every key of the vehicle, the per-service ones included: wider than the role's typed topics. Declared before
    # run_node declares the recorder alive, as the other services subscribe: a world that waits for the recorder
    # (neso up) then starts with every sample recorded; the writer starts below, the queue holds what comes first
    everything = node.session.declare_subscriber(f"{node.keys.prefix}/**", on_sample)

    def main(node: Node) -> None:
        writer_thread.start()
        node.log(f"recording {args.vehicle} into {config.directory} "
                 f"({'manual' if not config.auto else 'a file per flight'}, flush every {config.flush_period_s:g} s)")
        node.wait()
        everything.undeclare()
        recorder.stop()
        writer_thread.join(WRITER_FINISH_S)
        recorder.join_compactions(0.5)  # an unfinished one resumes at the next start

    return run_node(node, main)
