"""Failsafes with real PX4 v1.16.0 SITL: `neso up --vehicle px4`, a take-off through the controller, then kill -9
of the estimator mid-hover (the controller's local ESO flies on; the launcher restarts it) and then of the gateway
mid-lemniscate (PX4's own offboard-loss failsafe) (on the tier's shared flight: tests/px4/conftest.py)."""
from __future__ import annotations

import os
import signal
import time

import numpy as np

from tests.busutil import role_pid, wait_for


def test_the_estimator_killed_mid_hover_the_controller_flies_its_local_eso_through_px4(flight):
    """kill -9 of the estimator: within 3 periods the controller's setpoints come from its local ESO, PX4 stays in
    offboard and the vehicle at its height; the restarted estimator's estimates fly again."""
    flight.airborne()
    start = flight.probe.get("setpoint")[-1].seq
    old = role_pid(flight.proc.pid, "estimator")
    os.kill(old, signal.SIGKILL)
    local = flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "local_eso" and m.seq > start, 2.0)
    last = max(m.seq for m in flight.probe.get("setpoint") if m.estimate_source == "estimator" and m.seq < local.seq)
    back = flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > local.seq, 30.0)
    time.sleep(1.0)
    assert role_pid(flight.proc.pid, "estimator") != old, "the launcher restarted it"
    truth = [m for m in flight.probe.get("truth") if m.seq >= start]
    z = np.array([m.pos_enu_m[2] for m in truth])
    print(f"\nestimator killed: local ESO after {local.seq - last} samples, estimator back {back.seq - local.seq} "
          f"samples later; height {z.min():.2f}–{z.max():.2f} m meanwhile")
    assert local.seq - last <= 4, (last, local.seq)
    assert flight.telemetry().flight_mode == "offboard" and not any(m.crashed for m in truth)
    assert np.abs(z - 1.0).max() < 0.15, "the height held on the local ESO"


def test_the_gateway_killed_mid_lemniscate_px4s_own_failsafe_within_com_of_loss_t(flight):
    """kill -9 of the gateway mid-lemniscate: its setpoint stream stops; PX4's own offboard-loss action
    (COM_OF_LOSS_T 0.3 s, then COM_OBL_RC_ACT: Hold, sim/px4/neso_quad.params) within 0.8 s; the vehicle brakes and
    holds where it is. The restarted gateway leaves PX4 in its Hold (it streams no setpoints into a mode of the
    vehicle's own) until the operator's `land`: PX4's own Land, and its land detector disarms."""
    flight.into_lemniscate()
    before = len(flight.output)
    killed = time.monotonic()
    os.kill(role_pid(flight.proc.pid, "px4_gateway"), signal.SIGKILL)
    wait_for("PX4's failsafe", lambda: any("Failsafe activated" in line for line in flight.output[before:]), 5, 0.02)
    after = time.monotonic() - killed
    wait_for("the restarted gateway reports", lambda: (t := flight.telemetry()) and t.stamp_s > killed + 1, 20)
    time.sleep(4.0)
    seen = []  # (armed, PX4's mode) as the restarted gateway reported them, in order, each change once
    for t in flight.probe.get("telemetry"):
        if t.stamp_s > killed + 1 and t.connected and (not seen or seen[-1] != (t.armed, t.flight_mode)):
            seen.append((t.armed, t.flight_mode))
    truth = [m for m in flight.probe.get("truth") if m.stamp_s > killed]
    speed = np.linalg.norm(truth[-1].vel_enu_mps)
    print(f"gateway killed: PX4's failsafe {after:.2f} s later; then (armed, PX4 mode) {seen}; the vehicle at "
          f"{np.round(truth[-1].pos_enu_m, 2)} m, {speed:.2f} m/s, crashed {truth[-1].crashed}")
    assert after < 0.8
    assert flight.telemetry().flight_mode == "hold" and flight.telemetry().armed, seen
    assert not any(m.crashed for m in truth) and truth[-1].pos_enu_m[2] > 0.1 and speed < 0.3, "holding, in the air"
    start = time.monotonic()
    assert flight.cmd("px4_gateway", "land").ok  # the operator: PX4's AUTO.LAND (it needs only a local position)
    wait_for("PX4 disarms by itself once its land detector says landed", lambda: not flight.telemetry().armed, 30)
    print(f"PX4's own land from its hold: disarmed {time.monotonic() - start:.1f} s after the command")
    assert flight.log("Landing detected", before) and flight.log("Disarmed by landing", before)  # PX4's own words
    last = flight.probe.get("truth")[-1]
    assert last.on_ground and not last.crashed
