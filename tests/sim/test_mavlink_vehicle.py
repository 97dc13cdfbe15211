"""The MAVLink imitation of PX4 (sim/mavlink_vehicle.py) where it was aligned with PX4 v1.16.0 SITL (docs/px4.md, "Real
PX4 in the loop"): no arming before its pre-flight checks pass (external vision received for PX4's settle time;
PX4's ack, words and readiness signals), not ready again after a long loss of external vision; offboard loss → Hold
after 0.3 s (COM_OF_LOSS_T, COM_OBL_RC_ACT in this world's airframe) with PX4's "Failsafe activated", back to
offboard when setpoints stream again, and PX4's words for arming, landing and its auto-disarm 2 s after touch-down.
Driven over real MAVLink (pymavlink) on loopback UDP as a ground station and the gateway's external vision would,
its physics stepped by hand."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest
from pymavlink import mavutil

from neso.types import StateMeasurement
from sim.mavlink_vehicle import ARMING_DENIED, MAIN_OFFBOARD, NOT_SETTLED, READY, MavlinkVehicle, VehicleConfig
from tests.busutil import free_port

mavlink = mavutil.mavlink
GROUND = StateMeasurement(0.0, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0)


class Station:
    """A ground station on loopback UDP facing one imitation; everything it hears is kept with its arrival time."""

    def __init__(self, **config) -> None:
        port = free_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, dialect="common")
        self.console: list[str] = []
        self.vehicle = MavlinkVehicle(VehicleConfig(target=f"udpout:127.0.0.1:{port}", **config), dt_s=0.02,
                                      console=self.console.append)
        self.vehicle.publish(GROUND, t_s=0.0)  # its first datagram tells the ground station where it is
        first = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        assert first is not None
        self.heard: list[tuple[float, object]] = [(time.monotonic(), first)]

    def listen(self, seconds: float = 0.0) -> None:
        end = time.monotonic() + seconds
        while True:
            while (m := self.conn.recv_match(blocking=False)) is not None:
                self.heard.append((time.monotonic(), m))
            if time.monotonic() >= end:
                return
            time.sleep(0.005)

    def texts(self, since: float = 0.0) -> list[tuple[float, int, str]]:
        """(arrival, severity, text) of every STATUSTEXT, its 50-byte chunks joined (what MAVSDK hands on)."""
        out: list[tuple[float, int, str]] = []
        for t, m in self.heard:
            if m.get_type() == "STATUSTEXT" and t >= since:
                if m.chunk_seq > 0 and out:
                    out[-1] = (out[-1][0], out[-1][1], out[-1][2] + m.text)
                else:
                    out.append((t, m.severity, m.text))
        return out

    def said(self, since: float = 0.0) -> list[str]:
        return [text for _, _, text in self.texts(since)]

    def last(self, kind: str):
        return next((m for _, m in reversed(self.heard) if m.get_type() == kind), None)

    def command(self, cmd: int, *params: float) -> None:
        self.conn.mav.command_long_send(1, 1, cmd, 0, *(list(params) + [0.0] * 7)[:7])

    def arm(self) -> int:
        """Arm over MAVLink; the COMMAND_ACK's result."""
        since = time.monotonic()
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        deadline = since + 2.0
        while time.monotonic() < deadline:
            self.listen(0.02)
            acks = [m for t, m in self.heard if t >= since and m.get_type() == "COMMAND_ACK"
                    and m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM]
            if acks:
                self.listen(0.05)  # its STATUSTEXT follows the ack
                return acks[0].result
        raise AssertionError("no COMMAND_ACK for the arm command")

    def odometry(self, quality: int = 100) -> None:
        """One external-vision pose as the gateway forwards it (VISION, LOCAL_FRD, body FRD velocity)."""
        nan21 = [math.nan] + [0.0] * 20
        self.conn.mav.odometry_send(0, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 0.0, 0.0, 0.0,
                                    [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, nan21, nan21, 0,
                                    mavlink.MAV_ESTIMATOR_TYPE_VISION, quality)

    def stream(self, seconds: float, *, quality: int | None = 100, until=None) -> float:
        """Step the vehicle's telemetry at 50 Hz with external vision (``quality``; None: none) for ``seconds``
        or until ``until()``; the time it took."""
        start = time.monotonic()
        while time.monotonic() - start < seconds and not (until and until()):
            if quality is not None:
                self.odometry(quality)
            self.vehicle.publish(GROUND, t_s=0.0)
            self.listen(0.02)
        return time.monotonic() - start

    def standby(self) -> bool:
        """Ready as a ground station sees PX4 ready: HEARTBEAT system_status STANDBY (UNINIT before)."""
        hb = self.last("HEARTBEAT")
        return hb is not None and hb.system_status == mavlink.MAV_STATE_STANDBY

    def ready_for_takeoff(self) -> None:
        """The operator's wait: external vision streaming until PX4 has said "Ready for takeoff!"."""
        self.stream(10.0, until=lambda: READY in self.console)
        assert READY in self.console, self.said()

    def close(self) -> None:
        self.vehicle.close()
        self.conn.close()


def test_arming_is_refused_in_px4s_words_until_external_vision_has_settled_then_it_is_ready_for_takeoff():
    gcs = Station()
    try:
        assert gcs.last("HEARTBEAT").system_status == mavlink.MAV_STATE_UNINIT  # PX4: checks not passed
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # Commander: TRANSITION_DENIED
        assert gcs.said() == [ARMING_DENIED] and not gcs.vehicle.armed
        gcs.stream(0.5, quality=-1)  # "odometry has failed" is not fused (EKF2_EV_QMIN 1): still nothing
        assert not gcs.vehicle.ready and NOT_SETTLED not in gcs.said()
        first = time.monotonic()
        gcs.stream(1.0)
        assert gcs.said().count(NOT_SETTLED) == 1, gcs.said()  # PX4 reports a change once, no repetition
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "armed while EKF2 was still settling"
        assert gcs.said(first)[-1] == ARMING_DENIED
        gcs.stream(5.0, until=gcs.standby)
        settled_s = time.monotonic() - first
        gcs.stream(0.3)  # SYS_STATUS goes out at 10 Hz
        assert 1.9 <= settled_s < 2.4, settled_s  # PX4 v1.16.0 SITL: 1.93–1.94 s (VehicleConfig.ev_settle_s)
        assert gcs.console == [READY] and READY not in gcs.said()  # PX4 prints it on its console only
        assert gcs.last("SYS_STATUS").onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
        since = time.monotonic()
        assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED and gcs.vehicle.armed
        assert gcs.said(since) == ["Armed by external command"]
        assert [(severity, text) for _, severity, text in gcs.texts()] == [
            (mavlink.MAV_SEVERITY_CRITICAL, ARMING_DENIED), (mavlink.MAV_SEVERITY_CRITICAL, NOT_SETTLED),
            (mavlink.MAV_SEVERITY_CRITICAL, ARMING_DENIED), (mavlink.MAV_SEVERITY_INFO, "Armed by external command")]
    finally:
        gcs.close()


def test_external_vision_lost_longer_than_the_timeout_makes_it_not_ready_until_it_has_settled_again():
    # short figures to keep the tier fast; the defaults (1.9 s, 5 s) are PX4's (VehicleConfig)
    gcs = Station(ev_settle_s=0.3, ev_timeout_s=1.0)
    try:
        gcs.ready_for_takeoff()
        gcs.stream(0.3, quality=None)  # a gap shorter than the timeout: still ready
        assert gcs.vehicle.ready and gcs.standby()
        gcs.stream(0.3)
        gcs.stream(2.0, quality=-1)  # lost (the gateway's "failed" poses) longer than the timeout and PX4's 2 s
        assert not gcs.vehicle.ready and gcs.last("HEARTBEAT").system_status == mavlink.MAV_STATE_UNINIT
        assert not gcs.last("SYS_STATUS").onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED and gcs.said()[-1] == ARMING_DENIED
        back = time.monotonic()
        gcs.stream(5.0, until=gcs.standby)
        assert 0.3 <= time.monotonic() - back < 0.8  # settled again
        # settling again is a change PX4 reports (more than its 2 s report interval after the first report)
        assert gcs.said(back) == [NOT_SETTLED], gcs.said()
        assert gcs.console == [READY], "PX4 prints it once in its life"
        assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED and gcs.vehicle.armed
    finally:
        gcs.close()


@pytest.mark.parametrize("action, mode", [(None, "hold"), ("land", "land")])
def test_offboard_loss_holds_or_lands_says_so_and_setpoints_streaming_again_end_it(action, mode):
    """As the airframe sets it (COM_OF_LOSS_T 0.3 s, COM_OBL_RC_ACT Hold), or Land."""
    assert (VehicleConfig().offboard_loss_s, VehicleConfig().offboard_loss_action) == (0.3, "hold")  # the airframe's
    gcs = Station() if action is None else Station(offboard_loss_action=action)
    hover = StateMeasurement(0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0, 0.0, 0.0)
    vehicle = gcs.vehicle
    try:
        gcs.ready_for_takeoff()

        def run(seconds: float, streaming: bool) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                if streaming:
                    gcs.conn.mav.set_attitude_target_send(0, 1, 1, 0b00000111, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
                vehicle.control(hover, on_ground=False)
                gcs.listen(0.02)

        run(0.3, True)
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        gcs.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAIN_OFFBOARD)
        run(0.5, True)
        assert vehicle.mode_name == "offboard" and vehicle.armed
        run(0.2, False)
        assert vehicle.mode_name == "offboard", "not before COM_OF_LOSS_T"
        run(0.4, False)
        assert vehicle.mode_name == mode and "Failsafe activated" in gcs.said(), (vehicle.mode_name, gcs.said())
        run(0.3, True)
        assert vehicle.mode_name == "offboard", "PX4 ends its offboard-loss failsafe when setpoints stream again"
        assert "Armed by external command" in gcs.said(), gcs.said()
    finally:
        gcs.close()


def test_landing_is_detected_and_disarms_two_seconds_later_in_px4s_words():
    gcs = Station()
    vehicle = gcs.vehicle
    said: list[tuple[float, str]] = []
    try:
        gcs.ready_for_takeoff()
        for cmd, p1 in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), (mavlink.MAV_CMD_NAV_LAND, 0.0)):
            gcs.command(cmd, p1)
        deadline = time.monotonic() + 5.0
        while "Landing at current position" not in gcs.said() and time.monotonic() < deadline:
            gcs.listen(0.05)
        for k in range(200):  # 4 s of vehicle time on the ground, in land
            t = k * 0.02
            vehicle.control(StateMeasurement(t, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0), on_ground=True)
            while (m := gcs.conn.recv_match(type="STATUSTEXT", blocking=False)) is not None:
                said.append((t, m.text))
            time.sleep(0.002)
    finally:
        gcs.close()
    assert [e["text"] for e in vehicle.log if e["kind"] == "statustext"] == [
        NOT_SETTLED, "Armed by external command", "Landing at current position", "Landing detected",
        "Disarmed by landing"]
    assert not vehicle.armed
    disarmed_at = [t for t, text in said if text == "Disarmed by landing"]
    assert disarmed_at and 2.0 <= disarmed_at[0] <= 2.1, said  # COM_DISARM_LAND after touch-down at t = 0


def test_parameters_are_read_and_set_as_px4_answers_them_and_ekf2_ev_qmin_decides_what_is_fused():
    """PARAM_REQUEST_READ / PARAM_SET answered with PARAM_VALUE as PX4 answers them (int32 bytewise, floats as
    floats), from the world's airframe file; a name it does not have gets no answer; with EKF2_EV_QMIN set to 0
    (PX4's default) a pose with quality -1 is fused, as EKF2 does (ev_control.cpp)."""
    import struct

    from sim.px4_sitl import load_params

    s = Station()
    try:
        def read(name: str, since: float):
            s.conn.mav.param_request_read_send(1, 1, name.encode(), -1)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                s.listen(0.02)
                got = [m for t, m in s.heard if t >= since and m.get_type() == "PARAM_VALUE" and m.param_id == name]
                if got:
                    return got[-1]
            return None

        airframe = load_params()
        qmin = read("EKF2_EV_QMIN", time.monotonic())
        assert qmin.param_type == mavlink.MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", qmin.param_value))[0] == int(airframe["EKF2_EV_QMIN"]) == 1
        loss = read("COM_OF_LOSS_T", time.monotonic())
        assert loss.param_type == mavlink.MAV_PARAM_TYPE_REAL32 and loss.param_value == pytest.approx(0.3)
        assert read("NO_SUCH_PARAM", time.monotonic()) is None
        s.stream(3.0, quality=-1)
        assert not s.vehicle.ready, "quality -1 is not fused with EKF2_EV_QMIN 1"
        since = time.monotonic()
        s.conn.mav.param_set_send(1, 1, b"EKF2_EV_QMIN", struct.unpack("<f", struct.pack("<i", 0))[0],
                                  mavlink.MAV_PARAM_TYPE_INT32)
        s.listen(0.2)
        echo = [m for t, m in s.heard if t >= since and m.get_type() == "PARAM_VALUE"]
        assert echo and struct.unpack("<i", struct.pack("<f", echo[-1].param_value))[0] == 0
        s.stream(3.0, quality=-1)
        assert s.vehicle.ready, "with EKF2_EV_QMIN 0 the stale pose is fused"
        status = s.last("ESTIMATOR_STATUS")
        assert status is not None and status.flags & 8 and not status.flags & 128
    finally:
        s.close()
