"""``dashboard``: the operator's web page (viser) for every vehicle on the bus.

One process for the whole bus (role ``dashboard``, ``per_vehicle=False``). Zenoh callbacks
only enqueue raw samples (:class:`runtime.observer.Observer`); one UI thread drains them
every ``1/ui_rate`` s, decodes and ingests them into :class:`dashboard.model.FleetModel`,
moves the vehicle at that rate and re-renders plots and panels at half of it. Controls go
through :class:`BusFacade`, which runs the parameter set or command on a worker thread and
hands the reply (or the refusal) back to the page. The dashboard publishes nothing on the
streams: killing it changes nothing for the flight, and a restarted one picks the flight up
from the next samples plus a parameter get of every live service.
"""
from __future__ import annotations

import argparse
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable

from runtime.graph import role as graph_role
from runtime.options import add_options, config_from_options, option
from runtime.schema import EventMsg, HealthMsg, Keys, ParamStateMsg, SchemaError, TOPICS, vehicle_of

Reply = Callable[[bool, str], None]
WATCHED = graph_role("dashboard").watches  # the streams of every vehicle, declared in runtime/graph.py
PER_SERVICE = {"health": HealthMsg, "params": ParamStateMsg, "event": EventMsg}


PORT_RETRY_S = 5.0
# viser sends queued messages to the pages only while no thread is inside ``server.atomic()``: a UI
# loop that runs back to back (its step slower than its period on a loaded CPU) would hold the
# page frozen for seconds (measured: 40 ms steps back to back, 7 s with no update reaching the
# page; 5 ms of idle between them, every update). So the loop always idles this share of a period.
MIN_IDLE_SHARE = 0.25


@dataclass(frozen=True)
class DashboardConfig:
    host: str = option("127.0.0.1", help="address to serve on (loopback only unless you mean to share it)")
    port: int = option(8080, help="port to serve on")
    ui_rate_hz: float = option(20.0, flag="--ui-rate", unit="Hz", help="pose updates per second (plots at half)")
    window_s: float = option(10.0, flag="--window", unit="s", help="time shown in plots and figures")
    nice: int = option(10, help="CPU niceness added at start: the page must never slow the control loop")
    request_timeout_s: float = option(8.0, flag="--request-timeout", unit="s",
                                      help="how long a change or command sent from the page waits for the service's "
                                           "answer (the service checks it first: certifying a network took over 2 s "
                                           "on a busy machine)")


SUPERSEDED = "superseded by a newer change before it was sent"


class PortTaken(OSError):
    """The dashboard's port is in use by something else."""


class BusFacade:
    """Parameter sets and commands on worker threads; replies come back through callbacks.

    Requests about the same thing are superseded, like viser's ``redundancy_key``: per key at most
    one runs and one waits, and a newer one replaces the waiting one (whose reply says it was
    superseded), so an operator dragging the L_N slider sends the newest value, not a queue of stale
    ones, and two changes of the same parameters never overtake each other on the pool's threads.
    Commands have no key: every one is an intent (arm, then take off) and each is sent."""

    def __init__(self, session, *, timeout_s: float, workers: int = 3) -> None:
        """``timeout_s``: how long each request waits for its service's answer (:attr:`DashboardConfig.request_timeout_s`)."""
        self.session = session
        self.timeout_s = timeout_s
        self.pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dashboard-bus")
        self._lock = threading.Lock()
        self._busy: set = set()  # keys with a request running
        self._waiting: dict = {}  # key → the request to run when the running one is done
        self.superseded = 0

    def _submit(self, fn: Callable[[], tuple[bool, str]], reply: Reply, key=None) -> None:
        if key is None:
            self.pool.submit(self._run, fn, reply)
            return
        with self._lock:
            replaced = self._waiting.pop(key, None) if key in self._busy else None
            if key in self._busy:
                self._waiting[key] = (fn, reply)
            else:
                self._busy.add(key)
                self.pool.submit(self._run_keyed, key, fn, reply)
            self.superseded += replaced is not None
        if replaced is not None:
            self._reply(replaced[1], False, SUPERSEDED)

    def _run_keyed(self, key, fn: Callable[[], tuple[bool, str]], reply: Reply) -> None:
        self._run(fn, reply)
        with self._lock:
            waiting = self._waiting.pop(key, None)
            if waiting is None:
                self._busy.discard(key)
                return
        self.pool.submit(self._run_keyed, key, *waiting)

    def _run(self, fn: Callable[[], tuple[bool, str]], reply: Reply) -> None:
        try:
            ok, text = fn()
        except Exception as exc:  # no reply, or the service is gone: say so on the page
            ok, text = False, f"{type(exc).__name__}: {exc}"
        self._reply(reply, ok, text)

    @staticmethod
    def _reply(reply: Reply, ok: bool, text: str) -> None:
        try:
            reply(ok, text)
        except Exception as exc:
            print(f"[dashboard] showing a reply failed: {exc}", flush=True)

    def set_params(self, vehicle: str, service: str, values: dict, reply: Reply) -> None:
        from runtime.client import set_params

        def go() -> tuple[bool, str]:
            r = set_params(self.session, Keys(vehicle), service, values, timeout_s=self.timeout_s)
            return r.ok, r.error if not r.ok else f"{service} will apply {values}"
        self._submit(go, reply, key=("set", vehicle, service, tuple(sorted(k for k in values if k != "override"))))

    def command(self, vehicle: str, service: str, name: str, args: dict, reply: Reply) -> None:
        from runtime.client import command

        def go() -> tuple[bool, str]:
            r = command(self.session, Keys(vehicle), service, name, args, timeout_s=self.timeout_s)
            return r.ok, r.message
        self._submit(go, reply)

    def get_params(self, vehicle: str, service: str, done: Callable[[dict], None]) -> None:
        from runtime.client import get_params

        def go() -> tuple[bool, str]:
            done(get_params(self.session, Keys(vehicle), service, timeout_s=self.timeout_s).values)
            return True, ""

        def reply(ok: bool, text: str) -> None:
            if not ok and text != SUPERSEDED:
                print(f"[dashboard] params of {vehicle}/{service}: {text}", flush=True)
        self._submit(go, reply, key=("get", vehicle, service))

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def pace(due_s: float, now_s: float, period_s: float) -> tuple[float, float]:
    """(how long to wait, the next step's due time) for a loop whose next step is due at ``due_s``:
    on time it waits until then; late, it waits :data:`MIN_IDLE_SHARE` of a period and starts
    counting periods again from then (a late loop never catches up by running back to back)."""
    min_idle_s = MIN_IDLE_SHARE * period_s
    if due_s - now_s >= min_idle_s:
        return due_s - now_s, due_s
    return min_idle_s, now_s + min_idle_s


def decode_into(model, kind: str, key: str, payload: bytes, received_s: float) -> None:
    """One raw sample into the model (malformed ones counted, never fatal)."""
    try:
        vehicle = vehicle_of(key)
        if kind == "alive":
            model.ingest(vehicle, "alive", payload == b"1", received_s, service=key.rsplit("/", 1)[-1])
            return
        cls = PER_SERVICE.get(kind) or TOPICS[kind]
        model.ingest(vehicle, kind, cls.from_bytes(payload), received_s)
    except (SchemaError, ValueError, KeyError) as exc:
        model.reject(key, str(exc))


class Dashboard:
    """The running dashboard: observer → model → view, plus the bus facade for controls."""

    def __init__(self, bus, config: DashboardConfig, *, default_vehicle: str = "uav1") -> None:
        import viser

        from dashboard.model import FleetModel
        from dashboard.view import DashboardView
        from dashboard.viser_threads import install
        from runtime.observer import Observer

        install()  # before the server: its buffers are woken from our threads

        self.model = FleetModel(window_s=config.window_s)
        self.lock = threading.Lock()
        self.observer = Observer(bus)
        self.facade = BusFacade(self.observer.session, timeout_s=config.request_timeout_s)
        host, port = config.host, config.port
        self.server = viser.ViserServer(host=host, port=port, label="Neural-ESO", verbose=False)
        if self.server.get_port() != port:
            actual = self.server.get_port()
            self.server.stop()
            self.facade.close()
            self.observer.close()
            raise PortTaken(f"port {port} is taken (viser would have moved to {actual}): choose --port")
        self.view = DashboardView(self.server, self.model, self.lock, self.facade,
                                  default_vehicle=default_vehicle)
        self.period_s = 1.0 / config.ui_rate_hz
        self._seeded: set[tuple[str, str]] = set()
        self._stop = threading.Event()
        for topic in WATCHED:
            self.observer.watch(topic, topic)
        for kind in PER_SERVICE:
            self.observer.watch(f"{kind}/*", kind)
        self.observer.watch_alive()

    def _seed_params(self, vehicle: str, service: str) -> None:
        """A service seen alive for the first time: ask its parameters (broadcasts only come on change)."""
        if (vehicle, service) in self._seeded:
            return
        self._seeded.add((vehicle, service))

        def done(values: dict) -> None:
            with self.lock:
                self.model.vehicle(vehicle).ingest_params(service, values)
        self.facade.get_params(vehicle, service, done)

    def step(self, tick: int) -> None:
        items = self.observer.drain()
        now = time.monotonic()
        with self.lock:
            self.model.dropped = self.observer.dropped
            for kind, key, payload, received in items:
                decode_into(self.model, kind, key, payload, received)
                if kind == "alive" and payload == b"1":
                    self._seed_params(vehicle_of(key), key.rsplit("/", 1)[-1])
            with self.server.atomic():  # position and attitude land together; nothing else needs to
                self.view.render_pose()
            if tick % 2 == 0:
                self.view.render(now)

    def run(self, until=None) -> None:
        """Render at the UI rate until :meth:`stop` or ``until`` (an event-like flag: a signal's) is set."""
        tick = 0
        next_t = time.monotonic()
        while not self._stop.is_set() and not (until is not None and until.is_set()):
            try:
                self.step(tick)
            except Exception as exc:  # a rendering bug must not end the page
                print(f"[dashboard] render failed: {type(exc).__name__}: {exc}", flush=True)
            tick += 1
            delay, next_t = pace(next_t + self.period_s, time.monotonic(), self.period_s)
            self._stop.wait(delay)

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self.facade.close()
        self.server.stop()
        self.observer.close()


# -- service entry points ---------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DashboardConfig)


def run(args, bus) -> int:
    import os

    from runtime.node import freeze_startup_heap
    from runtime.signals import Signalled

    config = config_from_options(DashboardConfig, args)
    if config.nice:
        os.nice(config.nice)
    signalled = Signalled().install()  # a flag, never an event set in the handler (runtime/signals.py)
    while not signalled:
        try:
            dash = Dashboard(bus, config, default_vehicle=args.vehicle)
            break
        except PortTaken as exc:  # wait for it rather than crash-loop: the flight never depends on the page
            print(f"[dashboard] {exc}; trying again in {PORT_RETRY_S:g} s", flush=True)
            signalled.wait(PORT_RETRY_S)
    else:
        return 0
    freeze_startup_heap()
    print(f"[dashboard] serving http://{config.host}:{config.port}", flush=True)
    try:
        dash.run(until=signalled)
        return 0
    finally:
        dash.close()
