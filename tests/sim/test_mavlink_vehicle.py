"""The MAVLink imitation of PX4 (sim/mavlink_vehicle.py) where it was aligned with PX4 v1.16.0 SITL (README, "Real
PX4 in the loop"): offboard loss → Hold after 0.3 s (COM_OBL_RC_ACT, COM_OF_LOSS_T in this world's airframe) with
PX4's "Failsafe activated", back to offboard when setpoints stream again, and PX4's words for arming, landing and its auto-disarm
2 s after touch-down. Driven over real MAVLink (pymavlink) on loopback UDP, its physics stepped by hand."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from pymavlink import mavutil

from neso.types import StateMeasurement
from sim.mavlink_vehicle import MAIN_OFFBOARD, MavlinkVehicle, VehicleConfig
from tests.busutil import free_port

mavlink = mavutil.mavlink


@pytest.mark.parametrize("action, mode", [(None, "hold"), ("land", "land")])
def test_offboard_loss_holds_or_lands_says_so_and_setpoints_streaming_again_end_it(action, mode):
    """As the airframe sets it (COM_OF_LOSS_T 0.3 s, COM_OBL_RC_ACT Hold), or Land."""
    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, dialect="common")
    config = VehicleConfig(target=f"udpout:127.0.0.1:{port}")
    assert (config.offboard_loss_s, config.offboard_loss_action) == (0.3, "hold")  # sim/px4/neso_quad.params
    vehicle = MavlinkVehicle(config if action is None else replace(config, offboard_loss_action=action), dt_s=0.02)
    said: list[str] = []
    try:
        hover = StateMeasurement(0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0, 0.0, 0.0)
        vehicle.publish(hover, t_s=0.0)  # its first datagram tells the ground station where it is
        gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)

        def setpoint() -> None:
            gcs.mav.set_attitude_target_send(0, 1, 1, 0b00000111, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)

        def command(cmd: int, *params: float) -> None:
            gcs.mav.command_long_send(1, 1, cmd, 0, *(list(params) + [0.0] * 7)[:7])

        def run(seconds: float, streaming: bool) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                if streaming:
                    setpoint()
                vehicle.control(hover, on_ground=False)
                while (m := gcs.recv_match(type="STATUSTEXT", blocking=False)) is not None:
                    said.append(m.text)
                time.sleep(0.02)

        run(0.3, True)
        command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAIN_OFFBOARD)
        run(0.5, True)
        assert vehicle.mode_name == "offboard" and vehicle.armed
        run(0.2, False)
        assert vehicle.mode_name == "offboard", "not before COM_OF_LOSS_T"
        run(0.4, False)
        assert vehicle.mode_name == mode and "Failsafe activated" in said, (vehicle.mode_name, said)
        run(0.3, True)
        assert vehicle.mode_name == "offboard", "PX4 ends its offboard-loss failsafe when setpoints stream again"
        assert "Armed by external command" in said, said
    finally:
        vehicle.close()
        gcs.close()


def test_landing_is_detected_and_disarms_two_seconds_later_in_px4s_words():
    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, dialect="common")
    vehicle = MavlinkVehicle(VehicleConfig(target=f"udpout:127.0.0.1:{port}"), dt_s=0.02)
    said: list[tuple[float, str]] = []
    try:
        ground = StateMeasurement(0.0, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0)
        vehicle.publish(ground, t_s=0.0)
        gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        for cmd, p1 in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), (mavlink.MAV_CMD_NAV_LAND, 0.0)):
            gcs.mav.command_long_send(1, 1, cmd, 0, p1, 0, 0, 0, 0, 0, 0)
        deadline = time.monotonic() + 5.0
        while not any(text == "Landing at current position" for _, text in said) and time.monotonic() < deadline:
            while (m := gcs.recv_match(type="STATUSTEXT", blocking=True, timeout=0.05)) is not None:
                said.append((0.0, m.text))
        for k in range(200):  # 4 s of vehicle time on the ground, in land
            t = k * 0.02
            vehicle.control(StateMeasurement(t, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0), on_ground=True)
            while (m := gcs.recv_match(type="STATUSTEXT", blocking=False)) is not None:
                said.append((t, m.text))
            time.sleep(0.002)
        time.sleep(0.1)
        while (m := gcs.recv_match(type="STATUSTEXT", blocking=False)) is not None:
            said.append((4.0, m.text))
    finally:
        vehicle.close()
        gcs.close()
    assert [e["text"] for e in vehicle.log if e["kind"] == "statustext"] == [
        "Armed by external command", "Landing at current position", "Landing detected", "Disarmed by landing"]
    assert not vehicle.armed
    disarmed_at = [t for t, text in said if text == "Disarmed by landing"]
    assert disarmed_at and 2.0 <= disarmed_at[0] <= 2.1, said  # COM_DISARM_LAND after touch-down at t = 0
