"""`neso up --process-per-role`: one estimator, one controller and one recorder process serve two vehicles.

Both vehicles fly on their own estimates (a thread and a Zenoh session per vehicle in the shared
processes); `kill -9` of the shared estimator puts both on their controller's local ESO until the
supervisor has restarted it, then both fly on estimates again; Ctrl-C ends every thread and each
vehicle's recording is written.
"""
from __future__ import annotations

import os
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path

from runtime.schema import SetpointMsg
from tests.busutil import NesoUp, children_of, free_port, peer, role_pid

VEHICLES = ("a", "b")


class SharedFlight(NesoUp):
    def __init__(self) -> None:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.rec = tempfile.mkdtemp(prefix="neso-per-role-")
        args = ["--process-per-role", "--scenario", "nominal_landing", "--mission", "hover", "--hub", endpoint,
                "--no-dashboard", "--no-trainer", "--recordings-dir", self.rec]
        for v in VEHICLES:
            args += ["--name", v]
        super().__init__(*args, bus=peer(endpoint), topics=())
        self.lock = threading.Lock()
        self.setpoints: dict[str, list[SetpointMsg]] = {v: [] for v in VEHICLES}
        self.s.declare_subscriber("neso/*/setpoint", self._on_setpoint)

    def _on_setpoint(self, sample) -> None:
        msg = SetpointMsg.from_bytes(sample.payload.to_bytes())
        with self.lock:
            self.setpoints[str(sample.key_expr).split("/")[1]].append(msg)

    def sources_since(self, n: dict[str, int]) -> dict[str, list[str]]:
        """Per vehicle, the estimate source of each setpoint after the first ``n[vehicle]``."""
        with self.lock:
            return {v: [m.estimate_source for m in self.setpoints[v][n[v]:]] for v in VEHICLES}

    def counts(self) -> dict[str, int]:
        with self.lock:
            return {v: len(self.setpoints[v]) for v in VEHICLES}

    def wait(self, condition, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, f"{what} within {timeout_s} s; output:\n{''.join(self.output)[-3000:]}"
            time.sleep(0.1)


def test_two_vehicles_fly_on_one_estimator_and_one_controller_process_and_survive_its_kill():
    flight = SharedFlight()
    try:
        launcher = flight.proc.pid
        flight.wait(lambda: min(flight.counts().values()) > 100, 60, "both vehicles flying")
        argv = {pid: Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0") for pid in children_of(launcher)}
        roles = sorted(a[a.index(b"run") + 1].decode() for a in argv.values() if b"run" in a)
        assert roles.count("estimator") == roles.count("controller") == roles.count("recorder") == 1, roles
        assert roles.count("source") == 2, roles
        # the shared estimator starts beside the controller (its network's certificate first): once both vehicles
        # fly on its estimates, they go on doing so
        begun = flight.counts()
        flight.wait(lambda: all(s[-25:].count("estimator") == 25 for s in flight.sources_since(begun).values()), 30,
                    "both vehicles on the estimator's estimates")
        start = flight.counts()
        time.sleep(2.0)
        for v, sources in flight.sources_since(start).items():
            assert len(sources) > 60 and sources.count("estimator") >= 0.95 * len(sources), (v, sources[-20:])

        old = role_pid(launcher, "estimator")
        before_kill = flight.counts()
        os.kill(old, signal.SIGKILL)
        flight.wait(lambda: all("local_eso" in s for s in flight.sources_since(before_kill).values()), 10,
                    "both vehicles on their local ESO")

        def both_back() -> bool:
            return all(s[-25:].count("estimator") == 25 for s in flight.sources_since(before_kill).values())
        flight.wait(both_back, 60, "both vehicles on the restarted estimator's estimates")
        assert role_pid(launcher, "estimator") != old
    finally:
        output = flight.close()
    try:
        assert "Traceback" not in output, output[-3000:]
        for v in VEHICLES:
            assert list(Path(flight.rec).glob(f"{v}-*.rrd")), (v, sorted(os.listdir(flight.rec)), output[-2000:])
    finally:
        shutil.rmtree(flight.rec, ignore_errors=True)
