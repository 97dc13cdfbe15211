"""Real PX4 v1.16.0 SITL flying the world: `neso up --vehicle px4` (PX4 built by `make setup`, the world as
its simulator over TCP 4560 in lockstep, real MAVSDK over UDP, real Zenoh, real processes).

One flight, tests in file order: PX4 boots and fuses the motion capture (EKF2 external vision), the operator
flow (offboard, arm, the controller's take-off and hover) with PX4's own answers, PX4's own land and land
detector disarming it, and the recording. (The controller's own landing is not flown here: with PX4's default
attitude gains the controller's hover is a ±20 cm limit cycle at ~0.8 Hz, and a touch-down at that horizontal
speed is a crash by the world's rule; README "PX4 in the loop".) Figures are printed (pytest -s) for the README."""
from __future__ import annotations

import os
import time

import numpy as np
import pytest

from runtime.client import command
from sim.px4_sitl import missing_px4, px4_home
from tests.busutil import NesoUp, free_port, peer

TOPICS = ("state", "truth", "setpoint", "reference", "telemetry", "recording")


def wait_for(what: str, check, timeout_s: float, every_s: float = 0.2):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = check()
        if value:
            return value
        time.sleep(every_s)
    raise AssertionError(f"not within {timeout_s:.0f} s: {what}")


class Px4Flight(NesoUp):
    def __init__(self, tmp):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        old = dict(os.environ)
        # MAVSDK writes its cache under $HOME/.cache/mavsdk: a HOME of the test's own; PX4 stays where make setup put it
        os.environ.update(HOME=str(tmp), NESO_PX4_HOME=str(px4_home()))
        try:
            self.t0 = time.monotonic()
            super().__init__("--vehicle", "px4", "--hub", endpoint, "--no-trainer", "--no-dashboard",
                             "--recordings-dir", str(tmp / "recordings"), bus=peer(endpoint), topics=TOPICS)
        finally:
            os.environ.clear()
            os.environ.update(old)
        self.recordings = tmp / "recordings"

    def cmd(self, service: str, name: str, **args):
        return command(self.s, self.probe.keys, service, name, args, timeout_s=8.0)

    def telemetry(self):
        got = self.probe.get("telemetry")
        return got[-1] if got else None

    def log(self, text: str) -> bool:
        return any(text in line for line in self.output)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    assert not missing_px4(), missing_px4()  # make setup builds it (tests/README.md)
    f = Px4Flight(tmp_path_factory.mktemp("px4"))
    yield f
    out = f.close()
    assert "Traceback" not in out, out[-4000:]


def test_px4_boots_on_the_world_and_fuses_motion_capture(flight):
    wait_for("PX4 connects to the world's simulator port", lambda: flight.log("PX4 connected from"), 60)
    connected = wait_for("the gateway reaches PX4 over MAVSDK", lambda: (t := flight.telemetry()) and t.connected, 60)
    assert connected
    # without GPS PX4 arms only in a mode whose needs are met: offboard (needs attitude and the offboard signal)
    wait_for("offboard accepted (setpoints streaming)", lambda: flight.cmd("px4_gateway", "offboard_start").ok, 30, 1.0)
    armed = wait_for("PX4 arms: EKF2 fuses the motion capture (external vision)",
                     lambda: flight.cmd("px4_gateway", "arm").ok, 60, 1.0)
    print(f"\nPX4 SITL: ready to arm {time.monotonic() - flight.t0:.1f} s after neso up")
    assert armed and wait_for("PX4 reports armed", lambda: flight.telemetry().armed, 5)
    assert flight.telemetry().autopilot.startswith("PX4 v1.16.0")  # PX4's AUTOPILOT_VERSION, through MAVSDK


def test_the_controller_takes_off_and_hovers_through_px4(flight):
    assert flight.cmd("controller", "arm").ok
    assert flight.cmd("controller", "takeoff").ok
    wait_for("the vehicle climbs to the take-off height", lambda: flight.probe.get("truth")[-1].pos_enu_m[2] > 0.9, 30)
    wait_for("PX4's land detector says in the air", lambda: flight.telemetry().in_air, 10)
    time.sleep(6.0)
    truth = flight.probe.get("truth")[-250:]  # 5 s at 50 Hz
    ref = {m.seq: m for m in flight.probe.get("reference")}
    err = np.array([np.subtract(m.pos_enu_m, ref[m.seq].pos_enu_m) for m in truth if m.seq in ref])
    rms = np.sqrt((err ** 2).mean(0))
    tele = flight.telemetry()
    print(f"hover on PX4 (5 s): RMS error x {rms[0] * 100:.1f} y {rms[1] * 100:.1f} z {rms[2] * 100:.1f} cm, "
          f"PX4 mode {tele.flight_mode}, PX4 hover thrust learnt by the gateway {tele.hover_thrust_norm:.3f}")
    assert not any(m.crashed for m in truth) and tele.flight_mode == "offboard"
    assert rms[2] < 0.05, "height held"
    assert np.abs(err[:, :2]).max() < 0.5, "stays over the take-off point"


def test_px4s_own_land_brings_it_down_and_its_land_detector_disarms(flight):
    """The gateway's land (what its failsafe commands after hold): PX4's AUTO.LAND, needing only the local
    position EKF2 has from the motion capture."""
    start = time.monotonic()
    assert flight.cmd("px4_gateway", "land").ok
    wait_for("PX4 disarms by itself once its land detector says landed", lambda: not flight.telemetry().armed, 30)
    print(f"PX4 land: disarmed {time.monotonic() - start:.1f} s after the command")
    assert flight.log("Landing detected") and flight.log("Disarmed by landing")  # PX4's own words
    truth = flight.probe.get("truth")[-1]
    assert truth.on_ground and not truth.crashed and not flight.telemetry().in_air


def test_the_flight_is_recorded_and_reads_back(flight):
    from recordings.reader import read_recording

    path = wait_for("the recorder closes the flight", lambda: sorted(flight.recordings.glob("*.rrd")), 20)[0]
    time.sleep(2.0)
    rec = read_recording(path)
    assert len(rec.channel("truth")) > 500 and len(rec.channel("setpoint")) > 500
    assert [a.split()[:2] for a in rec.properties["summary"]["autopilots"]] == [["PX4", "v1.16.0"]]
    said = [m.status_text for m in rec.channel("telemetry").messages() if m.status_text]
    assert said, "PX4's own status texts reach the telemetry (and the dashboard)"
    print(f"recorded: {len(rec.channel('truth'))} samples; PX4 said, e.g. {said[-1]!r}")
