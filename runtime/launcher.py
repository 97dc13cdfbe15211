"""The supervisor behind ``neso up``: every role its own OS process, restarted if it crashes.

Children are started in the order given, their output is echoed with the role's name in
front, and each gets ``PR_SET_PDEATHSIG`` so it dies with the launcher even if the launcher is
killed with ``kill -9`` (no orphans). A child that exits while the launcher is running is
restarted after ``restart_delay_s`` (at most ``max_restarts`` times), unless it exited with
:data:`EXIT_CONFIG` (its configuration was refused: restarting cannot help); a child marked
``finishes`` (the lockstep source) ends the whole run when it exits cleanly. A child starts with its
spec's niceness and CPU affinity (both inherited by everything it starts). ``stop()``
sends SIGTERM to every child, waits up to its spec's ``stop_timeout_s`` (default the supervisor's),
then SIGKILLs what is left.
"""
from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

from runtime.signals import Signalled

_PR_SET_PDEATHSIG = 1
EXIT_CONFIG = 2  # a service refused its configuration (argparse's usage error too): never restarted


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except OSError:
        pass


@dataclass(frozen=True)
class ProcessSpec:
    name: str
    argv: tuple[str, ...]
    finishes: bool = False  # its clean exit ends the run (instead of being restarted)
    essential: bool = True  # False: when it keeps crashing, give up on it alone and let the rest run
    nice: int = 0  # CPU niceness from the start (its imports included): >0 for what must not slow the loop
    cpus: tuple[int, ...] = ()  # CPU affinity from the start (empty: any CPU)
    stop_timeout_s: float | None = None  # SIGTERM → SIGKILL at a stop (None: the supervisor's)


def interrupt(proc: subprocess.Popen, timeout_s: float = 15.0) -> None:
    """Ctrl-C a ``neso up`` (or any group leader started with ``start_new_session``) and wait;
    SIGKILL its whole process group if it has not ended within ``timeout_s``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


class Supervisor:
    def __init__(self, specs: list[ProcessSpec], *, restart_delay_s: float = 0.5, max_restarts: int = 5,
                 stop_timeout_s: float = 2.0, echo=print) -> None:
        self.specs = specs
        self.restart_delay_s = restart_delay_s
        self.max_restarts = max_restarts
        self.stop_timeout_s = stop_timeout_s
        self.echo = echo
        self.procs: dict[str, subprocess.Popen] = {}
        self.restarts: dict[str, int] = {s.name: 0 for s in specs}
        self.finished = threading.Event()
        self.signalled = Signalled()  # SIGINT/SIGTERM, once run() installed it (a flag: runtime/signals.py)
        self.exit_code = 0
        self._stopping = False
        self._lock = threading.Lock()

    def _spawn(self, spec: ProcessSpec) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")

        def setup() -> None:  # in the child between fork and exec
            _die_with_parent()
            if spec.nice:
                os.nice(spec.nice)
            if spec.cpus:
                os.sched_setaffinity(0, spec.cpus)
        proc = subprocess.Popen(list(spec.argv), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env,
                                preexec_fn=setup, text=True, bufsize=1)
        self.procs[spec.name] = proc
        threading.Thread(target=self._pump, args=(spec.name, proc), daemon=True).start()

    def _pump(self, name: str, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.echo(f"{name:>10} | {line.rstrip()}")

    def start(self) -> None:
        for spec in self.specs:
            self._spawn(spec)
        self.echo("started: " + ", ".join(f"{n} (pid {p.pid})" for n, p in self.procs.items()))

    def poll(self) -> None:
        """Restart what crashed; note a finishing child's exit. Call periodically."""
        with self._lock:
            if self._stopping:
                return
            for spec in self.specs:
                if self.signalled:  # a child that Ctrl-C ended is not restarted
                    return
                code = self.procs[spec.name].poll()
                if code is None or self.restarts[spec.name] > self.max_restarts:  # running, or given up on
                    continue
                if spec.finishes and code == 0:
                    self.echo(f"{spec.name} finished")
                    self.finished.set()
                    return
                if code == EXIT_CONFIG:
                    self.restarts[spec.name] = self.max_restarts + 1  # given up on: the same start would fail again
                    self.echo(f"{spec.name} exited with {code}: it refused its configuration (its last lines say why); "
                              "not restarting it" + ("" if spec.essential else " (not essential: the others go on)"))
                    if spec.essential:
                        self.exit_code = EXIT_CONFIG
                        self.finished.set()
                        return
                    continue
                if self.restarts[spec.name] >= self.max_restarts and not spec.essential:
                    self.echo(f"{spec.name} exited with {code}; restarted {self.max_restarts} times already: "
                              "giving up on it (not essential: the others go on)")
                    self.restarts[spec.name] += 1
                    continue
                if self.restarts[spec.name] >= self.max_restarts:
                    self.echo(f"{spec.name} exited with {code}; restarted {self.max_restarts} times already: giving up")
                    self.restarts[spec.name] += 1
                    self.exit_code = 1
                    self.finished.set()
                    return
                self.restarts[spec.name] += 1
                self.echo(f"{spec.name} exited with {code}; restarting (restart {self.restarts[spec.name]})")
                time.sleep(self.restart_delay_s)
                self._spawn(spec)

    def run(self, poll_s: float = 0.1) -> int:
        """Supervise until a finishing child ends or SIGINT/SIGTERM; then stop everything."""
        self.signalled.install()
        try:
            while not (self.signalled or self.finished.wait(poll_s)):
                self.poll()
        finally:
            self.stop()
        return self.exit_code

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
        live = [(name, p) for name, p in reversed(list(self.procs.items())) if p.poll() is None]
        for _name, p in live:
            p.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        grace = {s.name: self.stop_timeout_s if s.stop_timeout_s is None else s.stop_timeout_s for s in self.specs}
        for name, p in live:
            try:
                p.wait(max(0.0, sent + grace[name] - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.echo(f"{name} (pid {p.pid}) did not stop in {grace[name]:g} s: killing it")
                p.kill()
                p.wait()
        self.echo("all processes stopped")


def python_module_argv(module: str, *args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", module, *args)
