"""The PX4 gateway's pure parts: frame conversion, sanity limits, hover-thrust learning, the stale-setpoint failsafe."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from neso.frames import (FLU_FROM_FRD, NED_FROM_ENU, attitude_enu_from_ned, attitude_ned_from_enu, matrix_from_quat,
                         quat_ned_from_enu_euler, quat_to_euler_ned, tilt_rad)
from neso.rotations import world_from_body_zyx
from runtime.schema import SetpointMsg, StateMsg
from services.px4_gateway import GatewayConfig, GatewayCore


def setpoint(roll=0.0, pitch=0.0, yaw=0.0, thrust=0.5) -> SetpointMsg:
    return SetpointMsg(seq=1, stamp_s=1.0, state_stamp_s=1.0, t_s=0.0, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw,
                       thrust_norm=thrust, thrust_n=9.81, acc_cmd_enu_mps2=(0.0, 0.0, 0.0), estimate_source="estimator")


@pytest.mark.parametrize("rpy", [(0.1, -0.2, 0.3), (0.0, 0.0, 0.0), (-0.4, 0.3, 2.9), (0.2, 0.1, -1.7)])
def test_ned_attitude_is_the_same_physical_rotation_and_round_trips(rpy):
    ned = attitude_ned_from_enu(*rpy)
    r_enu = world_from_body_zyx(*rpy)
    r_ned = world_from_body_zyx(*ned)
    np.testing.assert_allclose(NED_FROM_ENU @ r_enu @ FLU_FROM_FRD, r_ned, atol=1e-12)
    np.testing.assert_allclose(attitude_enu_from_ned(*ned), rpy, atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(quat_ned_from_enu_euler(*rpy)), r_ned, atol=1e-12)
    np.testing.assert_allclose(quat_to_euler_ned(quat_ned_from_enu_euler(*rpy)), ned, atol=1e-12)


def test_small_angles_map_as_px4_users_expect():
    roll, pitch, yaw = attitude_ned_from_enu(0.1, 0.05, 0.0)  # ENU yaw 0 faces east = NED yaw +90°
    assert roll == pytest.approx(0.1, abs=1e-3) and pitch == pytest.approx(-0.05, abs=1e-3)
    assert yaw == pytest.approx(math.pi / 2, abs=1e-3)


def test_thrust_is_rescaled_to_the_vehicles_hover_thrust_and_angles_converted():
    core = GatewayCore(GatewayConfig(hover_thrust_norm=0.6))
    out = core.on_setpoint(setpoint(roll=0.1, pitch=0.05, yaw=0.0, thrust=0.5), 1.0)
    assert out.thrust_norm == pytest.approx(0.6)
    assert (out.roll_deg, out.pitch_deg, out.yaw_deg) == pytest.approx(
        tuple(math.degrees(a) for a in attitude_ned_from_enu(0.1, 0.05, 0.0)))


def test_over_tilt_is_scaled_back_keeping_its_direction_and_thrust_is_clamped():
    core = GatewayCore(GatewayConfig(max_tilt_rad=math.radians(40.0), thrust_max_norm=0.9))
    out = core.on_setpoint(setpoint(roll=1.2, pitch=-0.9, thrust=0.95), 1.0)
    r, p, _ = attitude_enu_from_ned(*(math.radians(a) for a in (out.roll_deg, out.pitch_deg, out.yaw_deg)))
    assert math.degrees(tilt_rad(r, p)) == pytest.approx(40.0, abs=1e-6)
    assert r / p == pytest.approx(1.2 / -0.9, rel=1e-9)
    assert out.thrust_norm == 0.9
    assert core.counts["clamped_tilt"] == 1 and core.counts["clamped_thrust"] == 1


def test_non_finite_setpoint_is_refused_and_counted():
    core = GatewayCore(GatewayConfig())
    bad = dataclasses.replace(setpoint(), pitch_rad=math.nan)  # the schema would refuse it on the wire
    assert core.on_setpoint(bad, 1.0) is None
    assert core.counts["refused_nonfinite"] == 1 and core.last_sent is None and core.setpoint_age_s(2.0) == -1.0


def feed_states(core, t0, t1):
    for k in range(int(round((t1 - t0) * 50))):
        core.on_state(state(t0 + k / 50), t0 + k / 50, offboard=True)


def test_stale_setpoints_in_offboard_hold_then_land_and_only_in_offboard():
    core = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_states=15, stale_max_s=1.0, land_after_s=3.0))
    core.on_setpoint(setpoint(), 10.0)
    feed_states(core, 10.0, 10.2)
    assert core.check_stale(10.2, offboard=True, armed=True) == ""
    feed_states(core, 10.2, 10.32)
    assert core.check_stale(11.0, offboard=False, armed=True) == "", "not in offboard: PX4 flies its own mode"
    assert core.check_stale(10.32, offboard=True, armed=True) == "hold"
    assert core.check_stale(11.0, offboard=False, armed=True) == ""  # now in hold
    core.on_setpoint(setpoint(), 12.0)  # a restarted controller does not cancel the landing
    assert core.check_stale(13.33, offboard=False, armed=True) == "land"
    assert core.failsafe == "land" and core.check_stale(20.0, offboard=False, armed=True) == ""
    core.clear_failsafe()
    assert core.failsafe == ""


def test_a_stall_of_the_whole_machine_is_not_taken_for_a_dead_controller_up_to_stale_max():
    core = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_states=15, stale_max_s=1.0))
    core.on_setpoint(setpoint(), 10.0)
    feed_states(core, 10.0, 10.1)  # then nothing at all: the source stalled too
    assert core.check_stale(10.6, offboard=True, armed=True) == ""
    assert core.check_stale(11.01, offboard=True, armed=True) == "hold"


def test_an_operator_taking_over_cancels_the_failsafe_landing():
    core = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_max_s=0.5, land_after_s=3.0))
    core.on_setpoint(setpoint(), 10.0)
    assert core.check_stale(10.6, offboard=True, armed=True) == "hold"
    core.clear_failsafe()  # offboard_start by an operator
    core.on_setpoint(setpoint(), 11.0)
    assert core.check_stale(11.1, offboard=True, armed=True) == ""


def state(t, z=1.0, vz=0.0) -> StateMsg:
    return StateMsg(seq=int(t * 50), stamp_s=t, t_s=t, pos_enu_m=(0.0, 0.0, z), vel_enu_mps=(0.0, 0.0, vz),
                    roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, source="sim")


def test_hover_thrust_is_learned_from_steady_hover_and_calibrated_on_command():
    core = GatewayCore(GatewayConfig(hover_thrust_norm=0.5, hover_tau_s=2.0))
    # the vehicle holds still while 0.525 goes out (the controller's closed loop found it)
    for k in range(1000):
        t = k / 50
        core.on_setpoint(setpoint(thrust=0.525 / core.hover_thrust_norm * 0.5), t)
        core.on_state(state(t), t, offboard=True)
    assert core.hover_thrust_norm == pytest.approx(0.525, abs=2e-3)
    near_ground = GatewayCore(GatewayConfig(hover_thrust_norm=0.5))
    for k in range(500):
        near_ground.on_setpoint(setpoint(thrust=0.45), k / 50)
        near_ground.on_state(state(k / 50, z=0.1), k / 50, offboard=True)
    assert near_ground.hover_thrust_norm == 0.5, "no learning in ground effect"
    cal = GatewayCore(GatewayConfig(hover_thrust_norm=0.5, learn_hover=False, calibrate_s=2.0))
    cal.start_calibration(0.0)
    for k in range(150):
        cal.on_setpoint(setpoint(thrust=0.55), k / 50)
        cal.on_state(state(k / 50), k / 50, offboard=True)
    assert cal.hover_thrust_norm == pytest.approx(0.55, abs=1e-9)
    assert any("calibrated" in text for _, text in cal.events)


def test_motion_capture_lost_is_told_to_px4_until_it_is_back():
    core = GatewayCore(GatewayConfig(pose_lost_after_s=0.1))
    assert not core.pose_failed(5.0), "nothing forwarded yet: nothing to call lost"
    core.on_pose(10.0)
    assert not core.pose_failed(10.1)
    assert core.pose_failed(10.15) and core.pose_failed(11.0)
    assert [e[0] for e in core.events] == ["warning"] and "quality -1" in core.events[0][1]
    core.on_pose(11.02)
    assert not core.pose_failed(11.05)
    assert core.events[-1] == ("info", "motion capture back after 1.02 s: PX4 fuses it again (odometry quality 100)")


def test_while_motion_capture_is_lost_the_vehicle_is_flown_level_at_its_hover_thrust_on_its_heading():
    core = GatewayCore(GatewayConfig(hover_thrust_norm=0.42))
    assert core.level_setpoint() is None, "no setpoint yet: nothing to level"
    sent = core.on_setpoint(setpoint(roll=0.3, pitch=-0.2, yaw=1.0, thrust=0.6), 1.0)
    level = core.level_setpoint()
    assert (level.roll_deg, level.pitch_deg, level.thrust_norm) == (0.0, 0.0, 0.42) and level.yaw_deg == sent.yaw_deg


def test_a_hold_the_vehicle_refuses_is_followed_by_land_at_once():
    """PX4 without a global position refuses Hold ("Switching to Hold is currently not available"): the
    failsafe lands at its next check instead of land_after_s later."""
    core = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_max_s=0.5, land_after_s=3.0))
    core.on_setpoint(setpoint(), 10.0)
    assert core.check_stale(10.6, offboard=True, armed=True) == "hold"
    core.hold_refused("COMMAND_DENIED")
    assert core.check_stale(10.62, offboard=True, armed=True) == "land" and core.failsafe == "land"
    assert "refused hold (COMMAND_DENIED): commanding land now" in core.events[-2][1]


def test_a_hold_acknowledged_but_not_taken_is_followed_by_land_after_hold_confirm():
    """PX4 v1.16 acks the failsafe's Hold as accepted and stays in offboard when it cannot switch (measured
    without a global position): still in offboard hold_confirm_s later, the gateway commands land."""
    core = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_max_s=0.5, land_after_s=3.0, hold_confirm_s=1.0))
    core.on_setpoint(setpoint(), 10.0)
    assert core.check_stale(10.6, offboard=True, armed=True) == "hold"
    assert core.check_stale(11.5, offboard=True, armed=True) == ""
    assert core.check_stale(11.61, offboard=True, armed=True) == "land" and core.failsafe == "land"
    assert "still in offboard 1.0 s after the failsafe's hold" in core.events[-1][1]
    taken = GatewayCore(GatewayConfig(stale_hold_s=0.3, stale_max_s=0.5, land_after_s=3.0, hold_confirm_s=1.0))
    taken.on_setpoint(setpoint(), 10.0)
    assert taken.check_stale(10.6, offboard=True, armed=True) == "hold"
    assert taken.check_stale(11.61, offboard=False, armed=True) == "", "in hold: land only after land_after_s"


def test_a_refused_arm_says_why_in_words_and_how_long_ekf2_may_still_take():
    """Before: "arm: ActionError: COMMAND_DENIED; origin: arm(); params: ()"."""
    core = GatewayCore(GatewayConfig(ev_settle_s=1.9))
    said = "CRITICAL: Arming denied: Resolve system health failures first"
    no_vision = core.refusal("arm", "COMMAND_DENIED", 10.0, ready=False, said=said)
    assert no_vision == ("arm refused by the vehicle: PX4 denied it; not ready: PX4 gets no external vision (is the "
                         f"motion capture reaching the gateway?); PX4 says: {said}")
    for k in range(61):  # 1.2 s of poses at 50 Hz
        core.on_pose(10.0 + 0.02 * k)
    settling = core.refusal("arm", "COMMAND_DENIED", 11.2, ready=False)
    assert "not ready: EKF2 settling on the motion capture, about 0.7 s more (1.2 s of it so far" in settling
    assert "not ready after 3.0 s of motion capture" in core.refusal("arm", "COMMAND_DENIED", 13.0, ready=False)
    assert core.refusal("takeoff", "COMMAND_DENIED_NOT_LANDED", 13.0, ready=True) == \
        "takeoff refused by the vehicle: PX4 does not do it in the air"


def test_the_capture_time_follows_the_poses_age_not_its_arrival():
    core = GatewayCore(GatewayConfig())
    aged = StateMsg(seq=1, stamp_s=50.0, t_s=1.0, pos_enu_m=(0, 0, 1), vel_enu_mps=(0, 0, 0), roll_rad=0.0,
                    pitch_rad=0.0, yaw_rad=0.0, source="mocap", capture_stamp_s=49.988)
    assert core.capture_s(aged, 60.0) == pytest.approx(60.0 - 0.012)  # another machine's clock: only the age counts
    assert core.capture_s(dataclasses.replace(aged, capture_stamp_s=0.0), 60.0) == 60.0
    for k in range(100):
        core.on_pose(60.0 + 0.02 * k, 60.0 + 0.02 * k - 0.012)
    p50, p99 = core.delay_to_vehicle_ms(link_s=0.001)
    assert p50 == pytest.approx(13.0) and p99 == pytest.approx(13.0)
