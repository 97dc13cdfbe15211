"""The MAVLink imitation of PX4 (sim/mavlink_vehicle.py) where it was aligned with PX4 v1.16.0 SITL (docs/px4.md, "Real
PX4 in the loop"): no arming before its pre-flight checks pass (external vision received for PX4's settle time;
PX4's ack, words and readiness signals), not ready again after a long loss of external vision; offboard loss → Hold
after 0.3 s (COM_OF_LOSS_T, COM_OBL_RC_ACT in this world's airframe) with PX4's "Failsafe activated", back to
offboard when setpoints stream again, and PX4's words for arming, landing and its auto-disarm 2 s after touch-down.
Driven over real MAVLink (pymavlink) on loopback UDP as a ground station and the gateway's external vision would,
its world stepped by hand: every interval is the vehicle's own time (the world's, as PX4 SITL's in lockstep), so
none depends on how fast this machine is; the test waits for each message to be handled before the world steps on.
"""
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
DT_S = 0.02  # the world's period
GROUND = StateMeasurement(0.0, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0)


class Station:
    """A ground station on loopback UDP facing one imitation whose world it steps (``t_s``, the vehicle's clock);
    everything it hears is kept in order."""

    def __init__(self, **config) -> None:
        port = free_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, dialect="common")
        self.console: list[str] = []
        self.vehicle = MavlinkVehicle(VehicleConfig(target=f"udpout:127.0.0.1:{port}", **config), dt_s=DT_S,
                                      console=self.console.append)
        self.t_s = 0.0
        self.sent = 0
        self.vehicle.publish(GROUND, t_s=0.0)  # its first datagram tells the ground station where it is
        first = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0)
        assert first is not None
        self.heard: list = [first]

    def send(self, what: str, *args) -> None:
        """One message to the vehicle (``self.conn.mav.<what>_send``), handled before this returns."""
        getattr(self.conn.mav, f"{what}_send")(*args)
        self.sent += 1
        deadline = time.monotonic() + 5.0
        while self.vehicle.received < self.sent:
            assert time.monotonic() < deadline, f"the vehicle never handled {what}"
            time.sleep(0.0005)

    def listen(self) -> None:
        while (m := self.conn.recv_match(blocking=False)) is not None:
            self.heard.append(m)

    def hear(self, until, timeout_s: float = 5.0):
        """Listen until ``until()`` (on the wall clock: delivery, not the vehicle's behaviour)."""
        deadline = time.monotonic() + timeout_s
        while not until() and time.monotonic() < deadline:
            self.listen()
            time.sleep(0.002)
        return until()

    def texts(self, since: int = 0) -> list[tuple[int, str]]:
        """(severity, text) of every STATUSTEXT heard from ``heard[since]`` on, its 50-byte chunks joined (what MAVSDK
        hands on)."""
        out: list[tuple[int, str]] = []
        for m in self.heard[since:]:
            if m.get_type() == "STATUSTEXT":
                if m.chunk_seq > 0 and out:
                    out[-1] = (out[-1][0], out[-1][1] + m.text)
                else:
                    out.append((m.severity, m.text))
        return out

    def said(self, since: int = 0) -> list[str]:
        return [text for _, text in self.texts(since)]

    def last(self, kind: str):
        return next((m for m in reversed(self.heard) if m.get_type() == kind), None)

    def command(self, cmd: int, *params: float) -> None:
        self.send("command_long", 1, 1, cmd, 0, *(list(params) + [0.0] * 7)[:7])

    def arm(self) -> int:
        """Arm over MAVLink; the COMMAND_ACK's result (its STATUSTEXT heard too)."""
        since = len(self.heard)
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        acks = lambda: [m for m in self.heard[since:] if m.get_type() == "COMMAND_ACK"
                        and m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM]
        assert self.hear(acks), "no COMMAND_ACK for the arm command"
        self.hear(lambda: self.texts(since))  # its STATUSTEXT follows the ack
        return acks()[0].result

    def odometry(self, quality: int = 100) -> None:
        """One external-vision pose as the gateway forwards it (VISION, LOCAL_FRD, body FRD velocity)."""
        nan21 = [math.nan] + [0.0] * 20
        self.send("odometry", 0, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 0.0, 0.0, 0.0,
                  [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, nan21, nan21, 0, mavlink.MAV_ESTIMATOR_TYPE_VISION,
                  quality)

    def stream(self, seconds: float, *, quality: int | None = 100, until=None) -> None:
        """Step the world ``seconds`` (its time) at 50 Hz, on the ground, with external vision (``quality``; None:
        none), or until ``until()``."""
        for _ in range(round(seconds / DT_S)):
            if until is not None and until():
                return
            if quality is not None:
                self.odometry(quality)
            self.t_s += DT_S
            self.vehicle.publish(GROUND, t_s=self.t_s)
            self.listen()

    def entries(self, kind: str, **match) -> list[dict]:
        """The vehicle's own log of ``kind`` (each with the vehicle's time it happened at, ``vehicle_t_s``)."""
        return [e for e in self.vehicle.log if e["kind"] == kind and all(e.get(k) == v for k, v in match.items())]

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


def within_a_period(measured_s: float, expected_s: float) -> bool:
    """At ``expected_s`` on the vehicle's clock, to the world step that sees it (its checks run once a period)."""
    return expected_s - 1e-9 <= measured_s <= expected_s + DT_S + 1e-9


def settled_at(gcs, after_s: float) -> float:
    """The vehicle's time at which it became ready after ``after_s`` (its own log)."""
    return next(e["vehicle_t_s"] for e in gcs.entries("preflight", ready=True) if e["vehicle_t_s"] >= after_s)


def test_arming_is_refused_in_px4s_words_until_external_vision_has_settled_then_it_is_ready_for_takeoff():
    ev_settle_s = VehicleConfig().ev_settle_s  # PX4 v1.16.0 SITL: 1.93–1.94 s from its ULogs
    gcs = Station()
    try:
        assert gcs.last("HEARTBEAT").system_status == mavlink.MAV_STATE_UNINIT  # PX4: checks not passed
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # Commander: TRANSITION_DENIED
        assert gcs.said() == [ARMING_DENIED] and not gcs.vehicle.armed
        gcs.stream(0.5, quality=-1)  # "odometry has failed" is not fused (EKF2_EV_QMIN 1): still nothing
        assert not gcs.vehicle.ready and NOT_SETTLED not in gcs.said()
        first_s = gcs.t_s  # the first pose EKF2 fuses
        gcs.stream(1.0)
        assert gcs.hear(lambda: NOT_SETTLED in gcs.said()) and gcs.said().count(NOT_SETTLED) == 1, gcs.said()
        since = len(gcs.heard)
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "armed while EKF2 was still settling"
        assert gcs.said(since) == [ARMING_DENIED]
        gcs.stream(ev_settle_s - 1.0 - DT_S)
        assert not gcs.vehicle.ready, f"ready before {ev_settle_s} s of external vision"
        gcs.stream(2 * DT_S)
        assert within_a_period(settled_at(gcs, first_s) - first_s, ev_settle_s)
        assert gcs.hear(gcs.standby), "HEARTBEAT STANDBY once ready"
        gcs.stream(0.2)  # SYS_STATUS goes out at 10 Hz
        assert gcs.hear(lambda: gcs.last("SYS_STATUS").onboard_control_sensors_health
                        & mavlink.MAV_SYS_STATUS_PREARM_CHECK)
        assert gcs.console == [READY] and READY not in gcs.said()  # PX4 prints it on its console only
        since = len(gcs.heard)
        assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED and gcs.vehicle.armed
        assert gcs.said(since) == ["Armed by external command"]
        assert gcs.texts() == [
            (mavlink.MAV_SEVERITY_CRITICAL, ARMING_DENIED), (mavlink.MAV_SEVERITY_CRITICAL, NOT_SETTLED),
            (mavlink.MAV_SEVERITY_CRITICAL, ARMING_DENIED), (mavlink.MAV_SEVERITY_INFO, "Armed by external command")]
    finally:
        gcs.close()


def test_external_vision_lost_longer_than_the_timeout_makes_it_not_ready_until_it_has_settled_again():
    config = VehicleConfig()  # PX4's figures: settled after 1.9 s, EKF2_NOAID_TOUT 5 s (each the vehicle's time)
    gcs = Station()
    try:
        gcs.ready_for_takeoff()
        gcs.stream(config.ev_timeout_s - 0.1, quality=None)  # a gap shorter than the timeout: still ready
        assert gcs.vehicle.ready and not gcs.entries("preflight", ready=False)
        gcs.stream(0.3)
        last_fused_s = gcs.t_s - DT_S
        gcs.stream(config.ev_timeout_s + 0.5, quality=-1)  # lost (the gateway's "failed" poses) past the timeout
        lost = gcs.entries("preflight", ready=False)
        assert len(lost) == 1 and within_a_period(lost[0]["vehicle_t_s"] - last_fused_s, config.ev_timeout_s)
        assert gcs.hear(lambda: gcs.last("HEARTBEAT").system_status == mavlink.MAV_STATE_UNINIT)
        gcs.stream(0.2, quality=-1)  # SYS_STATUS goes out at 10 Hz
        assert gcs.hear(lambda: not gcs.last("SYS_STATUS").onboard_control_sensors_health
                        & mavlink.MAV_SYS_STATUS_PREARM_CHECK)
        assert gcs.arm() == mavlink.MAV_RESULT_TEMPORARILY_REJECTED and gcs.said()[-1] == ARMING_DENIED
        back_s, since = gcs.t_s, len(gcs.heard)
        gcs.stream(config.ev_settle_s + 0.1)
        assert within_a_period(settled_at(gcs, back_s) - back_s, config.ev_settle_s)  # settled again
        # settling again is a change PX4 reports (more than its 2 s report interval after the first report)
        assert gcs.hear(lambda: gcs.said(since)) and gcs.said(since) == [NOT_SETTLED], gcs.said()
        assert gcs.console == [READY], "PX4 prints it once in its life"
        assert gcs.arm() == mavlink.MAV_RESULT_ACCEPTED and gcs.vehicle.armed
    finally:
        gcs.close()


@pytest.mark.parametrize("action, mode", [(None, "hold"), ("land", "land")])
def test_offboard_loss_holds_or_lands_says_so_and_setpoints_streaming_again_end_it(action, mode):
    """As the airframe sets it (COM_OF_LOSS_T 0.3 s, COM_OBL_RC_ACT Hold), or Land."""
    config = VehicleConfig()
    assert (config.offboard_loss_s, config.offboard_loss_action) == (0.3, "hold")  # the airframe's
    gcs = Station() if action is None else Station(offboard_loss_action=action)
    vehicle = gcs.vehicle
    try:
        gcs.ready_for_takeoff()

        def run(seconds: float, streaming: bool) -> None:
            for _ in range(round(seconds / DT_S)):
                if streaming:
                    gcs.send("set_attitude_target", 0, 1, 1, 0b00000111, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
                gcs.t_s += DT_S
                vehicle.control(StateMeasurement(gcs.t_s, np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0, 0.0, 0.0),
                                on_ground=False)
                gcs.listen()

        run(0.3, True)
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
        gcs.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MAIN_OFFBOARD)
        run(0.5, True)
        assert vehicle.mode_name == "offboard" and vehicle.armed
        last_setpoint_s = gcs.t_s - DT_S  # the vehicle's time when the last one arrived
        run(1.0, False)
        (failsafe,) = gcs.entries("failsafe")
        after_s = failsafe["vehicle_t_s"] - last_setpoint_s
        assert within_a_period(after_s, config.offboard_loss_s), after_s  # COM_OF_LOSS_T
        assert vehicle.mode_name == mode and gcs.hear(lambda: "Failsafe activated" in gcs.said()), gcs.said()
        run(0.3, True)
        assert vehicle.mode_name == "offboard", "PX4 ends its offboard-loss failsafe when setpoints stream again"
        assert "Armed by external command" in gcs.said(), gcs.said()
    finally:
        gcs.close()


def test_landing_is_detected_and_disarms_two_seconds_later_in_px4s_words():
    gcs = Station()
    vehicle = gcs.vehicle
    try:
        gcs.ready_for_takeoff()
        for cmd, p1 in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0), (mavlink.MAV_CMD_NAV_LAND, 0.0)):
            gcs.command(cmd, p1)
        touchdown_s = gcs.t_s + DT_S
        for k in range(1, 201):  # 4 s of the vehicle's time on the ground, in land
            vehicle.control(StateMeasurement(gcs.t_s + k * DT_S, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0),
                            on_ground=True)
        assert gcs.hear(lambda: "Disarmed by landing" in gcs.said()), gcs.said()
    finally:
        gcs.close()
    said = gcs.entries("statustext")
    assert [e["text"] for e in said] == [NOT_SETTLED, "Armed by external command", "Landing at current position",
                                         "Landing detected", "Disarmed by landing"]
    assert not vehicle.armed and said[3]["vehicle_t_s"] == pytest.approx(touchdown_s)
    disarmed_s = said[4]["vehicle_t_s"] - touchdown_s  # COM_DISARM_LAND after touch-down
    assert within_a_period(disarmed_s, VehicleConfig().disarm_after_landing_s), disarmed_s
    assert gcs.said()[-2:] == ["Landing detected", "Disarmed by landing"]  # what a ground station hears


def test_parameters_are_read_and_set_as_px4_answers_them_and_ekf2_ev_qmin_decides_what_is_fused():
    """PARAM_REQUEST_READ / PARAM_SET answered with PARAM_VALUE as PX4 answers them (int32 bytewise, floats as
    floats), from the world's airframe file; a name it does not have gets no answer; with EKF2_EV_QMIN set to 0
    (PX4's default) a pose with quality -1 is fused, as EKF2 does (ev_control.cpp)."""
    import struct

    from sim.px4_sitl import load_params

    s = Station()
    try:
        def values(since: int, name: str) -> list:
            return [m for m in s.heard[since:] if m.get_type() == "PARAM_VALUE" and m.param_id == name]

        def read(name: str):
            since = len(s.heard)
            s.send("param_request_read", 1, 1, name.encode(), -1)
            s.hear(lambda: values(since, name), timeout_s=1.0)
            got = values(since, name)
            return got[-1] if got else None

        airframe = load_params()
        qmin = read("EKF2_EV_QMIN")
        assert qmin.param_type == mavlink.MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", qmin.param_value))[0] == int(airframe["EKF2_EV_QMIN"]) == 1
        loss = read("COM_OF_LOSS_T")
        assert loss.param_type == mavlink.MAV_PARAM_TYPE_REAL32 and loss.param_value == pytest.approx(0.3)
        assert read("NO_SUCH_PARAM") is None
        s.stream(3.0, quality=-1)
        assert not s.vehicle.ready, "quality -1 is not fused with EKF2_EV_QMIN 1"
        since = len(s.heard)
        s.send("param_set", 1, 1, b"EKF2_EV_QMIN", struct.unpack("<f", struct.pack("<i", 0))[0],
               mavlink.MAV_PARAM_TYPE_INT32)
        assert s.hear(lambda: values(since, "EKF2_EV_QMIN")), "PARAM_SET is answered with the new value"
        assert struct.unpack("<i", struct.pack("<f", values(since, "EKF2_EV_QMIN")[-1].param_value))[0] == 0
        s.stream(3.0, quality=-1)
        assert s.vehicle.ready, "with EKF2_EV_QMIN 0 the stale pose is fused"
        s.hear(lambda: s.last("ESTIMATOR_STATUS") is not None and s.last("ESTIMATOR_STATUS").flags & 8)
        status = s.last("ESTIMATOR_STATUS")
        assert status is not None and status.flags & 8 and not status.flags & 128
    finally:
        s.close()
