"""``px4_gateway``: the bus's attitude setpoints to a PX4 vehicle through MAVSDK-Python 4.x, and back.

The step object (:class:`GatewayCore`) never sees MAVSDK or Zenoh:

- **mapping**: a setpoint (ENU/FLU ZYX Euler, the controller's normalised thrust computed with
  its nominal hover thrust ``nominal_hover_thrust_norm``) becomes PX4's offboard attitude
  (NED/FRD Euler, deg) and a normalised thrust rescaled to the vehicle's hover thrust:
  ``thrust = thrust_norm / nominal_hover · hover_estimate``;
- **hover thrust**: learned online while flying offboard steadily (height above
  ``learn_min_height_m``, tilt under 15°, |v_z| under 0.3 m/s): the vertical thrust that held
  the vehicle, ``thrust · cos(tilt) · g / (g + a_z)``, low-pass filtered with ``hover_tau_s``;
  ``calibrate_hover`` replaces it by the mean over a few seconds of steady hover;
- **sanity**: a non-finite setpoint is refused (nothing sent, the last valid one stays);
  a tilt beyond ``max_tilt_rad`` is scaled back to it; a thrust outside
  [``thrust_min_norm``, ``thrust_max_norm``] is clamped; each is counted;
- **stale setpoints**: in offboard, ``stale_hold_s`` without a setpoint while at least
  ``stale_states`` states arrived unanswered (the controller is gone, not the whole machine
  stalled), or ``stale_max_s`` without a setpoint whatever the states do → command hold;
  ``land_after_s`` later (at once if the vehicle refused the hold, as PX4 without a global position does),
  unless an operator took over (``offboard_start``), → command land.
  Setpoints coming back (a restarted controller) do not resume offboard by themselves, and setpoints reach the
  vehicle only in offboard or while it is not known armed and not in a mode of its own (real PX4 returns to
  offboard by itself when they stream again after its own failsafe). PX4's own offboard-loss failsafe stays the
  last line.

The adapter connects MAVSDK to ``--mavlink`` (``udpin://0.0.0.0:14540`` for PX4 SITL or a
companion link), streams each setpoint with ``Offboard.set_attitude`` as it arrives (MAVSDK
re-sends the last one at 20 Hz), answers ``arm disarm takeoff land hold offboard_start
offboard_stop calibrate_hover preflight param_set`` commands with the vehicle's acknowledgement in words, publishes
TelemetryMsg at 10 Hz, and forwards the bus state (motion capture) to PX4 as external-vision
ODOMETRY stamped with the pose's capture (answering PX4's TIMESYNC so that it can use that time); while no state has
come for ``pose_lost_after_s`` it repeats the last pose with quality -1 (MAVLink's "odometry has failed") at each tick
of its watchdog (``watchdog_hz``, 50 Hz, paced by deadlines; ticks later than a period are counted in its health
report), so that PX4 knows the motion capture is lost rather than late. Every second it judges whether the vehicle may arm
(:mod:`flight.preflight`, :mod:`services.px4_preflight`), publishes the verdict and refuses ``arm`` on a no-go unless
the operator overrides it; it gives the vehicle a global origin only when it reports none.
"""
from __future__ import annotations

import argparse
import math
import queue
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from neso.frames import (NED_FROM_ENU, attitude_enu_from_ned, attitude_ned_from_enu, matrix_from_quat,
                         quat_ned_from_enu_euler, tilt_rad)
from neso.types import GRAVITY_MPS2, LOOP_PERIOD_S
from runtime.options import add_options, comma_list, config_from_options, option
from runtime.schema import SetpointMsg, StateMsg, TelemetryMsg
from services.px4_preflight import (FAST_TIMESYNC_HZ, MAV_CMD_REQUEST_MESSAGE, MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
                                   GatewayPreflight, TimeSync)

# modes in which the vehicle flies (or waits) on its own, or not reported yet: setpoints are withheld (see _may_stream)
VEHICLE_OWN_MODES = ("UNKNOWN", "HOLD", "LAND", "RETURN_TO_LAUNCH", "TAKEOFF", "MISSION", "FOLLOW_ME", "POSCTL",
                     "ALTCTL", "STABILIZED", "MANUAL", "ACRO", "RATTITUDE")
COMMANDS = ("arm", "disarm", "takeoff", "land", "hold", "offboard_start", "offboard_stop", "calibrate_hover",
            "preflight", "param_set")
# PX4 SITL's default home (PX4_HOME_LAT, PX4_HOME_LON, PX4_HOME_ALT in PX4-Autopilot's SITL start scripts): deg, deg, m
PX4_SITL_HOME_LLA = (47.397742, 8.545594, 488.0)
# The origin given to a vehicle that has none: PX4 SITL's home at altitude 0 m. PX4 v1.16 EKF2 (re)starts its vision
# height as an altitude above sea level (ev_height_control.cpp: resetAltitudeTo(-measurement), the origin's altitude
# left out), so with an origin at A m every restart of vision height fusion (at boot, after each motion-capture gap
# longer than EKF2's vision timeout) puts its local height A m off. Measured in SITL with 488 m: after a 1.9 s gap
# (gateway restarted mid-flight, PX4 in Hold) the local z jumped -0.19 → 487.8 m and Hold climbed at 2.8 m/s to
# 8.8 m chasing the altitude it held; with 0 m the height stays the motion capture's (tests/px4/test_px4_failsafe.py).
INDOOR_ORIGIN_LLA = (PX4_SITL_HOME_LLA[0], PX4_SITL_HOME_LLA[1], 0.0)
MAV_FRAME_LOCAL_NED, MAV_FRAME_BODY_FRD, MAV_ESTIMATOR_TYPE_VISION = 1, 12, 2  # MAVLink common.xml
# ESTIMATOR_STATUS_FLAGS (common.xml): attitude, horizontal velocity, relative horizontal and absolute vertical
# position (EKF2 sets CONST_POS_MODE, 128, also for a vehicle at rest: ekf_helper.cpp get_ekf_soln_status)
EKF_LOCAL_POSITION = 1 | 2 | 8 | 32


# MAVSDK's ActionResult / OffboardResult names (what the vehicle's COMMAND_ACK said) in words
REFUSALS = {
    "COMMAND_DENIED": "PX4 denied it", "BUSY": "PX4 is busy (temporarily rejected)",
    "TEMPORARILY_REJECTED": "PX4 rejected it for now", "COMMAND_DENIED_NOT_LANDED": "PX4 does not do it in the air",
    "COMMAND_DENIED_LANDED_STATE_UNKNOWN": "PX4 does not know whether it is landed", "TIMEOUT": "no answer from PX4",
    "NO_SYSTEM": "no vehicle", "CONNECTION_ERROR": "the link to the vehicle is down",
    "UNSUPPORTED": "PX4 does not support it", "FAILED": "PX4 tried and failed", "NO_SETPOINT_SET":
    "no setpoint streamed yet",
}


def parse_lla(text: str) -> tuple[float, ...]:
    """``lat_deg,lon_deg,alt_m`` (or ``none``: the empty tuple); SystemExit with one line for anything else."""
    if text.strip().lower() == "none":
        return ()
    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--global-origin {text!r}: give lat_deg,lon_deg,alt_m (e.g. 47.397742,8.545594,488) "
                         "or none") from None
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and math.isfinite(alt)):
        raise SystemExit(f"--global-origin {text!r}: latitude within ±90°, longitude within ±180°, a finite altitude")
    return lat, lon, alt


@dataclass(frozen=True)
class GatewayConfig:
    """Units in the names; angles in rad. ``forward_sources``: state sources forwarded to PX4 as
    external vision (``mocap``; ``sim`` too when the simulator stands in for the mocap)."""

    mavlink: str = option("udpin://0.0.0.0:14540", help="MAVSDK connection URL of the vehicle (PX4 SITL: "
                                                        "udpin://0.0.0.0:14540; serial:///dev/ttyACM0:57600)")
    connect_timeout_s: float = 30.0
    nominal_hover_thrust_norm: float = option(0.5, flag="--nominal-hover-thrust", unit="0–1",
                                              help="the hover thrust the controller's thrust_norm assumes (its model)")
    hover_thrust_norm: float = option(0.5, flag="--hover-thrust", unit="0–1", help="initial hover thrust estimate")
    learn_hover: bool = option(True, flag="--no-learn-hover", help="keep the hover thrust fixed")
    hover_tau_s: float = 5.0
    learn_min_height_m: float = 0.3
    max_tilt_rad: float = option(math.radians(40.0), flag="--max-tilt-deg", unit="deg", cli=(math.degrees, math.radians),
                                 help="tilt limit (larger tilts are scaled back, direction kept)")
    thrust_min_norm: float = 0.0
    thrust_max_norm: float = option(0.9, flag="--thrust-max", unit="0–1", help="thrust clamp")
    stale_hold_s: float = option(0.3, flag="--stale-hold", unit="s",
                                 help="without setpoints (with --stale-states states unanswered) before hold")
    stale_states: int = option(15, unit="samples", help="unanswered states before hold")
    stale_max_s: float = option(1.0, flag="--stale-max", unit="s", help="without setpoints before hold, states or not")
    land_after_s: float = option(3.0, flag="--land-after", unit="s", help="in failsafe hold before land")
    # the failsafe's hold commanded and the vehicle still in offboard this long: land. The mode is what MAVSDK reads in
    # PX4's HEARTBEAT, sent once a second of PX4's clock (slower than the wall's when SITL's world lags): at 1.0 s
    # a hold PX4 took could still read "offboard" (loaded run 39 at 59f6351: offboard, land, never hold). Two beats
    # and a half; a vehicle that ignores our hold is covered meanwhile by PX4's own offboard-loss failsafe
    hold_confirm_s: float = 2.5
    calibrate_s: float = 3.0
    telemetry_hz: float = 10.0
    # the watchdog checks for stale setpoints and the failsafe this often, and while the motion capture is lost tells
    # PX4 so and sends the level attitude each tick
    watchdog_hz: float = 50.0
    # 0.3 s: longer than the gaps a wireless link has in normal use, so one of them is not taken for a lost motion
    # capture (which overrides the controller: level flight at hover thrust) — measured by others: UDP every 20 ms
    # over Wi-Fi, 18 latency spikes above 100 ms in 10 min, 12 above 200 ms, one of 250 ms (C. Huitema, "The weird
    # case of the wifi latency spikes", 2023); 99th percentile 250 ms over a campus network (Sui et al., MobiSys
    # 2016); an access point's neighbour scan ~100 ms (dB Performance via SmallNetBuilder, "Wi-Fi Ping Spikes").
    # Wired and on one machine the gaps are milliseconds (PLATFORM.md: Zenoh p99 0.3-6 ms; NatNet on loopback here
    # 0 lost frames in 10 s). Blind for 0.3 s on the controller's last tilt (at most --max-tilt-deg) before level.
    # Off by default: with PX4 v1.16 SITL in lockstep (its clock the world's), answering its TIMESYNC at 50 Hz made
    # PX4's failure detector report "Attitude failure (roll)" at the start of every landing and PX4 never disarmed
    # (3 of 3 flights; 6 of 6 tests pass without it, the capture time in ODOMETRY or not): not understood yet. On a
    # real vehicle PX4's clock is real time and the sync is what lets EKF2 date each pose by its capture.
    time_sync: bool = option(False, flag="--time-sync",
                             help="answer PX4's TIMESYNC and stamp ODOMETRY with the pose's capture time, so EKF2 "
                                  "dates external vision by it (EKF2_EV_DELAY 0); off: PX4 stamps each pose on arrival "
                                  "and EKF2_EV_DELAY must hold the latency (neso preflight measures it)")
    pose_lost_after_s: float = option(0.3, flag="--pose-lost-after", unit="s",
                                      help="without a forwarded state before PX4 is told the motion capture failed "
                                           "(external-vision odometry quality -1) and the vehicle is flown level")
    global_origin: tuple[float, ...] = option(
        INDOOR_ORIGIN_LLA, cli=(lambda lla: ",".join(str(v) for v in lla) or "none", parse_lla),
        help="lat_deg,lon_deg,alt_m sent to a vehicle that reports no global origin as its EKF's (SET_GPS_GLOBAL_ORIGIN) "
             "until it reports one: indoors, without GPS, PX4 has a global position only from it, and its Hold, and "
             "arming in Hold, need one; a vehicle with an origin keeps its own (default: PX4 SITL's home at 0 m; keep "
             "the altitude 0 with vision height: PX4 v1.16 drops it at each vision restart, preflight checks it); "
             "'none': never sent")
    origin_retry_s: float = 1.0
    origin_probe_s: float = 2.0  # listening for an origin the vehicle has before sending ours
    origin_tries: int = 30  # SET_GPS_GLOBAL_ORIGIN sent at most this often (then a warning)
    # PX4 v1.16 SITL from its first external-vision sample to "Ready for takeoff!" (three ULogs: 1.93-1.94 s; the
    # MAVLink imitation's ev_settle_s): how long a refused arm is told EKF2 may still take
    ev_settle_s: float = 1.9
    preflight_period_s: float = 1.0  # the verdict is judged and published this often
    preflight_params_s: float = 10.0  # the vehicle's parameters are read again this often while it is disarmed
    preflight_fresh_s: float = 3.0  # an arm command judges by a verdict at most this old (else it checks first)
    forward_sources: tuple[str, ...] = option(("mocap",), cli=comma_list(),
                                              help="state sources forwarded to PX4 as external vision (comma-separated; "
                                                   "'' none)")


@dataclass(frozen=True, slots=True)
class Px4Attitude:
    """What goes to PX4: NED/FRD ZYX Euler in degrees (MAVSDK's ``Offboard.Attitude``) and thrust 0–1."""

    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    thrust_norm: float


class GatewayCore:
    """The pure step object: :meth:`on_setpoint`, :meth:`on_state`, :meth:`check_stale`."""

    def __init__(self, config: GatewayConfig) -> None:
        self.config = config
        self.hover_thrust_norm = config.hover_thrust_norm
        self.counts = {"refused_nonfinite": 0, "clamped_tilt": 0, "clamped_thrust": 0, "sent": 0, "pose_failed_sent": 0,
                       "watchdog_late": 0}
        self.last_setpoint_s: float | None = None
        self.last_sent: Px4Attitude | None = None
        self.failsafe = ""  # "", "hold" or "land"
        self._failsafe_since_s = 0.0
        self.states_since_setpoint = 0
        self._prev_vz: tuple[float, float] | None = None
        self._acc_z = 0.0
        self._calibration: list[float] | None = None
        self._calibration_end_s = 0.0
        self.last_pose_s: float | None = None
        self.pose_lost_since_s: float | None = None
        self.events: list[tuple[str, str]] = []
        self._delays_s: deque[float] = deque(maxlen=250)  # the last 5 s at 50 Hz: capture → sent to PX4
        self.pose_run_since_s: float | None = None  # the start of the current unbroken run of forwarded poses

    # -- setpoints ---------------------------------------------------------------------
    def on_setpoint(self, sp: SetpointMsg, now_s: float) -> Px4Attitude | None:
        """The attitude to send for ``sp``, or None when it is refused."""
        roll, pitch, yaw, thrust = sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm
        if not all(math.isfinite(v) for v in (roll, pitch, yaw, thrust)):
            self.counts["refused_nonfinite"] += 1
            return None
        self.last_setpoint_s = now_s
        self.states_since_setpoint = 0
        tilt = tilt_rad(roll, pitch)
        if tilt > self.config.max_tilt_rad:
            roll, pitch = _scale_tilt(roll, pitch, self.config.max_tilt_rad)
            self.counts["clamped_tilt"] += 1
        out = thrust / self.config.nominal_hover_thrust_norm * self.hover_thrust_norm
        clamped = min(max(out, self.config.thrust_min_norm), self.config.thrust_max_norm)
        if clamped != out:
            self.counts["clamped_thrust"] += 1
        r, p, y = attitude_ned_from_enu(roll, pitch, yaw)
        self.last_sent = Px4Attitude(math.degrees(r), math.degrees(p), math.degrees(y), clamped)
        self.counts["sent"] += 1
        return self.last_sent

    def setpoint_age_s(self, now_s: float) -> float:
        return -1.0 if self.last_setpoint_s is None else max(0.0, now_s - self.last_setpoint_s)

    # -- failsafe ----------------------------------------------------------------------
    def check_stale(self, now_s: float, *, offboard: bool, armed: bool) -> str:
        """``hold``/``land`` when the gateway must command it now, else ``""``."""
        if not armed:
            self.failsafe = "" if self.failsafe != "land" else self.failsafe
            return ""
        age = self.setpoint_age_s(now_s)
        c = self.config
        stale = age < 0 or (age > c.stale_hold_s and self.states_since_setpoint >= c.stale_states) or age > c.stale_max_s
        if self.failsafe == "" and offboard and stale:
            self.failsafe, self._failsafe_since_s = "hold", now_s
            self.events.append(("warning", f"no setpoint for {age:.2f} s ({self.states_since_setpoint} states unanswered) "
                                           "in offboard: commanding hold"))
            return "hold"
        if self.failsafe == "hold" and offboard and now_s - self._failsafe_since_s >= c.hold_confirm_s:
            # acknowledged or not, the vehicle did not switch (PX4 v1.16 acks Hold as accepted and then says
            # "Switching to Hold is currently not available" without a global position: measured)
            self.failsafe, self._failsafe_since_s = "land", now_s
            self.events.append(("warning", f"still in offboard {c.hold_confirm_s:.1f} s after the failsafe's hold: "
                                           "commanding land"))
            return "land"
        if self.failsafe == "hold" and now_s - self._failsafe_since_s >= self.config.land_after_s:
            self.failsafe, self._failsafe_since_s = "land", now_s
            self.events.append(("warning", f"{self.config.land_after_s:.1f} s in failsafe hold without an operator: "
                                           "commanding land"))
            return "land"
        return ""

    def hold_refused(self, why: str) -> None:
        """The vehicle refused the failsafe's hold (PX4 without a global position does): land at the next check
        instead of ``land_after_s`` later."""
        if self.failsafe == "hold":
            self._failsafe_since_s = -math.inf
            self.events.append(("warning", f"the vehicle refused hold ({why}): commanding land now"))

    def clear_failsafe(self) -> None:
        """An operator took over (offboard start, or an explicit mode command)."""
        self.failsafe = ""

    # -- motion capture to PX4 -----------------------------------------------------------------
    def capture_s(self, state: StateMsg, received_s: float) -> float:
        """When ``state``'s pose was captured, on this process's clock: its arrival ``received_s`` less the age the
        source gave it (``stamp_s - capture_stamp_s``, machine-independent); its arrival when unknown."""
        if state.capture_stamp_s <= 0.0:
            return received_s
        return received_s - max(0.0, state.stamp_s - state.capture_stamp_s)

    def on_pose(self, now_s: float, capture_s: float | None = None) -> None:
        """A state to forward to PX4 as external vision arrived at ``now_s``, its pose captured at ``capture_s``."""
        if capture_s is not None:
            self._delays_s.append(now_s - capture_s)
        if self.pose_run_since_s is None or self.pose_lost_since_s is not None:
            self.pose_run_since_s = now_s
        if self.pose_lost_since_s is not None:
            self.events.append(("info", f"motion capture back after {now_s - self.pose_lost_since_s:.2f} s: PX4 "
                                        "fuses it again (odometry quality 100)"))
            self.pose_lost_since_s = None
        self.last_pose_s = now_s

    def delay_to_vehicle_ms(self, link_s: float = 0.0) -> tuple[float, float] | None:
        """The motion capture's delay to the vehicle over the last 5 s (ms, p50 and p99): capture → sent here, plus
        ``link_s`` (half the link's round trip); None before any pose."""
        if not self._delays_s:
            return None
        d = sorted(self._delays_s)
        p50, p99 = d[len(d) // 2], d[min(len(d) - 1, math.ceil(0.99 * len(d)) - 1)]
        return (p50 + link_s) * 1e3, (p99 + link_s) * 1e3

    def refusal(self, command: str, result: str, now_s: float, *, ready: bool | None, said: str = "") -> str:
        """A command the vehicle refused, in words: what MAVSDK's ``result`` means, why when it can be told (an arm
        before PX4's pre-arm checks pass: no external vision yet, or EKF2 still settling on it and about how long
        more), and PX4's own words (``said``: its STATUSTEXT after the command)."""
        words = REFUSALS.get(result, result.replace("_", " ").lower())
        why = ""
        if command in ("arm", "takeoff") and ready is not True:  # None: PX4 has not reported its checks yet
            run = None if self.pose_run_since_s is None or self.pose_lost_since_s is not None else \
                now_s - self.pose_run_since_s
            settle = self.config.ev_settle_s
            if run is None:
                why = "not ready: PX4 gets no external vision (is the motion capture reaching the gateway?)"
            elif run < settle:
                why = (f"not ready: EKF2 settling on the motion capture, about {settle - run:.1f} s more ({run:.1f} s "
                       f"of it so far; PX4 v1.16 took {settle:g} s in SITL)")
            else:
                why = (f"not ready after {run:.1f} s of motion capture (PX4 v1.16 took {settle:g} s in SITL): "
                       "`neso preflight` for what fails")
        return f"{command} refused by the vehicle: {words}" + (f"; {why}" if why else "") + (
            f"; PX4 says: {said}" if said else "")

    def level_setpoint(self) -> Px4Attitude | None:
        """What to fly while the motion capture is lost, or while a failsafe's mode is not taken yet: level, at the
        vehicle's hover thrust, on the last setpoint's heading (None before any setpoint). The controller has no
        state to answer (or is gone); repeating its last tilt would accelerate the vehicle blind (measured on PX4
        SITL in a ±0.2 m limit cycle, 1 s lost: 2.8 m x, 5.5 m y; the controller killed mid-lemniscate and a
        refused hold: 11.8 m and a crash)."""
        if self.last_sent is None:
            return None
        return Px4Attitude(0.0, 0.0, self.last_sent.yaw_deg, self.hover_thrust_norm)

    def pose_failed(self, now_s: float) -> bool:
        """True while PX4 must be told its external vision failed: a pose was forwarded once and none for
        ``pose_lost_after_s`` since (the rigid body lost, the stream or the source stopped)."""
        if self.last_pose_s is None or now_s - self.last_pose_s <= self.config.pose_lost_after_s:
            return False
        if self.pose_lost_since_s is None:
            self.pose_lost_since_s = self.last_pose_s
            self.events.append(("warning", f"no motion capture for {now_s - self.last_pose_s:.2f} s: PX4 told it "
                                           "failed (external-vision odometry quality -1, which EKF2 does not fuse "
                                           "with EKF2_EV_QMIN 1) and flown level at the hover thrust until it is "
                                           "back"))
        return True

    # -- hover thrust --------------------------------------------------------------------
    def on_state(self, state: StateMsg, now_s: float, *, offboard: bool) -> None:
        """Learn the hover thrust from the state (ENU) and the last thrust sent."""
        self.states_since_setpoint += 1
        vz = state.vel_enu_mps[2]
        if self._prev_vz is not None and state.t_s > self._prev_vz[0]:
            dt = state.t_s - self._prev_vz[0]
            a = math.exp(-dt / 0.1)  # 0.1 s low-pass on the differentiated vertical velocity
            self._acc_z = a * self._acc_z + (1 - a) * (vz - self._prev_vz[1]) / dt
        self._prev_vz = (state.t_s, vz)
        sent = self.last_sent
        steady = (offboard and sent is not None and state.pos_enu_m[2] > self.config.learn_min_height_m
                  and tilt_rad(state.roll_rad, state.pitch_rad) < math.radians(15.0) and abs(vz) < 0.3
                  and self.setpoint_age_s(now_s) < 0.1)
        if not steady:
            return
        sample = sent.thrust_norm * math.cos(tilt_rad(state.roll_rad, state.pitch_rad)) * GRAVITY_MPS2 / max(
            GRAVITY_MPS2 + self._acc_z, 1.0)
        if self._calibration is not None:
            self._calibration.append(sample)
            if now_s >= self._calibration_end_s:
                self._finish_calibration()
        elif self.config.learn_hover and 0.05 < sample < 0.95:
            dt = LOOP_PERIOD_S  # one setpoint per loop period
            self.hover_thrust_norm += (sample - self.hover_thrust_norm) * dt / self.config.hover_tau_s

    def start_calibration(self, now_s: float) -> tuple[bool, str]:
        self._calibration, self._calibration_end_s = [], now_s + self.config.calibrate_s
        return True, f"calibrating the hover thrust over {self.config.calibrate_s:.1f} s of steady offboard hover"

    def _finish_calibration(self) -> None:
        samples, self._calibration = self._calibration, None
        if len(samples) < 10:
            self.events.append(("warning", f"hover calibration: only {len(samples)} steady samples, kept "
                                           f"{self.hover_thrust_norm:.3f}"))
            return
        self.hover_thrust_norm = min(max(sum(samples) / len(samples), 0.05), 0.95)
        self.events.append(("info", f"hover thrust calibrated: {self.hover_thrust_norm:.4f} from {len(samples)} samples"))


def _is_warning(status_text: str) -> bool:
    """A STATUSTEXT as the gateway keeps it (``SEVERITY: text``) of severity warning or worse."""
    return status_text.split(":")[0] in ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING")


def _scale_tilt(roll: float, pitch: float, max_tilt: float) -> tuple[float, float]:
    """Roll and pitch scaled by a common factor so the tilt is ``max_tilt`` (bisection; direction kept)."""
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = (lo + hi) / 2
        if tilt_rad(roll * mid, pitch * mid) > max_tilt:
            hi = mid
        else:
            lo = mid
    return roll * lo, pitch * lo


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, GatewayConfig)


def config_from_args(args) -> GatewayConfig:
    return config_from_options(GatewayConfig, args)


def run(args, bus) -> int:
    from runtime.node import Node, run_node

    config = config_from_args(args)
    node = Node("px4_gateway", vehicle=args.vehicle, bus=bus, config=config)
    return run_node(node, lambda n: Px4Link(n, config).run())


def autopilot_version(system) -> tuple[str, str]:
    """(the firmware's version as the vehicle reports it, ``PX4 v1.16.0 6ea3539``, or "" and why it is unknown):
    AUTOPILOT_VERSION through MAVSDK's Info; PX4 answers it, a vehicle that does not leaves it unknown."""
    from mavsdk.plugins.info import Info

    try:
        v = Info(system).get_version()
    except Exception as exc:  # InfoError: the vehicle did not answer
        return "", f"{type(exc).__name__}: {exc}"
    raw = v.flight_sw_git_hash or ""
    git = raw[:7] if raw.strip("0") else ""  # MAVSDK gives zeros for a vehicle that never answered
    if not (v.flight_sw_major or v.flight_sw_minor or v.flight_sw_patch or git):
        return "", "it did not report one"
    return f"PX4 v{v.flight_sw_major}.{v.flight_sw_minor}.{v.flight_sw_patch} {git}".strip(), ""


class Px4Link:
    """The MAVSDK side. Bus handlers only compute and send a setpoint (a non-blocking MAVSDK call)
    or store; blocking MAVSDK actions run on a worker thread."""

    def __init__(self, node, config: GatewayConfig) -> None:
        self.node = node
        self.config = config
        self.core = GatewayCore(config)
        self.tele = {"armed": None, "in_air": False, "mode": "UNKNOWN", "att": (0.0, 0.0, 0.0),
                     "pos_ned": (0.0, 0.0, 0.0), "vel_ned": (0.0, 0.0, 0.0), "battery_v": 0.0, "battery": -1.0,
                     "autopilot": "", "status_text": "", "local_position_ok": None, "armable": None,
                     "origin_alt_m": None}
        self.system = self.action = self.offboard = self.direct = None
        self.system_id = 0
        self.last_attitude = None  # the newest setpoint handed to MAVSDK (mavsdk.plugins.offboard.Attitude)
        self.last_pose: StateMsg | None = None  # the newest state forwarded to PX4
        self.watchdog_worst_late_s = 0.0  # the latest any watchdog tick ran after its deadline (s)
        self.last_pose_capture_s = 0.0  # its capture on this process's clock (ODOMETRY time_usec)
        self.actions: queue.Queue = queue.Queue()
        self.said: queue.Queue = queue.Queue()  # PX4's words not yet on the bus, in order (each gets a message)
        self.param = self.timesync = None
        self.preflight = GatewayPreflight(self)
        self.heard: deque[tuple[float, str]] = deque(maxlen=20)  # PX4's STATUSTEXT, with its arrival (preflight's)

    # -- life ----------------------------------------------------------------------------
    def run(self) -> None:
        node = self.node
        from mavsdk import ComponentType, Configuration, Mavsdk, log_subscribe

        log_subscribe(lambda level, message, file, line: level < 2 or (node.log(f"mavsdk: {message}") or True))
        self.mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            result = self.mavsdk.add_any_connection(self.config.mavlink)
            node.log(f"MAVLink connection {self.config.mavlink}: {result}")
            node.subscribe("setpoint", self._on_setpoint)
            node.subscribe("state", self._on_state)
            node.subscribe("network", self.preflight.watch.on_network)
            node.subscribe_health(self.preflight.watch.on_health)
            node.on_command(self._on_command, unlocked=COMMANDS)
            node.status_hook = self._status
            threading.Thread(target=self._telemetry_loop, name="px4-telemetry", daemon=True).start()
            threading.Thread(target=self._watchdog_loop, name="px4-watchdog", daemon=True).start()
            threading.Thread(target=self.preflight.loop, name="px4-preflight", daemon=True).start()
            self._connect()
            while not node.stopping:
                try:
                    what, done = self.actions.get(timeout=0.05)
                except queue.Empty:
                    continue
                done(self._do(what))
        finally:
            with node.lock:  # no bus handler may reach a MAVSDK plugin once it is destroyed
                self.system = self.action = self.offboard = self.direct = self.param = None
            if self.timesync is not None:
                self.timesync.close()
            self.mavsdk.destroy()

    def _connect(self) -> None:
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry

        deadline = time.monotonic() + self.config.connect_timeout_s
        system = None
        while system is None and not self.node.stopping:
            system = self.mavsdk.first_autopilot(timeout_s=0.5)
            if system is None and time.monotonic() > deadline:
                self.node.event("warning", f"no autopilot on {self.config.mavlink} after "
                                           f"{self.config.connect_timeout_s:.0f} s; still waiting")
                deadline = math.inf
        if system is None:
            return
        tele = Telemetry(system)
        self.action, self.offboard, self.direct = Action(system), Offboard(system), MavlinkDirect(system)
        self.system_id = system.get_system_id()
        t = self.tele
        tele.subscribe_armed(lambda v, _: t.__setitem__("armed", bool(v)))
        tele.subscribe_in_air(lambda v, _: t.__setitem__("in_air", bool(v)))
        tele.subscribe_flight_mode(lambda v, _: t.__setitem__("mode", v.name))
        tele.subscribe_attitude_euler(lambda v, _: t.__setitem__("att", (v.roll_deg, v.pitch_deg, v.yaw_deg)))
        tele.subscribe_position_velocity_ned(lambda v, _: t.update(
            pos_ned=(v.position.north_m, v.position.east_m, v.position.down_m),
            vel_ned=(v.velocity.north_m_s, v.velocity.east_m_s, v.velocity.down_m_s)))
        tele.subscribe_battery(lambda v, _: t.update(battery_v=v.voltage_v, battery=v.remaining_percent / 100.0))
        tele.subscribe_status_text(self._on_status_text)
        tele.subscribe_health(lambda v, _: t.update(armable=v.is_armable))
        self._estimator_status = self.direct.subscribe_message("ESTIMATOR_STATUS", self._on_estimator_status)
        t["mode"] = tele.flight_mode().name  # MAVSDK calls subscribers on a change only; its mode here is the vehicle's
        threading.Thread(target=self._ask_version, args=(system,), name="px4-version", daemon=True).start()
        if len(self.config.global_origin) == 3:
            threading.Thread(target=self._set_global_origin, name="px4-origin", daemon=True).start()
        self.param = Param(system)
        if self.config.time_sync:
            self.timesync = TimeSync(self.direct, self.system_id, self.node.log)
            self.timesync.request_rate(FAST_TIMESYNC_HZ)
        self.telemetry = tele
        self.system = system
        self.node.event("info", f"connected to autopilot system {self.system_id} on {self.config.mavlink}")

    def _on_estimator_status(self, message, _user) -> None:
        """EKF2's solution flags (ESTIMATOR_STATUS, 1 Hz on PX4's onboard link): whether it has a local position.
        MAVSDK's ``health.is_local_position_ok`` cannot tell: PX4 v1.16 reports no vision sensor in SYS_STATUS, and
        MAVSDK takes GPS, flow or vision from there (telemetry_impl.cpp)."""
        import json

        flags = int(json.loads(message.fields_json).get("flags", 0))
        self.tele["local_position_ok"] = flags & EKF_LOCAL_POSITION == EKF_LOCAL_POSITION

    def _on_status_text(self, v, _) -> None:
        """PX4's own words (arming refusals, failsafes, landing): each on the telemetry at once, and in the log."""
        text = f"{v.type.name}: {v.text.strip()}"[:160]
        self.said.put(text)
        self.heard.append((time.monotonic(), text))
        self.node.log(f"vehicle says {text}")

    def _ask_version(self, system) -> None:
        """The firmware's version (:func:`autopilot_version`) on the telemetry."""
        text, unknown = autopilot_version(system)
        if not text:
            self.node.log(f"the vehicle's version is unknown: {unknown}")
            return
        self.tele["autopilot"] = text
        self.node.event("info", f"autopilot: {self.tele['autopilot']}")

    def _set_global_origin(self) -> None:
        """The vehicle's EKF global origin, only when it has none: first asked for (REQUEST_MESSAGE
        GPS_GLOBAL_ORIGIN; PX4 answers only with a valid origin, GPS_GLOBAL_ORIGIN.hpp) and listened for
        ``origin_probe_s``: a vehicle that has one (its GPS's, or one set before this gateway started) keeps it and
        none is sent. Else SET_GPS_GLOBAL_ORIGIN (MAVSDK's MavlinkDirect) every ``origin_retry_s`` until the vehicle
        reports an origin (PX4 answers one after each once it has a local position: mavlink_receiver.cpp; EKF2 takes
        it in setEkfGlobalOrigin), at most ``origin_tries`` times: then a warning, never an endless retry."""
        import json

        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        lat_deg, lon_deg, alt_m = self.config.global_origin
        wanted = (round(lat_deg * 1e7), round(lon_deg * 1e7))
        reported: list[tuple[int, int, int]] = []
        heard = threading.Event()

        def on_origin(message, _user) -> None:
            fields = json.loads(message.fields_json)
            reported.append((fields.get("latitude"), fields.get("longitude"), fields.get("altitude", 0)))
            heard.set()

        def send(name: str, fields: dict) -> bool:
            try:
                direct.send_message(MavlinkMessage(name, target_system_id=self.system_id, fields_json=json.dumps(fields)))
                return True
            except Exception as exc:  # MavlinkDirectError: the link is not up yet; the next try may pass
                self.node.log(f"{name} not sent: {exc}")
                return False

        direct = self.direct
        handle = direct.subscribe_message("GPS_GLOBAL_ORIGIN", on_origin)
        send("COMMAND_LONG", {"target_system": self.system_id, "target_component": 1,
                              "command": MAV_CMD_REQUEST_MESSAGE, "confirmation": 0,
                              "param1": MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, "param2": 0.0, "param3": 0.0, "param4": 0.0,
                              "param5": 0.0, "param6": 0.0, "param7": 0.0})
        sent = 0
        if not heard.wait(self.config.origin_probe_s):
            fields = {"target_system": self.system_id, "latitude": wanted[0], "longitude": wanted[1],
                      "altitude": round(alt_m * 1e3), "time_usec": 0}
            while not heard.is_set() and not self.node.stopping and sent < self.config.origin_tries:
                sent += send("SET_GPS_GLOBAL_ORIGIN", fields)
                heard.wait(self.config.origin_retry_s)
        direct.unsubscribe_message(handle)
        if not reported:
            if not self.node.stopping:
                self.node.event("warning", f"the vehicle reported no global origin after {sent} SET_GPS_GLOBAL_ORIGIN "
                                           "(it reports one once EKF2 has a local position: is the motion capture "
                                           "streaming?); without one PX4 refuses Hold. Restart the gateway to try again")
            return
        lat_e7, lon_e7, alt_mm = reported[0]
        self.tele["origin_alt_m"] = alt_mm / 1e3
        where = f"{lat_e7 / 1e7:.7f}°, {lon_e7 / 1e7:.7f}°, {alt_mm / 1e3:g} m"
        if sent == 0:
            self.node.event("info", f"the vehicle has a global origin already ({where}): kept, none sent")
        elif (lat_e7, lon_e7) == wanted:
            self.node.event("info", f"the vehicle's global origin is set: {where} ({sent} SET_GPS_GLOBAL_ORIGIN sent)")
        else:
            self.node.event("info", f"the vehicle reports its own global origin ({where}), not --global-origin's: "
                                    f"kept ({sent} SET_GPS_GLOBAL_ORIGIN sent)")

    # -- bus inputs (under the node lock; never block) ----------------------------------------
    def _on_setpoint(self, msg: SetpointMsg, received_s: float) -> None:
        att = self.core.on_setpoint(msg, received_s)
        if att is not None and self.offboard is not None:
            self._send_attitude(att, stream=self._may_stream())
            self.node.stats.output(time.monotonic() - received_s)
        self._drain_events()

    def _send_attitude(self, att: Px4Attitude, *, stream: bool = True) -> None:
        """Keep ``att`` as the newest setpoint (``offboard_start`` hands it over first) and, with ``stream``, hand
        it to MAVSDK's offboard stream (it re-sends the newest at 20 Hz)."""
        from mavsdk.plugins.offboard import Attitude

        self.last_attitude = Attitude(att.roll_deg, att.pitch_deg, att.yaw_deg, att.thrust_norm)
        if stream:
            self.offboard.set_attitude(self.last_attitude)

    def _may_stream(self) -> bool:
        """Setpoints go to the vehicle in offboard, or while it is not known to be armed and its mode is known and
        not one of its own (:data:`VEHICLE_OWN_MODES`: its failsafe, an operator's hold or land); the operator's
        ``offboard_start`` sends one itself. Real PX4 ends an offboard-loss failsafe and returns to offboard as
        soon as setpoints stream again (measured with PX4 v1.16 SITL: a restarted gateway's stream took it back
        to offboard mid-landing, where the controller's estimate had wound up during PX4's descent, and it flew
        off 5.8 m and crashed). The mode decides, not the armed flag alone: MAVSDK reports armed on a change from False only,
        and its ``armed()`` read at connection said False for an armed PX4 in Land."""
        mode = self.tele["mode"]
        return mode == "OFFBOARD" or (self.tele["armed"] is not True and mode not in VEHICLE_OWN_MODES)

    def _on_state(self, msg: StateMsg, received_s: float) -> None:
        self.core.on_state(msg, received_s, offboard=self.tele["mode"] == "OFFBOARD")
        if msg.source in self.config.forward_sources and self.direct is not None:
            capture_s = self.core.capture_s(msg, received_s)
            self.core.on_pose(received_s, capture_s)
            self.last_pose, self.last_pose_capture_s = msg, capture_s
            self._forward_pose(msg, capture_s)
        self._drain_events()

    def _forward_pose(self, msg: StateMsg, capture_s: float, quality_percent: int = 100) -> None:
        """The state as external vision, in the form PX4 v1.16's EKF2 fuses (mavlink_receiver.cpp,
        handle_message_odometry): ODOMETRY with estimator type VISION (MOCAP goes to vehicle_mocap_odometry, which
        EKF2 does not read), pose frame LOCAL_NED (MOCAP_NED is not among the frames it accepts: the position
        arrives as NaN; with LOCAL_FRD EKF2 takes the heading as relative (ev_yaw_control.cpp: yaw_align false)
        and publishes no global position even with an origin, so PX4 refuses Hold: measured), velocity in the body
        FRD frame. MAVSDK's Mocap plugin offers only MOCAP_NED and LOCAL_FRD, so the message goes through its
        MavlinkDirect. Covariances unknown (NaN: EKF2 then uses EKF2_EVP_NOISE, EKF2_EVV_NOISE); body rates 0
        (MavlinkDirect takes no NaN for a single field; EKF2 does not read them). ``quality_percent``: 100 for a
        tracked pose, -1 ("odometry has failed") for the last one repeated while the motion capture is lost;
        EKF2 fuses none below EKF2_EV_QMIN (ev_control.cpp). ``time_usec``: the pose's capture ``capture_s`` on
        this machine's monotonic clock, which PX4 converts into its own once its time sync with this gateway has
        converged (:mod:`services.px4_preflight`; before, and with 0, it stamps the sample on arrival:
        mavlink_receiver.cpp, Timesync::sync_stamp)."""
        import json

        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        x, y, z = msg.pos_enu_m
        q = quat_ned_from_enu_euler(msg.roll_rad, msg.pitch_rad, msg.yaw_rad)
        v_frd = matrix_from_quat(q).T @ (NED_FROM_ENU @ np.asarray(msg.vel_enu_mps, dtype=float))
        unknown = ["NaN"] + [0.0] * 20
        fields = {"time_usec": round(capture_s * 1e6) if self.timesync is not None else 0, "frame_id": MAV_FRAME_LOCAL_NED,
                  "child_frame_id": MAV_FRAME_BODY_FRD,
                  "x": y, "y": x, "z": -z, "q": [float(v) for v in q],
                  "vx": float(v_frd[0]), "vy": float(v_frd[1]), "vz": float(v_frd[2]),
                  "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0, "pose_covariance": unknown,
                  "velocity_covariance": unknown, "reset_counter": 0, "estimator_type": MAV_ESTIMATOR_TYPE_VISION,
                  "quality": quality_percent}
        self.direct.send_message(MavlinkMessage("ODOMETRY", target_system_id=self.system_id,
                                                fields_json=json.dumps(fields)))

    def _on_command(self, name: str, args: dict) -> tuple[bool, str]:
        """Runs without the node lock: waits (up to 5 s) for the worker to get the vehicle's answer."""
        if name not in COMMANDS:
            return False, f"unknown command {name!r}; choose one of {list(COMMANDS)}"
        if name == "calibrate_hover":
            with self.node.lock:
                return self.core.start_calibration(time.monotonic())
        if name == "preflight":  # a fresh check, the vehicle's parameters read again (seconds: off the worker)
            verdict = self.preflight.check(read_params=True)
            return verdict.go, verdict.table()
        if self.system is None:
            return False, f"no vehicle connected on {self.config.mavlink}"
        if name == "arm":
            refusal = self.preflight.arm_gate(args.get("override") is True)
            if refusal:
                return False, refusal
        if name == "param_set":
            return self.preflight.param_set(args)
        done = threading.Event()
        answer: list = []
        self.actions.put((name, lambda result: (answer.append(result), done.set())))
        if not done.wait(5.0):
            return False, f"{name}: no answer from the vehicle within 5 s"
        return answer[0]

    # -- the worker (blocking MAVSDK calls) ----------------------------------------------------
    def _do(self, name: str) -> tuple[bool, str]:
        started_s = time.monotonic()
        try:
            if name == "offboard_start":
                with self.node.lock:
                    age = self.core.setpoint_age_s(time.monotonic())
                    if age < 0 or age > 0.2 or self.last_attitude is None:
                        return False, ("no setpoint streamed yet" if age < 0 or self.last_attitude is None
                                       else f"the last setpoint is {age:.2f} s old (stream setpoints first)")
                    # MAVSDK drops its setpoint stream at every heartbeat that does not say offboard, and start()
                    # answers NO_SETPOINT_SET until the next setpoint: a start right after a heartbeat (PX4 sends
                    # one on each arming or mode change) failed. Hand it the newest setpoint again first.
                    self.offboard.set_attitude(self.last_attitude)
                self.offboard.start()
                with self.node.lock:
                    self.core.clear_failsafe()
            elif name == "offboard_stop":
                self.offboard.stop()
            else:
                getattr(self.action, name)()
            return True, f"{name}: accepted by the vehicle"
        except Exception as exc:  # MAVSDK raises ActionError/OffboardError with the vehicle's result
            result = getattr(getattr(exc, "result", None), "name", f"{type(exc).__name__}: {exc}")
            said = self._said_since(started_s)
            with self.node.lock:
                return False, self.core.refusal(name, result, time.monotonic(), ready=self.tele["armable"], said=said)

    def px4_warning(self) -> str:
        """PX4's newest warning or worse (its arming refusals and failed checks), "" when none came."""
        return next((text for _, text in reversed(self.heard) if _is_warning(text)), "")

    def _said_since(self, since_s: float, wait_s: float = 0.5) -> str:
        """PX4's newest warning or worse (STATUSTEXT) after ``since_s`` (it follows a refusal's COMMAND_ACK: waited
        up to ``wait_s``)."""
        deadline = time.monotonic() + wait_s
        while True:
            said = [text for t, text in self.heard if t >= since_s and _is_warning(text)]
            if said or time.monotonic() >= deadline:
                return said[-1] if said else ""
            time.sleep(0.02)

    # -- loops ---------------------------------------------------------------------------
    def _watchdog_loop(self) -> None:
        """A tick every 1/``watchdog_hz`` s, on deadlines: a tick's work (while the motion capture is lost, two MAVSDK
        calls, each a gRPC round trip to ``mavsdk_server``) does not push the next tick later. A tick more than a
        period late is counted in the health report (``watchdog late``, with the worst) and the ticks go on from
        then, not in a burst."""
        period_s = 1.0 / self.config.watchdog_hz
        due_s = time.monotonic() + period_s
        while not self.node.wait(max(0.0, due_s - time.monotonic())):
            with self.node.lock:
                now = time.monotonic()
                late_s, due_s = now - due_s, due_s + period_s
                if late_s > period_s:
                    self.core.counts["watchdog_late"] += 1
                    self.watchdog_worst_late_s = max(self.watchdog_worst_late_s, late_s)
                    due_s = now + period_s
                action = self.core.check_stale(now, offboard=self.tele["mode"] == "OFFBOARD", armed=self.tele["armed"])
                pose_failed = self.core.pose_failed(now) and self.direct is not None and self.last_pose is not None
                if pose_failed:
                    self._forward_pose(self.last_pose, self.last_pose_capture_s, quality_percent=-1)  # each tick
                    self.core.counts["pose_failed_sent"] += 1
                if (pose_failed or self.core.failsafe) and self.offboard is not None and self.tele["mode"] == "OFFBOARD":
                    level = self.core.level_setpoint()
                    if level is not None:
                        self._send_attitude(level)
                self._drain_events()
            if action and self.system is not None:
                self.actions.put((action, lambda result, a=action: self._failsafe_done(a, result)))

    def _failsafe_done(self, action: str, result: tuple[bool, str]) -> None:
        self.node.event("warning" if result[0] else "error", f"failsafe {action}: {result[1]}")
        if action == "hold" and not result[0]:
            with self.node.lock:
                self.core.hold_refused(result[1])

    def _telemetry_loop(self) -> None:
        """The vehicle's report at ``telemetry_hz``, and one at once for each of its words: a message carries one
        text, so words that came between two reports (PX4 says "Disarmed by landing" and a pre-flight check within
        milliseconds) would otherwise leave only the newest on the bus."""
        put = self.node.publisher("telemetry")
        period_s = 1.0 / self.config.telemetry_hz
        due_s = time.monotonic() + period_s
        last_problem = ""
        while not self.node.stopping:
            try:
                texts = [self.said.get(timeout=max(0.0, min(due_s - time.monotonic(), 0.1)))]
            except queue.Empty:
                texts = []
            if not texts and time.monotonic() < due_s:
                continue
            while not self.said.empty():
                texts.append(self.said.get_nowait())
            if not texts:  # the periodic report
                due_s += period_s
                if due_s < time.monotonic():  # late by more than a period: from now on
                    due_s = time.monotonic() + period_s
            for text in texts or [self.tele["status_text"]]:
                self.tele["status_text"] = text  # the newest stays on the periodic reports (the dashboard shows it)
                try:
                    put(self._telemetry())
                except Exception as exc:  # e.g. a value MAVSDK reported as NaN before its first message
                    if str(exc) != last_problem:
                        last_problem = str(exc)
                        self.node.log(f"telemetry not published: {type(exc).__name__}: {exc}")

    def _telemetry(self) -> TelemetryMsg:
        """The vehicle's report (converted to ENU/FLU) plus the gateway's own state; validated."""
        t = self.tele
        roll, pitch, yaw = attitude_enu_from_ned(*(math.radians(a) for a in t["att"]))
        n, e, d = t["pos_ned"]
        vn, ve, vd = t["vel_ned"]
        with self.node.lock:
            hover, failsafe = self.core.hover_thrust_norm, self.core.failsafe
            age = self.core.setpoint_age_s(time.monotonic())
        volts = t["battery_v"] if math.isfinite(t["battery_v"]) else 0.0
        remaining = t["battery"] if math.isfinite(t["battery"]) else -1.0
        return TelemetryMsg.validate(
            stamp_s=time.monotonic(), connected=self.system is not None and self.system.is_connected(),
            armed=bool(t["armed"]), in_air=t["in_air"], flight_mode=t["mode"].lower()[:32], roll_rad=roll, pitch_rad=pitch,
            yaw_rad=yaw, pos_enu_m=[e, n, -d], vel_enu_mps=[ve, vn, -vd], battery_v=min(max(volts, 0.0), 100.0),
            battery_remaining=min(max(remaining, -1.0), 1.0), hover_thrust_norm=min(max(hover, 0.0), 1.0),
            setpoint_age_s=age, failsafe=failsafe, autopilot=t["autopilot"][:64], status_text=t["status_text"])

    def _drain_events(self) -> None:
        while self.core.events:
            self.node.event(*self.core.events.pop(0))

    def _status(self) -> str:
        c = self.core.counts
        return (f"{'connected' if self.system is not None else 'waiting for the vehicle'}, mode {self.tele['mode']}, "
                f"armed {self.tele['armed']}, hover {self.core.hover_thrust_norm:.3f}, sent {c['sent']}, "
                f"refused {c['refused_nonfinite']}, clamped tilt {c['clamped_tilt']} thrust {c['clamped_thrust']}, "
                f"mocap failed sent {c['pose_failed_sent']}, watchdog late {c['watchdog_late']}"
                + (f" (worst {self.watchdog_worst_late_s * 1e3:.0f} ms)" if c["watchdog_late"] else "")
                + (f", FAILSAFE {self.core.failsafe}" if self.core.failsafe else ""))
