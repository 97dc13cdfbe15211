"""Helpers for bus and process tests: free ports, real Zenoh sessions, `neso` subprocesses, collectors."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager

from runtime.bus import BusConfig, hub_config, open_session
from runtime.schema import TOPICS, Keys, SchemaError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peer(endpoint: str) -> BusConfig:
    return BusConfig(connect=(endpoint,))


@contextmanager
def session(config: BusConfig):
    s = open_session(config)
    try:
        yield s
    finally:
        s.close()


@contextmanager
def hub(endpoint: str):
    with session(hub_config(endpoint)) as s:
        yield s


class Collector:
    """Every valid message of some topics of one vehicle, in arrival order, with arrival times."""

    def __init__(self, s, vehicle: str = "uav1", topics=("state", "truth", "estimate", "setpoint", "reference")):
        self.keys = Keys(vehicle)
        self.lock = threading.Lock()
        self.messages: dict[str, list] = {t: [] for t in topics}
        self.arrivals: dict[str, list[float]] = {t: [] for t in topics}
        self.subs = [s.declare_subscriber(self.keys.topic(t), self._handler(t)) for t in topics]

    def _handler(self, topic):
        cls = TOPICS[topic]

        def on_sample(sample):
            now = time.monotonic()
            try:
                msg = cls.from_bytes(sample.payload.to_bytes())
            except SchemaError:
                return
            with self.lock:
                self.messages[topic].append(msg)
                self.arrivals[topic].append(now)
        return on_sample

    def get(self, topic: str) -> list:
        with self.lock:
            return list(self.messages[topic])

    def wait_for(self, topic: str, predicate, timeout_s: float):
        """The first message of ``topic`` (arriving from now on, or already there) satisfying ``predicate``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for msg in reversed(self.get(topic)):
                if predicate(msg):
                    return msg
            time.sleep(0.01)
        raise AssertionError(f"no {topic} message satisfying the condition within {timeout_s} s")


def neso(*args: str, **kwargs) -> subprocess.Popen:
    """A `neso ...` subprocess in its own process group, output captured to a file-like pipe."""
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env=dict(os.environ, PYTHONUNBUFFERED="1"), **kwargs)


def stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> str:
    """SIGINT the process (as Ctrl-C would), wait, and return its output; kill the group if stuck."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
    return out or ""


def pids_in_group(pgid: int) -> list[int]:
    out = []
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                if os.getpgid(int(pid)) == pgid:
                    out.append(int(pid))
            except ProcessLookupError:
                pass
    return out


def children_of(pid: int) -> list[int]:
    """Direct children of ``pid`` (from /proc)."""
    kids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        kids.append(int(d))
            except (FileNotFoundError, ProcessLookupError, IndexError):
                pass
    return kids


def role_pid(launcher_pid: int, role: str) -> int:
    """The pid of the ``neso run <role>`` child of a ``neso up`` launcher."""
    for pid in children_of(launcher_pid):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except FileNotFoundError:
            continue
        if b"run" in argv and argv.index(b"run") + 1 < len(argv) and argv[argv.index(b"run") + 1] == role.encode():
            return pid
    raise AssertionError(f"no {role} process under the launcher")
