"""Real PX4 v1.16.0 SITL flying the world: `neso up --vehicle px4 --duration 78` (PX4 built by `make setup`, the
world as its simulator over TCP 4560 in lockstep, real MAVSDK over UDP, real Zenoh, real processes), flown by the
operator's commands through the real CLI (`neso cmd …`).

One flight (tests in file order): PX4 boots, takes the global origin and fuses the motion capture (EKF2 external
vision); offboard and arm; the controller's take-off and hover, landing test, lemniscate and its own landing, after
which PX4's land detector disarms the vehicle; `neso up` ends by itself after 78 s and leaves one recording, with
PX4's version, that replays. (PX4's own Land and its offboard-loss failsafe fly in test_px4_failsafe.py and
test_px4_controller_lost.py, flights of their own.) Figures are printed (pytest -s) for docs/px4.md."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from tests.busutil import REPO, wait_for
from tests.px4.conftest import px4_flight

DURATION_S = 78  # 90 with the mission's 5 lemniscate cycles: the same 12 s left after the landing
LEMNISCATE_CYCLES = 3  # of 6 s each: enough to show the z figure and no limit cycle, 12 s shorter than the mission's 5


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    with px4_flight(tmp_path_factory, "--duration", str(DURATION_S)) as f:
        yield f


def operator(flight, *args: str) -> str:
    """``neso cmd ARGS`` must be accepted; what it printed."""
    done = flight.cli("cmd", *args)
    assert done.returncode == 0 and done.stdout.startswith("ok"), (args, done.stdout, done.stderr)
    return done.stdout


def fly(flight, mission: str, timeout_s: float, *args: str) -> np.ndarray:
    """The controller's ``mission`` (with ``args``, ``name=value``) from the CLI, until its reference is back to
    hover; the errors truth − reference (m, ENU, n × 3) over the mission's own segment. No crash meanwhile."""
    start = flight.probe.get("reference")[-1].seq
    operator(flight, "controller", mission, *args)
    flight.probe.wait_for("reference", lambda m: m.seq > start and m.segment == mission, 15.0)
    flight.probe.wait_for("reference", lambda m: m.seq > start and m.segment == "hover" and
                          any(r.segment == mission and r.seq < m.seq for r in flight.probe.get("reference")[-3000:]),
                          timeout_s)
    ref = {m.seq: m for m in flight.probe.get("reference") if m.seq > start and m.segment == mission}
    truth = [m for m in flight.probe.get("truth") if m.seq in ref]
    assert not any(m.crashed for m in flight.probe.get("truth") if m.seq > start)
    return np.array([np.subtract(m.pos_enu_m, ref[m.seq].pos_enu_m) for m in truth])


def rms_cm(err: np.ndarray) -> np.ndarray:
    return np.sqrt((err ** 2).mean(0)) * 100


def test_px4_boots_on_the_world_takes_the_origin_and_fuses_motion_capture(flight):
    wait_for("PX4 connects to the world's simulator port", lambda: flight.log("PX4 connected from"), 60)
    connected = wait_for("the gateway reaches PX4 over MAVSDK", lambda: (t := flight.telemetry()) and t.connected, 60)
    assert connected
    # indoors, without GPS: the gateway's global origin (SET_GPS_GLOBAL_ORIGIN), which PX4 reports back
    wait_for("PX4 reports the global origin", lambda: flight.log("the vehicle's global origin is set"), 30)
    # as an operator does: PX4's own "Ready for takeoff" first (EKF2 settled on the motion capture)
    wait_for("PX4 says it is ready for takeoff", lambda: flight.log("Ready for takeoff"), 60)
    wait_for("offboard accepted (setpoints streaming)",
             lambda: flight.cli("cmd", "px4_gateway", "offboard_start").returncode == 0, 30, 1.0)
    armed = wait_for("PX4 arms: EKF2 fuses the motion capture (external vision)",
                     lambda: flight.cli("cmd", "px4_gateway", "arm").returncode == 0, 60, 1.0)
    print(f"\nPX4 SITL: armed {time.monotonic() - flight.t0:.1f} s after neso up")
    assert armed and wait_for("PX4 reports armed", lambda: flight.telemetry().armed, 5)
    assert flight.telemetry().autopilot.startswith("PX4 v1.16.0")  # PX4's AUTOPILOT_VERSION, through MAVSDK


def test_the_controller_takes_off_and_hovers_through_px4_on_the_px4_gains(flight):
    operator(flight, "controller", "arm")
    err = fly(flight, "takeoff", 20)
    wait_for("PX4's land detector says in the air", lambda: flight.telemetry().in_air, 10)
    time.sleep(2.0)
    ref = {m.seq: m for m in flight.probe.get("reference")}
    hover = np.array([np.subtract(m.pos_enu_m, ref[m.seq].pos_enu_m)
                      for m in flight.probe.get("truth")[-100:] if m.seq in ref])
    tele = flight.telemetry()
    print(f"take-off: RMS {rms_cm(err).round(1)} cm; hover 2 s: RMS {rms_cm(hover).round(1)} cm; PX4 mode "
          f"{tele.flight_mode}; hover thrust learnt by the gateway {tele.hover_thrust_norm:.3f}")
    assert tele.flight_mode == "offboard"
    assert rms_cm(hover)[2] < 5.0, "height held"
    assert np.abs(hover[:, :2]).max() < 0.1, "no limit cycle (the paper's xy gains: ±0.2 m on PX4)"


def test_the_landing_test_through_px4(flight):
    err = fly(flight, "landing_test", 30)
    print(f"landing test on PX4: RMS {rms_cm(err).round(1)} cm over {len(err)} samples")
    assert rms_cm(err)[2] < 5.0 and np.abs(err[:, :2]).max() < 0.15


def test_the_lemniscate_through_px4(flight):
    err = fly(flight, "lemniscate", 50, f"cycles={LEMNISCATE_CYCLES}")
    assert len(err) >= LEMNISCATE_CYCLES * 6 * 50, len(err)  # the cycles asked, flown
    print(f"lemniscate on PX4: RMS {rms_cm(err).round(1)} cm over {len(err)} samples, |xy| at most "
          f"{np.abs(err[:, :2]).max() * 100:.0f} cm")
    assert rms_cm(err)[2] < 5.0, "z: the experiments' figure"
    assert flight.telemetry().flight_mode == "offboard"


def test_the_controllers_landing_and_px4s_land_detector_disarms(flight):
    """Timed in PX4's own clock (the world's: PX4 SITL steps in lockstep with it), from the controller's first
    landing reference to the telemetry's first "disarmed": its descent and 1 s on the floor, PX4's land detector,
    COM_DISARM_LAND 2 s. On the wall clock a loaded machine stretches all of it (and the CLI's own start).
    Landed from a settled hover, as an operator does: the lemniscate ends mid-figure at ~2 m/s and the reference
    steps to the hover point; a land commanded 1.2 s after it (seen once, with one core busy), the vehicle 0.5 m
    off and at 1 m/s at 0.25 m, met the floor moving: a crash, PX4's failure detector ("Attitude failure (roll)")
    and no disarm."""
    wait_for("a settled hover (within 10 cm, under 0.2 m/s for 0.5 s)", flight.hover_settled, 30)
    n0, asked = len(flight.output), time.monotonic()
    operator(flight, "controller", "land")
    try:
        disarmed = wait_for("PX4 disarms by itself once its land detector says landed", lambda: next(
            (t for t in flight.probe.get("telemetry") if t.stamp_s > asked and not t.armed), None), 120)
    finally:
        print("".join(line for line in flight.output[n0:] if "health" not in line)[-3000:])
    landing_s = next(m.t_s for m in flight.probe.get("reference") if m.stamp_s > asked and m.segment == "land")
    (disarmed_s,) = wait_for("the world's time then", lambda: next(
        ((m.t_s,) for m in flight.probe.get("truth") if m.stamp_s >= disarmed.stamp_s), None), 5)
    print(f"the controller's landing: PX4 disarmed {disarmed_s - landing_s:.1f} s of PX4's time after it began")
    assert disarmed_s - landing_s < 10.0, "descent and settling ~2 s, land detector ~1 s, COM_DISARM_LAND 2 s"
    assert flight.log("Landing detected", n0) and flight.log("Disarmed by landing", n0)  # PX4's own words
    truth = flight.probe.get("truth")[-1]
    assert truth.on_ground and not truth.crashed and not flight.telemetry().in_air


def test_neso_up_ends_after_its_duration_and_leaves_one_recording_that_replays(flight):
    from recordings.reader import read_recording

    assert flight.proc.wait(timeout=DURATION_S + 60) == 0, "".join(flight.output[-30:])
    print(f"neso up --duration {DURATION_S} ended by itself {time.monotonic() - flight.t0:.0f} s after it started")
    paths = sorted(flight.recordings.glob("*.rrd"))
    assert len({p.name.split(".seg")[0] for p in paths}) == 1, paths  # one flight (its segments, if any)
    rec = read_recording(paths[0])
    assert len(rec.channel("truth")) > 2000 and len(rec.channel("setpoint")) > 2000
    assert [a.split()[:2] for a in rec.properties["summary"]["autopilots"]] == [["PX4", "v1.16.0"]]
    said = [m.status_text for m in rec.channel("telemetry").messages() if m.status_text]
    assert any("Disarmed by landing" in s for s in said), "PX4's own words reach the telemetry (and the dashboard)"
    # it replays as any flight does: another estimator configuration flown offline on what was recorded
    replay = subprocess.run([sys.executable, "-m", "cli.main", "replay", str(paths[0]), "--what-if", "pathway=eso"],
                            cwd=REPO, capture_output=True, text=True, timeout=180)
    assert replay.returncode == 0 and "'pathway': 'eso'" in replay.stdout, replay.stdout + replay.stderr
    samples = int(replay.stdout.split(" over ")[1].split()[0])
    print(f"recorded: {len(rec.channel('truth'))} samples in {len(paths)} segment(s); replayed over {samples}")
    assert samples > 2000, replay.stdout
