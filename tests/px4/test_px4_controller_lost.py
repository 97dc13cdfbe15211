"""The controller killed mid-lemniscate with real PX4 v1.16.0 SITL (on the tier's shared flight: tests/px4/conftest.py): its setpoints stop, the
gateway's failsafe commands PX4's Hold (available indoors because the gateway gave PX4 a global origin), then, with
no operator, PX4's own Land; PX4's land detector disarms. Nothing of the recording is lost."""
from __future__ import annotations

import os
import signal
import time

import numpy as np

from tests.busutil import role_pid, wait_for


def test_the_controller_killed_mid_lemniscate_px4_holds_then_lands_and_disarms(flight):
    from recordings.reader import read_recording

    flight.into_lemniscate()
    before = len(flight.output)
    killed_s = time.monotonic()
    at = np.array(flight.probe.get("truth")[-1].pos_enu_m)
    os.kill(role_pid(flight.proc.pid, "controller"), signal.SIGKILL)
    wait_for("PX4 in Hold", lambda: flight.telemetry().flight_mode == "hold", 5, 0.02)
    hold_s = time.monotonic() - killed_s
    wait_for("PX4 lands and disarms", lambda: not flight.telemetry().armed, 30)
    said = flight.output[before:]
    truth = [m for m in flight.probe.get("truth") if m.stamp_s > killed_s]
    pos = np.array([m.pos_enu_m for m in truth])
    print(f"\ncontroller killed mid-lemniscate: PX4 in Hold {hold_s:.2f} s later; farthest from where it was "
          f"{np.linalg.norm(pos[:, :2] - at[:2], axis=1).max():.2f} m; disarmed {time.monotonic() - killed_s:.1f} s "
          f"after the kill; ends at {np.round(pos[-1], 2)} m")
    assert hold_s < 1.5, "the gateway's failsafe: hold after 0.3 s of unanswered states (or 1 s of none)"
    assert any("commanding hold" in line for line in said) and any("commanding land" in line for line in said)
    assert any("Landing detected" in line for line in said) and any("Disarmed by landing" in line for line in said)
    assert truth[-1].on_ground and not any(m.crashed for m in truth)
    path = wait_for("the recorder closes the flight", lambda: sorted(flight.recordings.glob("*.rrd")), 20)[-1]  # the newest
    time.sleep(2.0)
    rec = read_recording(path)
    modes = {m.flight_mode for m in rec.channel("telemetry").messages() if m.stamp_s > killed_s - 5}
    assert {"offboard", "hold", "land"} <= modes, modes  # the recorder, its own process, kept all of it
