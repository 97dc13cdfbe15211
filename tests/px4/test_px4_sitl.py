"""Real PX4 v1.16.0 SITL flying the world: `neso up --vehicle px4` (PX4 built by `make setup`, the world as
its simulator over TCP 4560 in lockstep, real MAVSDK over UDP, real Zenoh, real processes).

One flight (tests/px4/conftest.py), tests in file order: PX4 boots and fuses the motion capture (EKF2 external
vision), the operator flow (offboard, arm, the controller's take-off and hover) with PX4's own answers, PX4's own
land and land detector disarming it, and the recording. (PX4's offboard-loss failsafe flies in
test_px4_failsafe.py, a flight of its own: re-arming after this landing was refused in one run for minutes, "High
Accelerometer Bias".) Figures are printed (pytest -s) for the README."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np

from tests.busutil import REPO, wait_for

def test_px4_boots_on_the_world_and_fuses_motion_capture(flight):
    wait_for("PX4 connects to the world's simulator port", lambda: flight.log("PX4 connected from"), 60)
    connected = wait_for("the gateway reaches PX4 over MAVSDK", lambda: (t := flight.telemetry()) and t.connected, 60)
    assert connected
    # as an operator does: PX4's own "Ready for takeoff" first (EKF2 settled on the motion capture)
    wait_for("PX4 says it is ready for takeoff", lambda: flight.log("Ready for takeoff"), 60)
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
    # it replays as any flight does: another estimator configuration flown offline on what was recorded
    replay = subprocess.run([sys.executable, "-m", "cli.main", "replay", str(path), "--what-if", "pathway=eso"],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert replay.returncode == 0 and "'pathway': 'eso'" in replay.stdout, replay.stdout + replay.stderr
    samples = int(replay.stdout.split(" over ")[1].split()[0])
    assert samples > 400, replay.stdout
    print(replay.stdout.strip())
