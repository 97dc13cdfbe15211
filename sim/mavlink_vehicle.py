"""The simulator presented as a PX4 quadrotor on a MAVLink UDP endpoint (pymavlink, MAVLink 2).

What a ground station (MAVSDK) sees: a 1 Hz HEARTBEAT as ``MAV_TYPE_QUADROTOR`` /
``MAV_AUTOPILOT_PX4`` with PX4's mode encoding (``custom_mode = main << 16 | sub << 24``,
``base_mode`` custom-mode-enabled plus the armed flag); COMMAND_ACK for every COMMAND_LONG and
COMMAND_INT (accepted: arm/disarm 400, set mode 176, take-off 22, land 21, message requests; refused
as unsupported: anything else); ``SET_ATTITUDE_TARGET`` applied to the physics while in offboard;
ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, ODOMETRY at the control rate and
GLOBAL_POSITION_INT, HOME_POSITION, SYS_STATUS, BATTERY_STATUS, EXTENDED_SYS_STATE slower.

Its own flight modes are deliberately simple stand-ins for PX4's (a PD position loop on the
truth, with the true hover thrust, through the same attitude/thrust interface the offboard
setpoints use): **hold** (AUTO.LOITER) keeps the position where it was entered; **take-off**
(AUTO.TAKEOFF) climbs 0.5 m/s to ``takeoff_height_m`` above the ground, then holds; **land**
(AUTO.LAND) descends at 0.5 m/s; once at rest on the ground it idles, level, without position
control (PX4's land detector), and disarms 2 s of vehicle time later (PX4's COM_DISARM_LAND);
**offboard** applies the newest SET_ATTITUDE_TARGET, and if none has come for
``offboard_loss_s`` it holds (or lands) by itself, as the world's PX4 airframe sets COM_OF_LOSS_T and
COM_OBL_RC_ACT (``sim/px4/neso_quad.params``, read here: 0.3 s, Hold; the last line of defence behind the gateway's
own failsafe) and, as PX4 does, returns to offboard when setpoints stream again. Disarmed: motors off. It says
what PX4 v1.16 says in STATUSTEXT for the same events (arming, disarming, land, landing detected, the failsafe);
it answers SET_GPS_GLOBAL_ORIGIN with GPS_GLOBAL_ORIGIN, and a request for it only once it has one, as PX4 does. Where
it still differs from PX4 SITL: docs/px4.md, "Real PX4 in the loop".

**Pre-flight checks** (PX4's EKF2 settling on external vision, then commander's arming checks): it is ready
only once it has received external-vision ODOMETRY (quality at least EKF2_EV_QMIN 1, as the gateway forwards the
motion capture) without a gap longer than ``ev_timeout_s`` for ``ev_settle_s``. Until then an arm command is
refused as PX4 refuses it (COMMAND_ACK ``MAV_RESULT_TEMPORARILY_REJECTED`` and the CRITICAL STATUSTEXT "Arming
denied: Resolve system health failures first", Commander::arm); when external vision starts arriving it says
PX4's CRITICAL "Preflight Fail: heading estimate not stable" (PX4 reports its checks on a change of their
results, at most once per ``health_report_interval_s``, not periodically); ready, it prints "Ready for
takeoff!" to its ``console`` once in its life, as PX4 SITL's commander does on its console (PX4_INFO: a log line,
never a STATUSTEXT). Over MAVLink readiness shows as PX4 shows it: HEARTBEAT ``system_status`` UNINIT while not
ready, STANDBY when ready (MAVLink's HEARTBEAT stream), and SYS_STATUS's ``MAV_SYS_STATUS_PREARM_CHECK`` health
bit (MAVSDK's ``health.is_armable``). External vision lost for longer than ``ev_timeout_s`` while disarmed makes
it not ready again, silently, until it has settled again.

**Its clock is the world's**, as PX4 SITL's is in lockstep with its simulator: every timeout and interval above
(external vision's settling and loss, offboard loss, the disarm after landing, its reports) is measured in the
world time the simulator hands to :meth:`control` and :meth:`publish`; what arrives between two steps is stamped
with the newest. A loaded machine that slows the world slows this PX4 with it, never the other way round.

Everything received is logged (``log``, and as JSON lines to ``log_path`` if given) with its
``time.monotonic()`` arrival stamp (``t``) and the vehicle's time then (``vehicle_t_s``), so tests can check what
actually reached the vehicle.
Frames: MAVLink attitudes are NED/FRD; the simulator is ENU/FLU (converted here).
"""
from __future__ import annotations

import json
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

os.environ.setdefault("MAVLINK20", "1")  # ODOMETRY and MAVSDK's messages need MAVLink 2

import numpy as np  # noqa: E402
from pymavlink import mavutil  # noqa: E402

from neso.control import ControlConfig, PositionController  # noqa: E402
from neso.frames import attitude_enu_from_ned, quat_ned_from_enu_euler, quat_to_euler_ned  # noqa: E402
from neso.types import AttitudeSetpoint, Reference, StateMeasurement, VehicleModel  # noqa: E402
from sim.px4_sitl import load_params  # noqa: E402

mavlink = mavutil.mavlink

# PX4 main / sub modes (px4_custom_mode.h)
MAIN_MANUAL, MAIN_POSCTL, MAIN_AUTO, MAIN_OFFBOARD = 1, 3, 4, 6
SUB_READY, SUB_TAKEOFF, SUB_LOITER, SUB_LAND = 1, 2, 3, 6
OFFBOARD_LOSS_ACTIONS = {4: "land", 5: "hold"}  # COM_OBL_RC_ACT values the imitation flies (PX4: 0-7)
MODE_NAMES = {(MAIN_MANUAL, 0): "manual", (MAIN_POSCTL, 0): "posctl", (MAIN_AUTO, SUB_READY): "ready",
              (MAIN_AUTO, SUB_TAKEOFF): "takeoff", (MAIN_AUTO, SUB_LOITER): "hold", (MAIN_AUTO, SUB_LAND): "land",
              (MAIN_OFFBOARD, 0): "offboard"}
ARMING_DENIED = "Arming denied: Resolve system health failures first"  # Commander::arm, canArm false
NOT_SETTLED = "Preflight Fail: heading estimate not stable"  # estimatorCheck: pre_flt_fail_innov_heading
READY = "Ready for takeoff!"  # Commander::checkAndInformReadyForTakeoff, SITL only, PX4_INFO once
ACCEPTED_COMMANDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_NAV_TAKEOFF,
    mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
}


@dataclass(frozen=True)
class VehicleConfig:
    """``target``: where the ground station listens (pymavlink ``udpout:host:port``).
    ``hover_thrust_norm``: the vehicle's own (true) hover thrust, used by its internal modes."""

    target: str = "udpout:127.0.0.1:14540"
    system_id: int = 1
    hover_thrust_norm: float = 0.525
    takeoff_height_m: float = 1.0
    climb_speed_mps: float = 0.5
    land_speed_mps: float = 0.5
    # PX4's offboard-loss timeout and action as the world's airframe sets them (what PX4 SITL flies)
    offboard_loss_s: float = field(default_factory=lambda: float(load_params()["COM_OF_LOSS_T"]))
    offboard_loss_action: str = field(default_factory=lambda: OFFBOARD_LOSS_ACTIONS[int(load_params()["COM_OBL_RC_ACT"])])
    disarm_after_landing_s: float = 2.0  # PX4's COM_DISARM_LAND default
    battery_full_v: float = 16.8
    battery_empty_v: float = 13.2
    battery_minutes: float = 10.0
    # PX4 v1.16.0 SITL in this world, from its first external-vision sample (vehicle_visual_odometry) to
    # commander's "Ready for takeoff!", read from three boots' ULogs: 1.93, 1.94, 1.94 s (EKF2's heading
    # innovation test passes ~0.9 s after the first sample, commander's checks pass ~1 s later).
    ev_settle_s: float = 1.9
    # EKF2_NOAID_TOUT's default (EKF2's valid_timeout_max, 5 s): inertial dead reckoning that long and EKF2 reports
    # the local position invalid, which fails commander's arming checks. A stand-in: PX4 also stops fusing after
    # 1 s (no_aid_timeout_max) and may fail on the position error growing first; here only the 5 s count.
    ev_timeout_s: float = 5.0
    health_report_interval_s: float = 2.0  # PX4's HealthAndArmingChecks Report: at most one report per 2 s
    log_path: str = ""


class MavlinkVehicle:
    """One simulated PX4. The simulator loop calls :meth:`control` each period (what to apply) and
    :meth:`publish` after stepping (telemetry); a receiver thread handles what arrives. ``console``: where it
    prints what PX4 prints on its console only ("Ready for takeoff!"); the service passes its log."""

    def __init__(self, config: VehicleConfig, *, dt_s: float, console: Callable[[str], None] | None = None) -> None:
        self.config = config
        self.console = console
        self.dt_s = dt_s
        self.conn = mavutil.mavlink_connection(config.target, source_system=config.system_id,
                                               source_component=mavlink.MAV_COMP_ID_AUTOPILOT1, dialect="common")
        self.lock = threading.Lock()
        self.send_lock = threading.Lock()
        self.armed = False
        self.main_mode, self.sub_mode = MAIN_AUTO, SUB_READY
        self.offboard_setpoint: AttitudeSetpoint | None = None
        self.offboard_setpoint_s = -math.inf
        self.log: list[dict] = []
        self.received = 0  # MAVLink messages its receiver has handled (tests wait for theirs before stepping on)
        self._log_file = open(config.log_path, "a", buffering=1) if config.log_path else None
        ctrl = ControlConfig(dt_s=dt_s, vehicle=VehicleModel(hover_thrust_norm=config.hover_thrust_norm))
        self._position = PositionController(ctrl)
        self._target: np.ndarray | None = None
        self._touchdown_s: float | None = None  # vehicle time (s) AUTO.LAND came to rest on the ground
        self._offboard_lost = False  # in the offboard-loss failsafe (its Land), which setpoints streaming again end
        self._home_enu_m: np.ndarray | None = None
        self._last_meas: StateMeasurement | None = None
        self._on_ground = True
        self._ev_since_s: float | None = None  # start of the current unbroken external-vision run (vehicle time)
        self._ev_last_s = -math.inf
        self.ready = False  # its pre-flight checks pass (module docstring)
        self.params = dict(load_params())  # name → value as the airframe file writes it (a point: a float)
        self.origin: tuple[int, int, int] | None = None  # its EKF global origin (lat, lon deg·1e7, alt mm)
        self._said_ready = False
        self._last_report_s = -math.inf
        self._report_due = False  # a change of the checks' results not yet reported (PX4's rate limit)
        self._text_id = 0  # STATUSTEXT id, one per text
        self.t_s = 0.0  # the vehicle's clock: the world's time, as the simulator last handed it (module docstring)
        self._next_slow_s = 0.0
        self._next_hb_s = 0.0
        self._next_estimator_s = 0.0
        self._stop = threading.Event()
        self._rx = threading.Thread(target=self._receive, name="mavlink-vehicle-rx", daemon=True)
        self._rx.start()

    # -- what arrives ------------------------------------------------------------------------
    def _record(self, entry: dict) -> None:
        entry["vehicle_t_s"] = self.t_s
        self.log.append(entry)
        if len(self.log) > 200_000:
            del self.log[:100_000]
        if self._log_file is not None:
            self._log_file.write(json.dumps(entry) + "\n")

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError):
                if self._stop.is_set():
                    return
                continue
            if msg is None:
                continue
            now, arrived = self.t_s, time.monotonic()
            kind = msg.get_type()
            if kind == "ODOMETRY" and (self._param("EKF2_EV_QMIN") <= 0 or msg.quality >= self._param("EKF2_EV_QMIN")):
                self._on_external_vision(now)  # EKF2's quality_sufficient (ev_control.cpp): -1 is not fused with 1
            if kind == "SET_ATTITUDE_TARGET":
                self._on_attitude_target(msg, now, arrived)
            elif kind in ("COMMAND_LONG", "COMMAND_INT"):
                self._on_command(msg, now, arrived)
            elif kind == "ODOMETRY":
                self._record({"t": arrived, "kind": "odometry", "xyz_ned": [msg.x, msg.y, msg.z], "q": list(msg.q),
                              "frame": msg.frame_id, "quality": msg.quality})
            elif kind == "SET_GPS_GLOBAL_ORIGIN":  # PX4 takes it as its EKF origin and reports it back
                self._record({"t": arrived, "kind": "global_origin", "lat_e7": msg.latitude, "lon_e7": msg.longitude})
                self.origin = (msg.latitude, msg.longitude, msg.altitude)
                self._send_origin()
            elif kind in ("PARAM_REQUEST_READ", "PARAM_SET", "PARAM_REQUEST_LIST"):
                self._on_param(msg, kind)
            self.received += 1  # handled

    # -- parameters (PX4's: the world's airframe file, sim/px4/neso_quad.params) ---------------------------
    def _param(self, name: str) -> float:
        with self.lock:
            return float(self.params[name])

    def _on_param(self, msg, kind: str) -> None:
        """PARAM_REQUEST_READ / PARAM_SET / PARAM_REQUEST_LIST answered with PARAM_VALUE as PX4 answers them: int32
        values bytewise in the float field (PX4's encoding; MAVSDK reads it so from a PX4); a name it does not have
        gets no answer (PX4 v1.16 sends none)."""
        names = list(self.params)
        if kind == "PARAM_REQUEST_LIST":
            wanted = names
        else:
            name = msg.param_id.rstrip("\0") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\0")
            if name not in self.params:
                return
            wanted = [name]
            if kind == "PARAM_SET":
                is_int = "." not in self.params[name]
                value = _int_of_bytes(msg.param_value) if is_int else float(msg.param_value)
                with self.lock:
                    self.params[name] = str(int(value)) if is_int else repr(float(value))
                self._record({"t": time.monotonic(), "kind": "param_set", "name": name, "value": value})
        for name in wanted:
            text = self.params[name]
            if "." in text:
                value, kind_id = float(text), mavlink.MAV_PARAM_TYPE_REAL32
            else:
                value, kind_id = _bytes_of_int(int(text)), mavlink.MAV_PARAM_TYPE_INT32
            index = names.index(name)
            self._send(lambda m, n=name, v=value, k=kind_id, i=index: m.param_value_send(n.encode(), v, k, len(names), i))

    def _on_attitude_target(self, msg, now: float, arrived: float) -> None:
        q = tuple(float(v) for v in msg.q)
        thrust = float(msg.thrust)
        entry = {"t": arrived, "kind": "setpoint", "q": q, "thrust": thrust, "mask": int(msg.type_mask)}
        finite = all(math.isfinite(v) for v in (*q, thrust)) and abs(math.sqrt(sum(v * v for v in q)) - 1) < 1e-3
        if finite and 0.0 <= thrust <= 1.0:
            roll_ned, pitch_ned, yaw_ned = quat_to_euler_ned(q)
            roll, pitch, yaw = attitude_enu_from_ned(roll_ned, pitch_ned, yaw_ned)
            entry.update(roll_ned_rad=roll_ned, pitch_ned_rad=pitch_ned, yaw_ned_rad=yaw_ned)
            with self.lock:
                self.offboard_setpoint = AttitudeSetpoint(roll, pitch, yaw, thrust, 0.0)
                self.offboard_setpoint_s = now
        else:
            entry["rejected"] = True  # PX4 ignores such a setpoint; the log shows it arrived
        self._record(entry)

    # -- pre-flight checks (module docstring) -----------------------------------------------------
    def _on_external_vision(self, now: float) -> None:
        with self.lock:
            if self._ev_since_s is None or now - self._ev_last_s > self.config.ev_timeout_s:
                self._ev_since_s = now  # a new run: EKF2 (re)starts fusing, its heading innovation is large
                self._report_due = True
            self._ev_last_s = now
        self._check(now)

    def _check(self, now: float) -> None:
        """Commander's checks (PX4 runs them at 10 Hz; here on every ODOMETRY and telemetry step)."""
        c = self.config
        say, changed, became_ready = "", False, False
        with self.lock:
            if self._ev_since_s is not None and now - self._ev_last_s > c.ev_timeout_s:
                self._ev_since_s = None  # EKF2's local position invalid
            ready = self._ev_since_s is not None and now - self._ev_since_s >= c.ev_settle_s
            if self.armed:
                ready = ready or self.ready  # once flying, its failsafes (not these checks) act on a loss
            if ready != self.ready:
                self.ready, changed, became_ready = ready, True, ready
                self._record({"t": time.monotonic(), "kind": "preflight", "ready": ready})
            if self._report_due and not ready and now - self._last_report_s >= c.health_report_interval_s:
                self._report_due, self._last_report_s, say = False, now, NOT_SETTLED
            elif ready:
                self._report_due = False
            print_ready = became_ready and not self._said_ready
            self._said_ready = self._said_ready or print_ready
        if say:
            self._say(mavlink.MAV_SEVERITY_CRITICAL, say)
        if print_ready:
            self._record({"t": time.monotonic(), "kind": "console", "text": READY})
            if self.console is not None:
                self.console(READY)
        if changed:
            self._heartbeat()  # system_status changes with the checks

    def _on_command(self, msg, now: float, arrived: float) -> None:
        cmd = int(msg.command)
        params = [float(getattr(msg, f"param{i}")) for i in range(1, 5)]
        if msg.get_type() == "COMMAND_LONG":
            params += [float(msg.param5), float(msg.param6), float(msg.param7)]
        result = mavlink.MAV_RESULT_ACCEPTED if cmd in ACCEPTED_COMMANDS else mavlink.MAV_RESULT_UNSUPPORTED
        self._check(now)
        with self.lock:
            said, severity = "", mavlink.MAV_SEVERITY_INFO
            if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if params[0] >= 0.5 and not self.armed and not self.ready:
                    # PX4 checks an external arm command even when forced (21196): Commander::arm
                    result, said, severity = mavlink.MAV_RESULT_TEMPORARILY_REJECTED, ARMING_DENIED, \
                        mavlink.MAV_SEVERITY_CRITICAL
                elif params[0] >= 0.5:
                    self.armed, self._touchdown_s = True, None
                    said = "Armed by external command"
                elif self._on_ground or params[1] == 21196:  # 21196: forced disarm
                    self.armed = False
                    said = "Disarmed by external command"
                else:
                    result = mavlink.MAV_RESULT_DENIED  # PX4 refuses to disarm in the air
            elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
                main, sub = int(params[1]), int(params[2])
                if main == MAIN_OFFBOARD and (self.offboard_setpoint is None or now - self.offboard_setpoint_s > 0.5):
                    result = mavlink.MAV_RESULT_DENIED  # PX4 refuses offboard without a setpoint stream
                else:
                    self._set_mode(main, sub if main == MAIN_AUTO else 0)
            elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
                if self.armed:
                    self._set_mode(MAIN_AUTO, SUB_TAKEOFF)
                else:
                    result = mavlink.MAV_RESULT_DENIED
            elif cmd == mavlink.MAV_CMD_NAV_LAND:
                self._set_mode(MAIN_AUTO, SUB_LAND)
                said = "Landing at current position"
            state = (self.armed, self.mode_name)
        self._record({"t": arrived, "kind": "command", "command": cmd, "params": params, "result": int(result),
                      "armed": state[0], "mode": state[1]})
        self._send(lambda m: m.command_ack_send(cmd, result, 100, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        if said:
            self._say(severity, said)
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE and int(params[0]) == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send_autopilot_version()
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE and int(params[0]) == mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            self._send_origin()
        if cmd == mavlink.MAV_CMD_DO_SET_MODE or cmd in (mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
                                                         mavlink.MAV_CMD_COMPONENT_ARM_DISARM):
            self._heartbeat()  # report the new mode at once, as PX4 does

    def _set_mode(self, main: int, sub: int) -> None:
        """Under ``self.lock``."""
        if (main, sub) != (self.main_mode, self.sub_mode):
            self._target = None  # hold/take-off/land pick their target from where the vehicle is
            self._touchdown_s = None
        self.main_mode, self.sub_mode = main, sub

    @property
    def mode_name(self) -> str:
        return MODE_NAMES.get((self.main_mode, self.sub_mode), f"{self.main_mode}/{self.sub_mode}")

    # -- what the simulator applies ----------------------------------------------------------
    def control(self, meas: StateMeasurement, *, on_ground: bool) -> AttitudeSetpoint:
        """The attitude/thrust command for the next period given the vehicle's state (``meas.t_s``: the world's
        time, the vehicle's clock)."""
        now = self.t_s = meas.t_s
        self._last_meas = meas
        self._on_ground = on_ground
        if self._home_enu_m is None:
            self._home_enu_m = np.array(meas.pos_enu_m, dtype=float)
        with self.lock:
            if not self.armed:
                self._target = None
                return AttitudeSetpoint(0.0, 0.0, meas.yaw_rad, 0.0, 0.0)
            fresh = now - self.offboard_setpoint_s <= self.config.offboard_loss_s
            if self._offboard_lost and fresh and (self.main_mode, self.sub_mode) in ((MAIN_AUTO, SUB_LAND),
                                                                                      (MAIN_AUTO, SUB_LOITER)):
                self._set_mode(MAIN_OFFBOARD, 0)  # PX4 ends its offboard-loss failsafe when setpoints stream again
                self._record({"t": time.monotonic(), "kind": "failsafe", "what": "setpoints again: back to offboard"})
            if self.main_mode == MAIN_OFFBOARD:
                if fresh:
                    self._offboard_lost = False
                    return self.offboard_setpoint
                # PX4's offboard-loss action COM_OBL_RC_ACT (sim/px4/neso_quad.params)
                action = self.config.offboard_loss_action
                self._record({"t": time.monotonic(), "kind": "failsafe", "what": f"offboard loss: {action}"})
                self._say(mavlink.MAV_SEVERITY_CRITICAL, "Failsafe activated")
                self._set_mode(MAIN_AUTO, SUB_LOITER if action == "hold" else SUB_LAND)
                self._offboard_lost = True
            if self._target is None:
                self._target = np.array(meas.pos_enu_m, dtype=float)
                self._position.reset(np.array([0.0, 0.0, self._position.config.vehicle.hover_thrust_n]))
            target, vel = self._target.copy(), np.zeros(3)
            if self.sub_mode == SUB_TAKEOFF:
                top = self._home_enu_m[2] + self.config.takeoff_height_m
                target[2] = min(top, self._target[2] + self.config.climb_speed_mps * self.dt_s)
                vel[2] = self.config.climb_speed_mps if target[2] < top else 0.0
                self._target = target
                if meas.pos_enu_m[2] > top - 0.05:
                    self._set_mode(MAIN_AUTO, SUB_LOITER)
                    self._target = target
            elif self.sub_mode == SUB_LAND:
                if on_ground and self._touchdown_s is None:
                    self._touchdown_s = meas.t_s
                    self._say(mavlink.MAV_SEVERITY_INFO, "Landing detected")
                if self._touchdown_s is not None:
                    # Landed stays landed (PX4's land detector): motors idle, level, no position control. Flying
                    # the position loop on the ground tilts the vehicle up to the tilt limit (a few mm of position
                    # error over a vertical force at its minimum), and it rocked, hopped and tipped over.
                    if meas.t_s - self._touchdown_s >= self.config.disarm_after_landing_s:
                        self.armed, self._touchdown_s, self._offboard_lost = False, None, False
                        self._set_mode(MAIN_AUTO, SUB_READY)  # the next arming starts from "ready", not from "land"
                        self._record({"t": time.monotonic(), "kind": "disarmed", "why": "landed"})
                        self._say(mavlink.MAV_SEVERITY_INFO, "Disarmed by landing")
                    return AttitudeSetpoint(0.0, 0.0, meas.yaw_rad, 0.0, 0.0)
                target[2] = self._target[2] - self.config.land_speed_mps * self.dt_s
                vel[2] = -self.config.land_speed_mps
                self._target = target
            out = self._position.step(meas, Reference(pos_enu_m=target, vel_enu_mps=vel, yaw_rad=meas.yaw_rad),
                                      np.zeros(3))
            return out.setpoint

    # -- what goes out -------------------------------------------------------------------------
    def _send(self, fn) -> None:
        with self.send_lock:
            try:
                fn(self.conn.mav)
            except OSError:
                pass  # nobody listening yet (connection refused on loopback): next time

    def _heartbeat(self) -> None:
        with self.lock:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
            custom = (self.main_mode << 16) | (self.sub_mode << 24)
            status = (mavlink.MAV_STATE_ACTIVE if self.armed else
                      mavlink.MAV_STATE_STANDBY if self.ready else mavlink.MAV_STATE_UNINIT)
        self._send(lambda m: m.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom, status))

    def _send_origin(self) -> None:
        """GPS_GLOBAL_ORIGIN when it has one (PX4 sends it only with a valid origin: GPS_GLOBAL_ORIGIN.hpp)."""
        if self.origin is not None:
            lat, lon, alt = self.origin
            self._send(lambda m: m.gps_global_origin_send(lat, lon, alt, 0))

    def _send_autopilot_version(self) -> None:
        caps = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT)
        self._send(lambda m: m.autopilot_version_send(caps, 0, 0, 0, 0, bytes(8), bytes(8), bytes(8), 0, 0, 1))

    def _say(self, severity: int, text: str) -> None:
        """STATUSTEXT in PX4 v1.16's words for the same event (commander's mavlink_log_*), logged too."""
        self._record({"t": time.monotonic(), "kind": "statustext", "text": text})
        data = text.encode()
        with self.send_lock:
            self._text_id = self._text_id % 0xFFFF + 1
            text_id = self._text_id
        for seq, k in enumerate(range(0, len(data), 50)):  # PX4's STATUSTEXT stream: 50-byte chunks of one id
            self._send(lambda m, chunk=data[k:k + 50], seq=seq: m.statustext_send(severity, chunk, text_id, seq))

    def publish(self, meas: StateMeasurement, *, t_s: float, body_rates_frd_rps=(0.0, 0.0, 0.0)) -> None:
        """Telemetry after a simulator step (``t_s``: the world's time, the vehicle's clock): fast messages every
        call, slow ones at 1–10 Hz."""
        now = self.t_s = t_s
        self._check(now)
        boot_ms = int(now * 1e3) & 0xFFFFFFFF
        pos_ned = (float(meas.pos_enu_m[1]), float(meas.pos_enu_m[0]), -float(meas.pos_enu_m[2]))
        vel_ned = (float(meas.vel_enu_mps[1]), float(meas.vel_enu_mps[0]), -float(meas.vel_enu_mps[2]))
        q = quat_ned_from_enu_euler(meas.roll_rad, meas.pitch_rad, meas.yaw_rad)
        roll_ned, pitch_ned, yaw_ned = quat_to_euler_ned(q)
        p, qr, r = (float(v) for v in body_rates_frd_rps)
        self._send(lambda m: m.attitude_send(boot_ms, roll_ned, pitch_ned, yaw_ned, p, qr, r))
        self._send(lambda m: m.attitude_quaternion_send(boot_ms, *q, p, qr, r))
        self._send(lambda m: m.local_position_ned_send(boot_ms, *pos_ned, *vel_ned))
        nan21 = [math.nan] + [0.0] * 20
        self._send(lambda m: m.odometry_send(int(now * 1e6), mavlink.MAV_FRAME_LOCAL_NED,
                                             mavlink.MAV_FRAME_BODY_FRD, *pos_ned, list(q), *_frd_velocity(q, vel_ned),
                                             p, qr, r, nan21, nan21, 0, mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT, 100))
        if now >= self._next_hb_s:
            self._next_hb_s = now + 1.0
            self._heartbeat()
        if now >= self._next_slow_s:
            self._next_slow_s = now + 0.1
            self._send_slow(pos_ned, vel_ned, yaw_ned, boot_ms)
        if now >= self._next_estimator_s:
            self._next_estimator_s = now + 1.0
            self._send_estimator_status()

    def _send_estimator_status(self) -> None:
        """ESTIMATOR_STATUS as PX4 v1.16 streams it on its onboard link (1 Hz): EKF2's solution flags, a local
        position (attitude, horizontal velocity, relative horizontal and absolute vertical position) once it has
        settled on external vision, else attitude and a constant position."""
        flags = (1 | 2 | 8 | 32) if self.ready else (1 | 128)
        self._send(lambda m: m.estimator_status_send(int(self.t_s * 1e6), flags, 0, 0, 0, 0, 0,
                                                     0, 0, 0))

    def _send_slow(self, pos_ned, vel_ned, yaw_ned: float, boot_ms: int) -> None:
        lat0, lon0, alt0 = 47.397742, 8.545594, 488.0  # PX4 SITL's default origin (Zurich)
        lat = lat0 + math.degrees(pos_ned[0] / 6378137.0)
        lon = lon0 + math.degrees(pos_ned[1] / (6378137.0 * math.cos(math.radians(lat0))))
        hdg = int(math.degrees(yaw_ned) % 360 * 100)
        self._send(lambda m: m.global_position_int_send(boot_ms, int(lat * 1e7), int(lon * 1e7),
                                                        int((alt0 - pos_ned[2]) * 1e3), int(-pos_ned[2] * 1e3),
                                                        int(vel_ned[0] * 100), int(vel_ned[1] * 100),
                                                        int(vel_ned[2] * 100), hdg))
        self._send(lambda m: m.home_position_send(int(lat0 * 1e7), int(lon0 * 1e7), int(alt0 * 1e3), 0.0, 0.0, 0.0,
                                                  [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0))
        volts, remaining = self.battery(self.t_s)
        health = mavlink.MAV_SYS_STATUS_PREARM_CHECK if self.ready else 0  # PX4's SYS_STATUS stream sets only this
        self._send(lambda m: m.sys_status_send(0, 0, health, 500, int(volts * 1e3), -1, int(remaining * 100), 0, 0, 0,
                                               0, 0, 0))
        cells = [int(volts / 4 * 1e3)] * 4 + [65535] * 6
        self._send(lambda m: m.battery_status_send(0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO,
                                                   2500, cells, -1, -1, -1, int(remaining * 100)))
        with self.lock:
            armed, on_ground = self.armed, self._on_ground
        landed = (mavlink.MAV_LANDED_STATE_ON_GROUND if (on_ground or not armed) else mavlink.MAV_LANDED_STATE_IN_AIR)
        self._send(lambda m: m.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed))

    def battery(self, elapsed_s: float) -> tuple[float, float]:
        """(voltage V, remaining 0–1): linear over ``battery_minutes`` (a stand-in for a LiPo's sag)."""
        c = self.config
        remaining = max(0.0, 1.0 - elapsed_s / 60.0 / c.battery_minutes)
        return c.battery_empty_v + (c.battery_full_v - c.battery_empty_v) * remaining, remaining

    def close(self) -> None:
        self._stop.set()
        self._rx.join(timeout=1.0)
        self.conn.close()
        if self._log_file is not None:
            self._log_file.close()


def _frd_velocity(q_wxyz, vel_ned) -> tuple[float, float, float]:
    """The NED velocity expressed in the body FRD frame (ODOMETRY's child frame)."""
    w, x, y, z = q_wxyz
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    v = r.T @ np.asarray(vel_ned)
    return float(v[0]), float(v[1]), float(v[2])


def _bytes_of_int(value: int) -> float:
    """An int32 parameter as PX4 sends it in PARAM_VALUE's float field: its four bytes, reinterpreted."""
    return struct.unpack("<f", struct.pack("<i", value))[0]


def _int_of_bytes(value: float) -> int:
    return struct.unpack("<i", struct.pack("<f", value))[0]
