"""The px4 tier's flight: `neso up --vehicle px4` on a free PX4 instance (``flight``: one shared by the modules that
use it, one after another; a module with flags of its own opens its own with :func:`px4_flight`)."""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from cli.paper_px4 import free_px4_instance, release_px4_instance
from runtime.client import command
from sim.px4_sitl import missing_px4
from tests.busutil import REPO, NesoUp, free_port, peer, wait_for
from tests.px4 import px4_env

TOPICS = ("state", "truth", "setpoint", "reference", "telemetry", "recording")


class Px4Flight(NesoUp):
    """``neso up --vehicle px4`` with ``extra`` flags, its recordings under ``tmp``."""

    def __init__(self, tmp, *extra: str):
        endpoint = self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        old = dict(os.environ)
        os.environ.update(px4_env(tmp))
        self.instance = free_px4_instance()  # held by this test process until close()
        try:
            self.t0 = time.monotonic()
            super().__init__("--vehicle", "px4", "--px4-instance", str(self.instance), "--hub", endpoint,
                             "--no-trainer", "--no-dashboard", "--recordings-dir", str(tmp / "recordings"), *extra,
                             bus=peer(endpoint), topics=TOPICS)
        finally:
            os.environ.clear()
            os.environ.update(old)
        self.recordings = tmp / "recordings"

    def close(self, *, kill: bool = False) -> str:
        try:
            return super().close(kill=kill)
        finally:
            release_px4_instance(self.instance)

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        """``neso ARGS`` as an operator types it, connected to this flight's hub."""
        return subprocess.run([sys.executable, "-m", "cli.main", *args, "--connect", self.endpoint], cwd=REPO,
                              capture_output=True, text=True, timeout=60)

    def cmd(self, service: str, name: str, **args):
        return command(self.s, self.probe.keys, service, name, args, timeout_s=8.0)

    def newest_ulog(self):
        """PX4's newest ULog (the current arming's; PX4 writes it as it flies, so it may end a moment behind)."""
        from pathlib import Path

        from cli.up import px4_workdir

        return max(Path(px4_workdir(self.instance, "uav1")).glob("log/*/*.ulg"), key=lambda p: p.stat().st_mtime)

    def telemetry(self):
        got = self.probe.get("telemetry")
        return got[-1] if got else None

    def log(self, text: str, since: int = 0) -> bool:
        """Whether a process said ``text`` in a line of :attr:`output` from index ``since`` on (the shared flight's
        output holds the modules' before it too)."""
        return any(text in line for line in self.output[since:])

    def hover_settled(self) -> bool:
        """Whether the last 0.5 s (25 samples) hovered within 10 cm of the hover reference, under 0.2 m/s."""
        ref = {m.seq: m for m in self.probe.get("reference")[-50:]}
        last = [m for m in self.probe.get("truth")[-50:] if m.seq in ref]
        return len(last) >= 25 and all(np.linalg.norm(np.subtract(m.pos_enu_m, ref[m.seq].pos_enu_m)) < 0.1 and
                                       np.linalg.norm(m.vel_enu_mps) < 0.2 and ref[m.seq].segment == "hover"
                                       for m in last)

    def airborne(self) -> None:
        """The operator's flow to a hover at 1 m (PX4's "Ready for takeoff", offboard, arm, the controller's
        take-off), then a settled hover (:meth:`hover_settled`; 2 s after 0.9 m, with a core busy, the vehicle was
        once still at 1.28 m: loaded run 24); nothing if it is already up."""
        truth = self.probe.get("truth")
        if truth and truth[-1].pos_enu_m[2] > 0.9:
            return
        wait_for("PX4 says it is ready for takeoff", lambda: self.log("Ready for takeoff"), 60)
        wait_for("offboard accepted", lambda: self.cmd("px4_gateway", "offboard_start").ok, 30, 1.0)
        wait_for("PX4 arms", lambda: self.cmd("px4_gateway", "arm").ok, 60, 1.0)
        assert self.cmd("controller", "arm").ok and self.cmd("controller", "takeoff").ok
        wait_for("airborne", lambda: self.probe.get("truth")[-1].pos_enu_m[2] > 0.9, 30)
        time.sleep(2.0)
        wait_for("a settled hover (within 10 cm, under 0.2 m/s for 0.5 s)", self.hover_settled, 30)

    def into_lemniscate(self, seconds: float = 8.0) -> None:
        """Airborne, then the controller's lemniscate flown for ``seconds`` (into the figure eight, at speed)."""
        self.airborne()
        assert self.cmd("controller", "lemniscate").ok
        self.probe.wait_for("reference", lambda m: m.segment == "lemniscate", 15.0)
        time.sleep(seconds)


@contextlib.contextmanager
def px4_flight(tmp_path_factory, *extra: str):
    """A :class:`Px4Flight` with ``extra`` flags; afterwards what every process said is kept in the test's folder
    (``flight.log``, to read after a failure) and must hold no traceback."""
    assert not missing_px4(), missing_px4()  # make setup builds it (tests/README.md)
    tmp = tmp_path_factory.mktemp("px4")
    f = Px4Flight(tmp, *extra)
    yield f
    out = f.close()
    (tmp / "flight.log").write_text(out)
    assert "Traceback" not in out, out[-4000:]


_shared: dict = {}  # the flight the modules of the default ``flight`` share: "context", "flight", "last"


def _shares(item) -> bool:
    """Whether ``item`` (a test, or None) flies the default ``flight`` (its module defines none of its own)."""
    return item is not None and "flight" in item.fixturenames and "flight" not in vars(item.module)


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_teardown(item, nextitem):
    """Before a test's fixtures end: whether the next test to run still flies the shared flight."""
    if _shares(item):
        _shared["last"] = not _shares(nextitem)


#: How long a module waits for the shared PX4 to arm after the module before it landed
REARM_WAIT_S = 20.0


def arm_refusal(f: Px4Flight, timeout_s: float) -> str:
    """Empty once the shared PX4 arms (offboard, then arm, through the gateway, as :meth:`Px4Flight.airborne` does)
    within ``timeout_s``, else the last refusal. A real arm, not the preflight verdict: after PX4's own failsafe
    landing the verdict once said GO and PX4 still denied every arm for 60 s ("Preflight Fail: High Accelerometer
    Bias", a check it runs only when asked to arm: quiet run 18). PX4 is left armed: it denies a disarm until its
    land detector says landed, which it did not within 23 s of an arm with the controller idle (measured); the
    module's first :meth:`Px4Flight.airborne` takes off from there (PX4 accepts an arm when armed)."""
    deadline, refusal = time.monotonic() + timeout_s, ""
    while time.monotonic() < deadline:
        reply = f.cmd("px4_gateway", "offboard_start")
        if reply.ok:
            reply = f.cmd("px4_gateway", "arm")
        if reply.ok:
            return ""
        refusal = reply.message
        time.sleep(1.0)
    return refusal or f"no arm within {timeout_s:g} s"


def _close_shared() -> None:
    """Ends the shared flight (and checks its log: :func:`px4_flight`)."""
    _shared.pop("flight")
    _shared.pop("context").__exit__(None, None, None)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """One PX4 flight shared by the modules that use this fixture, one after another (the controller lost, the
    failsafes, motion capture lost: each test takes off again with :meth:`Px4Flight.airborne` after the one before
    left it landed and disarmed): one PX4 boot for them instead of one each (~15 s with its start and stop). It
    ends, and its log is checked, once the next test to run flies something else.

    A module that finds the shared PX4 refusing to arm for :data:`REARM_WAIT_S` (:func:`arm_refusal`) gets a fresh
    boot, as a module of its own had before: seen after PX4's own failsafe landing, its EKF2 said "Preflight Fail:
    High Accelerometer Bias" for the next 120 s (quiet runs at 19be7b4 and 6b83cc1) — a vehicle an operator would
    power-cycle, and not what the next module is about."""
    if "context" in _shared:
        try:
            refusal = arm_refusal(_shared["flight"], REARM_WAIT_S)
        except BaseException:  # its processes and PX4 stopped, not left running after the run
            _close_shared()
            raise
        if refusal:
            print(f"\nthe shared PX4 still refuses to arm {REARM_WAIT_S:g} s into this module: a fresh boot\n{refusal}")
            _close_shared()
    if "context" not in _shared:
        _shared["context"] = px4_flight(tmp_path_factory)
        _shared["flight"] = _shared["context"].__enter__()
    yield _shared["flight"]
    if _shared.pop("last", False):
        _close_shared()
