"""The thin adapter every service uses: typed publish/subscribe, live parameters, commands,
health and liveliness over one Zenoh session.

A service builds a :class:`Node` for its role, registers handlers, calls :meth:`Node.start`
and runs. Handlers run under the node's lock (one at a time, whichever Zenoh thread
delivers), so a service's step object never sees two inputs at once. A payload that fails
its schema is counted in health and dropped; a handler that raises is reported as an event
and counted; neither stops the service.
"""
from __future__ import annotations

import contextlib
import dataclasses
import gc
import json
import os
import sys
import threading
import time
import traceback
from typing import Any, Callable

from runtime.bus import BusConfig, close_session, open_session, publisher_qos
from runtime.graph import ROLES, role as graph_role
from runtime.health import HealthStats
from runtime.params import ParamSet
from runtime.schema import (OFFER_COMMANDS, CommandReply, CommandRequest, EventMsg, HealthMsg, Keys, Message,
                            ParamReply, ParamRequest, ParamStateMsg, SchemaError)
from runtime.signals import POLL_S, Signalled

HEALTH_PERIOD_S = 1.0
SIGNALLED = Signalled()  # SIGINT/SIGTERM came (stop_all_on_signals): every node stops, one made later at once
CommandHandler = Callable[[str, dict], tuple[bool, str]]
FAILED = (False, "command failed (see events)")


class AnsweredOnce:
    """Commands by request id, each done once. A client repeats a query it got no answer to in
    time (:func:`runtime.client.command`); a repeat of a finished request gets the first answer,
    a repeat of one still running waits up to ``wait_s`` for it (then no answer: the client asks
    again; the wait is short because it holds one of Zenoh's threads). Without this a slow command (a vehicle's acknowledgement, a file read) would run
    once per retry, and a second rollback would undo the first. Keeps the last ``keep`` answers."""

    def __init__(self, keep: int = 256) -> None:
        self._lock = threading.Lock()
        self._done: dict[str, tuple[bool, str]] = {}
        self._running: dict[str, threading.Event] = {}
        self._keep = keep

    def run(self, request_id: str, fn: Callable[[], tuple[bool, str]], wait_s: float = 0.05):
        """``fn()``'s answer, or the first answer to ``request_id``; None if it is still running."""
        with self._lock:
            if request_id in self._done:
                return self._done[request_id]
            running = self._running.get(request_id)
            if running is None:
                self._running[request_id] = threading.Event()
        if running is not None:
            running.wait(wait_s)
            with self._lock:
                return self._done.get(request_id)
        result = FAILED
        try:
            result = fn()
        finally:
            with self._lock:
                self._done[request_id] = result
                while len(self._done) > self._keep:
                    self._done.pop(next(iter(self._done)))
                self._running.pop(request_id).set()
        return result


def describe_config(config: Any) -> str:
    """A dataclass config as indented JSON (what a service prints at start and records)."""
    data = dataclasses.asdict(config) if dataclasses.is_dataclass(config) else dict(config)
    return json.dumps(data, default=str)


class Node:
    """One service's presence on the bus (see module docstring)."""

    def __init__(self, service: str, *, vehicle: str, bus: BusConfig, config: Any = None,
                 params: ParamSet | None = None) -> None:
        self.role = graph_role(service)
        self.service = service
        self.keys = Keys(vehicle)
        self.config = config
        self.params = params
        self.lock = threading.RLock()
        self.stats = HealthStats(service, tuple(self.role.subscribes) + ("param", "cmd"))
        self.status_hook: Callable[[], str] | None = None
        self._command_handler: CommandHandler | None = None
        self._unlocked_commands: frozenset[str] = frozenset()
        self._answered = AnsweredOnce()
        self._stop = threading.Event()
        self._closed = False  # under the lock: no handler runs once the session is closing
        if SIGNALLED:
            self._stop.set()
        self._declared: list[Any] = []
        self._publishers: dict[str, Any] = {}
        self.bus = bus
        self.session = open_session(bus)
        service_qos = publisher_qos(bus, "service")
        self._event_pub = self.session.declare_publisher(self.keys.event(service), **service_qos)
        self._health_pub = self.session.declare_publisher(self.keys.health(service), **service_qos)
        self._params_pub = self.session.declare_publisher(self.keys.params(service), **service_qos)

    # -- streams ------------------------------------------------------------------------
    def publisher(self, topic: str) -> Callable[[Message], None]:
        """A function that publishes a ``topic`` message; the role must declare the topic."""
        cls = self.role.publishes.get(topic)
        if cls is None:
            raise ValueError(f"{self.service} does not publish {topic!r} (runtime/graph.py)")
        if topic not in self._publishers:
            self._publishers[topic] = self.session.declare_publisher(self.keys.topic(topic),
                                                                     **publisher_qos(self.bus, topic))
        pub = self._publishers[topic]

        def put(msg: Message) -> None:
            if not isinstance(msg, cls):
                raise TypeError(f"{topic} carries {cls.__name__}, not {type(msg).__name__}")
            pub.put(msg.to_bytes())
        return put

    def subscribe(self, topic: str, handler: Callable[[Any, float], None]) -> None:
        """Call ``handler(message, received_monotonic_s)`` under the node lock for every valid
        ``topic`` message; count the invalid ones."""
        cls = self.role.subscribes.get(topic)
        if cls is None:
            raise ValueError(f"{self.service} does not subscribe {topic!r} (runtime/graph.py)")

        def on_sample(sample) -> None:
            received = time.monotonic()
            try:
                msg = cls.from_bytes(sample.payload.to_bytes())
            except SchemaError as exc:
                self.stats.reject(topic, str(exc))
                return
            self.stats.valid(topic, received)
            self._handle(f"{topic} handler", handler, msg, received)

        self._declared.append(self.session.declare_subscriber(self.keys.topic(topic), on_sample))

    def subscribe_params(self, service: str, handler: Callable[[dict], None]) -> None:
        """Call ``handler(values)`` under the node lock whenever ``service``'s parameters take effect
        (its :class:`ParamStateMsg` broadcast); invalid broadcasts are counted."""

        def on_sample(sample) -> None:
            try:
                msg = ParamStateMsg.from_bytes(sample.payload.to_bytes())
            except SchemaError as exc:
                self.stats.reject("params", str(exc))
                return
            self._handle("params handler", handler, dict(msg.values))

        self._declared.append(self.session.declare_subscriber(self.keys.params(service), on_sample))

    def subscribe_health(self, handler: Callable[[str, HealthMsg, float], None]) -> None:
        """Call ``handler(service, health, received_monotonic_s)`` under the node lock for every service's 1 Hz
        health report of this vehicle (what a watcher needs to tell whether the bus and every service are up);
        invalid reports are counted."""

        def on_sample(sample) -> None:
            received = time.monotonic()
            try:
                msg = HealthMsg.from_bytes(sample.payload.to_bytes())
            except SchemaError as exc:
                self.stats.reject("health", str(exc))
                return
            self._handle("health handler", handler, msg.service, msg, received)

        self._declared.append(self.session.declare_subscriber(self.keys.every("health"), on_sample))

    def alive_services(self, timeout_s: float = 0.5) -> set[str]:
        """The services of this vehicle whose liveliness token is on the bus now (asked, at most ``timeout_s``)."""
        replies = self.session.liveliness().get(self.keys.every("alive"), timeout=timeout_s)
        return {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}

    def _handle(self, what: str, handler: Callable, *args) -> None:
        """A bus handler under the node lock, guarded; none once the node is closing."""
        with self.lock:
            if not self._closed:
                self._guarded(what, handler, *args)

    def _guarded(self, what: str, fn: Callable, *args) -> Any:
        try:
            return fn(*args)
        except Exception as exc:  # a bug in one handler must not stop the service
            self.stats.reject(what.split()[0], f"{type(exc).__name__}: {exc}")
            self.event("error", f"{what} failed: {type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}")
            return None

    # -- parameters and commands -----------------------------------------------------------
    def on_command(self, handler: CommandHandler, *, unlocked: tuple[str, ...] = ()) -> None:
        """``handler(name, args) -> (ok, message)`` answers commands under the node lock, except
        those named in ``unlocked`` (slow ones, e.g. reading a file, that take the lock themselves
        only for the moment they touch the step object)."""
        self._command_handler = handler
        self._unlocked_commands = frozenset(unlocked)

    def _on_param_query(self, query, read_only: bool = False) -> None:
        try:
            request = ParamRequest.from_bytes(query.payload.to_bytes() if query.payload is not None else b"")
        except SchemaError as exc:
            self.stats.reject("param", str(exc))
            query.reply_err(ParamReply(ok=False, service=self.service, values={}, error=str(exc)).to_bytes())
            return
        if read_only and request.op != "get":
            reply = ParamReply(ok=False, service=self.service, values={},
                               error=f"{self.keys.params(self.service)} is read only: set on {self.keys.param(self.service)}")
        elif self.params is None:
            reply = ParamReply(ok=request.op == "get", service=self.service, values={},
                               error="" if request.op == "get" else f"{self.service} has no parameters")
        elif request.op == "get":
            reply = ParamReply(ok=True, service=self.service, values=self.params.values())
        else:
            self.params.prepare(request.values)  # slow work (a certificate) outside the lock
            with self.lock:  # a check may read the step object's state
                ok, error, values = self.params.request(request.values)
            for note in self.params.take_overrides():
                self.event("warning", note)
            reply = ParamReply(ok=ok, service=self.service, values=values, error=error)
            self.log(f"param set {request.values}: " + ("accepted" if ok else f"refused: {error}"))
        query.reply(query.key_expr, reply.to_bytes())

    def _on_command_query(self, query, offer_key: bool = False) -> None:
        try:
            request = CommandRequest.from_bytes(query.payload.to_bytes() if query.payload is not None else b"")
        except SchemaError as exc:
            self.stats.reject("cmd", str(exc))
            query.reply_err(CommandReply(ok=False, service=self.service, message=str(exc)).to_bytes())
            return
        args = {k: v for k, v in request.args.items() if k != "request"}
        wrong_key = (request.name in OFFER_COMMANDS) != offer_key  # an offer has its own key (the ACL tells them apart)
        if wrong_key:
            ok, message = False, (f"{request.name} goes to {self.keys.offer(self.service)}" if not offer_key
                                  else f"{self.keys.offer(self.service)} takes only {', '.join(OFFER_COMMANDS)}")
        elif self._command_handler is None:
            ok, message = False, f"{self.service} takes no commands"
        else:
            def execute() -> tuple[bool, str]:
                with contextlib.nullcontext() if request.name in self._unlocked_commands else self.lock:
                    result = self._guarded(f"cmd {request.name}", self._command_handler, request.name, args)
                return result if result is not None else FAILED
            request_id = request.args.get("request")
            if isinstance(request_id, str) and request_id:
                answer = self._answered.run(request_id, execute)
                if answer is None:
                    return  # the first of these is still running: no answer now, the client asks again
                ok, message = answer
            else:
                ok, message = execute()
        self.log(f"command {request.name} {args}: " + ("ok" if ok else "refused") + (f": {message}" if message else ""))
        query.reply(query.key_expr, CommandReply(ok=ok, service=self.service, message=message).to_bytes())

    def broadcast_params(self, seq: int, note: str = "") -> None:
        if self.params is not None:
            self._params_pub.put(ParamStateMsg(stamp_s=time.monotonic(), service=self.service, seq=seq,
                                               values=self.params.effective(), note=note[:4096]).to_bytes())

    # -- telling people -----------------------------------------------------------------
    def log(self, text: str) -> None:
        print(f"[{self.service}] {text}", flush=True)

    def event(self, level: str, text: str) -> None:
        self.log(f"{level}: {text}")
        self._event_pub.put(EventMsg(stamp_s=time.monotonic(), service=self.service, level=level,
                                     text=text[:4096]).to_bytes())

    def _health_loop(self) -> None:
        while not self.wait(HEALTH_PERIOD_S):
            if self.status_hook is not None:
                self.stats.status = self._guarded("health status", self.status_hook) or "ok"
            try:
                self._health_pub.put(self.stats.report().to_bytes())
            except Exception as exc:  # the session is closing
                if not self._stop.is_set():
                    self.log(f"health publish failed: {exc}")

    # -- life cycle ---------------------------------------------------------------------
    def start(self) -> None:
        """Print the config, answer parameter and command queries, report health, then declare
        the liveliness token: a service is "alive" once it can do its job."""
        self.log(f"vehicle {self.keys.vehicle}, keys under {self.keys.prefix}/, pid {os.getpid()}")
        if self.config is not None:
            self.log("config " + describe_config(self.config))
        if self.params is not None:
            self.log(f"parameters {self.params.values()}")
        self._declared.append(self.session.declare_queryable(self.keys.param(self.service), self._on_param_query))
        self._declared.append(self.session.declare_queryable(self.keys.cmd(self.service), self._on_command_query))
        self._declared.append(self.session.declare_queryable(  # parameters read by anyone, set by the operator only
            self.keys.params(self.service), lambda query: self._on_param_query(query, read_only=True)))
        if any(self.service in r.offers_to for r in ROLES):
            self._declared.append(self.session.declare_queryable(
                self.keys.offer(self.service), lambda query: self._on_command_query(query, offer_key=True)))
        self.stats.report()  # the first report pays numpy's one-off percentile set-up (~7 ms): not mid-flight
        threading.Thread(target=self._health_loop, name=f"{self.service}-health", daemon=True).start()
        self._declared.append(self.session.liveliness().declare_token(self.keys.alive(self.service)))
        self.broadcast_params(0, "start")

    def stop(self) -> None:
        self._stop.set()

    @property
    def stopping(self) -> bool:
        if SIGNALLED and not self._stop.is_set():
            self._stop.set()  # here, not in the handler (runtime/signals.py)
        return self._stop.is_set()

    def wait(self, timeout_s: float | None = None) -> bool:
        """Until the node stops (True) or ``timeout_s`` passes (False), waking at least every 0.1 s to see a
        signal's flag: the handler sets no event (runtime/signals.py), and a SIGINT the kernel hands to one of
        Zenoh's native threads does not interrupt the main thread's wait either — Python runs the handler only
        when the main thread wakes (seen as a recorder that ignored Ctrl-C until the launcher's SIGKILL)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self.stopping:
            left = POLL_S if deadline is None else min(POLL_S, deadline - time.monotonic())
            if left <= 0:
                return False
            self._stop.wait(left)
        return True

    def close(self) -> None:
        self._stop.set()
        with self.lock:  # a handler running now ends first; none runs after (it would publish on a closed session)
            self._closed = True
        close_session(self.session, self._declared)

    def stop_on_signals(self) -> None:
        """SIGINT/SIGTERM end :meth:`wait` of every node of this process. Off the main thread (one
        process serving several vehicles, ``neso run --vehicles``) the main thread has done it."""
        if threading.current_thread() is threading.main_thread():
            stop_all_on_signals()


def stop_all_on_signals() -> None:
    """SIGINT/SIGTERM stop every node of this process, those made later included (main thread only): the handler
    sets :data:`SIGNALLED`, which every node's :attr:`Node.stopping` and :meth:`Node.wait` read."""
    SIGNALLED.install()


def freeze_startup_heap() -> None:
    """Move every object alive now (the imported modules: numpy, torch, cvxpy, zenoh; the node, its
    network) out of the garbage collector's reach. They live as long as the process, yet each full
    collection walked them all: 144 ms in an estimator-sized process (224,000 objects), a stall that
    could land on any sample, and most of the CPU a service spent exiting (its final collection),
    which under a CPU hog made ``neso up`` kill processes that did not stop in 2 s."""
    gc.freeze()


def run_node(node: Node, main: Callable[[Node], None] | None = None) -> int:
    """Start ``node``, run ``main(node)`` (or wait for a signal), always close the session."""
    try:
        node.stop_on_signals()
        node.start()
        freeze_startup_heap()
        if main is None:
            node.wait()
        else:
            main(node)
        return 0
    except Exception:
        traceback.print_exc(file=sys.stderr)
        return 1
    finally:
        node.close()
