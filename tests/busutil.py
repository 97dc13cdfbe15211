"""Helpers for bus and process tests: free ports, real Zenoh sessions, `neso` subprocesses
(watching a vehicle's streams is :class:`runtime.probe.Probe`)."""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import warnings
from contextlib import contextmanager
from typing import Callable

from runtime.bus import BusConfig, hub_config, open_session

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peer(endpoint: str) -> BusConfig:
    return BusConfig(connect=(endpoint,))


def secure_peer(endpoint: str, directory: str, identity: str = "operator", *, mode: str = "peer") -> BusConfig:
    """A session on a secure bus as ``identity`` (its certificate in ``directory``); a ``client``
    talks through the hub only (what it sends meets the hub's ACL, which logs refusals)."""
    from runtime.secure import Credentials

    return BusConfig(connect=(endpoint,), listen=("tls/127.0.0.1:0",) if mode == "peer" else (), mode=mode,
                     credentials=Credentials(directory, identity))


def secure_init(directory: str) -> str:
    """`neso secure init DIR` in a subprocess (the real command); DIR."""
    done = subprocess.run([sys.executable, "-m", "cli.main", "secure", "init", directory], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    return directory


@contextmanager
def session(config: BusConfig):
    s = open_session(config)
    try:
        yield s
    finally:
        s.close()


@contextmanager
def timed_step(what: str, warn_after_s: float = 5.0):
    """A teardown step that took longer than ``warn_after_s`` becomes a warning in the run's summary, with its
    seconds and the machine's load: a passing test's output is not shown, and one teardown once took 71 s of a
    loaded run without saying where (tests/browser/test_dashboard_secure.py, loaded run 35)."""
    started = time.monotonic()
    try:
        yield
    finally:
        took_s = time.monotonic() - started
        if took_s > warn_after_s:
            warnings.warn(f"{what} took {took_s:.1f} s (load {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores)",
                          stacklevel=3)


@contextmanager
def hub(endpoint: str):
    with session(hub_config(endpoint)) as s:
        yield s


def neso(*args: str, env: dict | None = None, **kwargs) -> subprocess.Popen:
    """A `neso ...` subprocess in its own process group, output captured to a file-like pipe (``env``:
    the environment, default this one's)."""
    return subprocess.Popen([sys.executable, "-m", "cli.main", *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env=dict(env if env is not None else os.environ, PYTHONUNBUFFERED="1"), **kwargs)


class NesoUp:
    """``neso up ARGS`` as a subprocess (its output collected by a thread into ``output``) and a
    session ``s`` on its bus (``bus``: the hub it listens on, as a peer or an identity) with a
    :class:`runtime.probe.Probe` of ``topics``. :meth:`close` ends both, removes ``workdir`` (a
    folder the flight owns, if given) and returns the output."""

    def __init__(self, *args: str, bus: BusConfig,
                 topics: tuple[str, ...] = ("state", "truth", "estimate", "setpoint", "reference"),
                 workdir: str | None = None) -> None:
        from runtime.probe import Probe

        self.workdir = workdir

        self.proc = neso("up", *args)
        self.output: list[str] = []
        self.output_s: list[float] = []  # when each line of ``output`` arrived (time.monotonic())
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()
        self._session_cm = session(bus)
        self.s = self._session_cm.__enter__()
        self.probe = Probe(self.s, topics=topics)

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.output_s.append(time.monotonic())
            self.output.append(line)

    def close(self, *, kill: bool = False) -> str:
        """Close the session, then Ctrl-C ``neso up`` and wait (``kill``: SIGKILL its process group
        instead); everything it printed."""
        import shutil

        from runtime.launcher import interrupt

        try:
            self.probe.close()
            with timed_step("closing the test's Zenoh session"):
                self._session_cm.__exit__(None, None, None)
            with timed_step(f"{'killing' if kill else 'Ctrl-C of'} neso up until it ended"):
                if kill:
                    if self.proc.poll() is None:
                        os.killpg(self.proc.pid, signal.SIGKILL)
                else:
                    interrupt(self.proc)
            with timed_step("reading the rest of neso up's output"):
                self._pump_thread.join(5.0)
            return "".join(self.output)
        finally:
            if self.workdir is not None:
                shutil.rmtree(self.workdir, ignore_errors=True)


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
            with contextlib.suppress(ProcessLookupError):  # exited since it was listed
                if os.getpgid(int(pid)) == pgid:
                    out.append(int(pid))
    return out


def children_of(pid: int) -> list[int]:
    """Direct children of ``pid`` (from /proc)."""
    kids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            with contextlib.suppress(FileNotFoundError, ProcessLookupError, IndexError):  # exited meanwhile
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        kids.append(int(d))
    return kids


def roles_of(launcher_pid: int) -> dict[str, int]:
    """``{role: pid}`` of the ``neso run <role>`` children of a ``neso up`` launcher (with several vehicles, a
    role's first child)."""
    out: dict[str, int] = {}
    for pid in children_of(launcher_pid):
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except FileNotFoundError:
            continue
        if b"run" in argv and argv.index(b"run") + 1 < len(argv):
            out.setdefault(argv[argv.index(b"run") + 1].decode(errors="replace"), pid)
    return out


def role_pid(launcher_pid: int, role: str) -> int:
    """The pid of the ``neso run <role>`` child of a ``neso up`` launcher."""
    pid = roles_of(launcher_pid).get(role)
    if pid is None:
        raise AssertionError(f"no {role} process under the launcher")
    return pid


def wait_for(what: str, check, timeout_s: float, every_s: float = 0.2):
    """``check()``'s first truthy value within ``timeout_s`` (polled every ``every_s``), else AssertionError naming
    ``what``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError(f"not within {timeout_s:.0f} s: {what}")


def flood_windows(session, keys, payloads: dict[str, list[bytes]], latest_seq: Callable[[], int], windows: int,
                  per_key_per_s: int = 2000) -> dict[str, list[tuple[int, int]]]:
    """``windows`` 1 s windows, quiet and flooded in turn (quiet first), on ``session``: in each flooded one
    ``per_key_per_s`` of ``payloads[topic]`` (the next ones in order) put on every topic's key, 100 at a time, paced
    over the second; sent to the other processes only (``Locality.REMOTE``: this session's own subscribers, e.g. a
    probe, never decode them). The ``(first, end)`` samples (``latest_seq()`` at each window's edges) per kind,
    ``"quiet"`` and ``"flood"``."""
    import zenoh

    pubs = {t: session.declare_publisher(keys.topic(t), congestion_control=zenoh.CongestionControl.BLOCK,
                                         allowed_destination=zenoh.Locality.REMOTE) for t in payloads}
    spans: dict[str, list[tuple[int, int]]] = {"quiet": [], "flood": []}
    try:
        for w in range(windows):
            kind, first, t0 = ("flood" if w % 2 else "quiet"), latest_seq(), time.monotonic()
            if kind == "flood":
                for j, i in enumerate(range(w // 2 * per_key_per_s, (w // 2 + 1) * per_key_per_s)):
                    for topic, sent in payloads.items():
                        pubs[topic].put(sent[i])
                    if j % 100 == 99:
                        time.sleep(max(0.0, t0 + (j + 1) / per_key_per_s - time.monotonic()))
            time.sleep(max(0.0, t0 + 1.0 - time.monotonic()))
            spans[kind].append((first, latest_seq()))
    finally:
        for pub in pubs.values():
            pub.undeclare()
    return spans
