"""What a PX4 vehicle flown by this runtime must be set to: one table, in code, read against PX4 v1.16.0's own
sources (each row names the file). Three things are made from it and nothing else, so they cannot disagree:

- the world's airframe file ``sim/px4/neso_quad.params`` (:func:`airframe_text`; PX4 SITL boots with it),
- the lab table in ``services/README.md`` (:func:`lab_table`),
- the preflight's parameter checks (:func:`judge`, :mod:`flight.preflight`).

``neso preflight table --write`` writes the first two; unit tests check both files equal what this module makes.

A row with a :class:`Requirement` is checked on every vehicle (a lab's and the world's); a row without one is the
world's own (its geometry, its simulated sensors): written into the airframe file, never asked of a lab. ``advice``
rows are shown in the lab table and printed by preflight, not judged (a value only the lab knows). Pure: no I/O.
"""
from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field

PX4_SOURCE = "PX4 v1.16.0"  # the sources every row was read from (../shared/px4/px4-v1.16.0-sitl-src.tar.xz)
COMMANDER = "src/modules/commander/commander_params.c"
EKF2_EV = "src/modules/ekf2/params_external_vision.yaml"
EKF2_MODULE = "src/modules/ekf2/module.yaml"
EKF2_GNSS = "src/modules/ekf2/params_gnss.yaml"
EKF2_MAG = "src/modules/ekf2/params_magnetometer.yaml"
MISSION = "src/modules/navigator/mission_params.c"


@dataclass(frozen=True)
class Requirement:
    """What a checked parameter must be: any of ``values`` (with PX4's ``meanings``), or within [``low``,
    ``high``]; ``measured``: the value preflight measures (``EKF2_EV_DELAY``), judged there. ``fix``: the value
    to set when it is wrong. ``severity``: ``no-go`` (no arming) or ``warning`` (go, with the advice)."""

    values: tuple[float, ...] = ()
    low: float = -math.inf
    high: float = math.inf
    meanings: dict[float, str] = field(default_factory=dict)
    unit: str = ""
    fix: float = math.nan
    measured: bool = False
    severity: str = "no-go"

    def holds(self, value: float) -> bool:
        """Whether ``value`` meets it, a float as MAVLink carries it (float32: 0.3 arrives as 0.30000001)."""
        if not math.isfinite(value):
            return False
        if self.values:
            return any(math.isclose(value, v, rel_tol=1e-6, abs_tol=1e-9) for v in self.values)
        slack = 1e-6 * max(abs(self.low) if math.isfinite(self.low) else 0.0, abs(self.high) if math.isfinite(
            self.high) else 0.0, 1.0)
        return self.low - slack <= value <= self.high + slack

    def text(self) -> str:
        """The requirement in a few words: ``5 (Hold mode) or 4 (Land mode)``, ``0.1–0.3 s``, ``≥ 1``."""
        unit = f" {self.unit}" if self.unit else ""
        if self.measured:
            return "what preflight measures"
        if self.values:
            return " or ".join(_value_text(v, self.meanings) for v in self.values) + unit
        if math.isinf(self.high):
            return f"≥ {_number(self.low)}{unit}"
        if math.isinf(self.low):
            return f"≤ {_number(self.high)}{unit}"
        return f"{_number(self.low)}–{_number(self.high)}{unit}"


@dataclass(frozen=True)
class Px4Param:
    """One PX4 parameter. ``kind``: PX4's type (``int32`` or ``float``: which MAVLink PARAM_VALUE type and MAVSDK
    getter). ``world``: its value in the world's airframe (None: PX4's default there). ``why``: the reason, with
    what was measured; ``source``: the PX4 file its meaning and values were read from."""

    name: str
    kind: str
    world: float | None
    why: str
    source: str
    required: Requirement | None = None
    advice: str = ""

    def world_text(self) -> str:
        """The world's value as the airframe file writes it: floats always with a point (``10.0``), so a reader
        of the file knows PX4's type from it (``sim/mavlink_vehicle.py`` answers PARAM_VALUE with it)."""
        if self.kind == "int32":
            return str(int(self.world))
        return repr(float(self.world))


@dataclass(frozen=True)
class Group:
    """A heading of the airframe file: its comment lines and its rows."""

    comment: tuple[str, ...]
    rows: tuple[Px4Param, ...]


def _number(v: float) -> str:
    return f"{v:g}"


def _value_text(v: float, meanings: dict[float, str]) -> str:
    return f"{_number(v)} ({meanings[v]})" if v in meanings else _number(v)


def _rotor(i: int, px: float, py: float, km: float) -> tuple[Px4Param, ...]:
    where = "the world's rotor hub (body FRD, m) and yaw moment / thrust (m, + counter-clockwise)"
    src = "src/modules/control_allocator/module.yaml"
    return (Px4Param(f"CA_ROTOR{i}_PX", "float", px, where, src), Px4Param(f"CA_ROTOR{i}_PY", "float", py, where, src),
            Px4Param(f"CA_ROTOR{i}_KM", "float", km, where, src))


OBL_ACTIONS = {0: "Position mode", 1: "Altitude mode", 2: "Stabilized", 3: "Return mode", 4: "Land mode",
               5: "Hold mode", 6: "Terminate", 7: "Disarm"}
RCL_ACTIONS = {1: "Hold mode", 2: "Return mode", 3: "Land mode", 5: "Terminate", 6: "Disarm"}

GROUPS: tuple[Group, ...] = (
    Group(("--- geometry: the world's X quad, rotor hubs at (±a, ±a), a = 0.18 m / √2 = 0.127 m "
           "(QuadrotorParams.arm_length_m);",
           "PX4 motor order (1 front right CCW, 2 rear left CCW, 3 front left CW, 4 rear right CW; FRD: +y right);",
           "KM: yaw moment / thrust = QuadrotorParams.yaw_moment_per_thrust_m 0.016 m, + for CCW (PX4's sign)"),
          (Px4Param("CA_AIRFRAME", "int32", 0, "multicopter", "src/modules/control_allocator/module.yaml"),
           Px4Param("CA_ROTOR_COUNT", "int32", 4, "four rotors", "src/modules/control_allocator/module.yaml"),
           *_rotor(0, 0.127, 0.127, 0.016), *_rotor(1, -0.127, -0.127, 0.016), *_rotor(2, 0.127, -0.127, -0.016),
           *_rotor(3, -0.127, 0.127, -0.016),
           Px4Param("THR_MDL_FAC", "float", 0.0, "motors: thrust linear in the output (the world: thrust = output · "
                    "max thrust), PX4's default model factor 0", "src/modules/control_allocator/module.yaml"),
           Px4Param("MPC_THR_HOVER", "float", 0.5,
                    "PX4's first hover-thrust guess: the controller's nominal model (thrust_norm 0.5 holds 1.0 kg, "
                    "neso.types); PX4's hover-thrust estimator (MPC_USE_HTE, default on) learns the vehicle's own "
                    "(the world's truth 0.525)", "src/modules/mc_hover_thrust_estimator/hover_thrust_estimator_params.c",
                    advice="your vehicle's hover thrust: a start value; compare with the gateway's `calibrate_hover` "
                           "and pass it as `--hover-thrust`"))),
    Group(("--- sensors: one simulated IMU, baro and mag (sim.px4_hil.HilSensors), no GPS (indoors, as with motion "
           "capture)",),
          (Px4Param("SYS_HAS_GPS", "int32", 0, "the world simulates no GPS", "src/lib/systemlib/system_params.c"),
           Px4Param("SYS_HAS_MAG", "int32", 0, "the world's magnetometer is not relied on", "src/lib/systemlib/system_params.c"),
           Px4Param("EKF2_MULTI_IMU", "int32", 0, "one simulated IMU", "src/modules/ekf2/params_multi.yaml"),
           Px4Param("SENS_IMU_MODE", "int32", 1, "one simulated IMU", "src/modules/sensors/module.yaml"),
           Px4Param("EKF2_GPS_CTRL", "int32", 0,
                    "no GNSS aiding indoors: a fix (or its multipath) would pull the position away from the motion "
                    "capture's", EKF2_GNSS, Requirement(values=(0,), fix=0)),
           Px4Param("EKF2_MAG_TYPE", "int32", 5,
                    "no magnetometer fusion: indoors the field is bent by steel and motors, and the heading comes "
                    "from the motion capture (EKF2_EV_CTRL bit 3)", EKF2_MAG,
                    Requirement(values=(5,), meanings={5: "None"}, fix=5)))),
    Group(("--- motion capture as external vision (the gateway's ODOMETRY): position, velocity and yaw fused, height",
           "referenced to it (PX4's user guide, \"Using Vision or Motion Capture Systems\": EKF2_EV_CTRL, EKF2_HGT_REF",
           "Vision, mag off). Noise: the world's mocap (1 mm, 0.1°) is below PX4's minimum EKF2_EVP_NOISE (0.01 m);",
           "velocity is a filtered difference, ~0.07 m/s (sim/README.md) → 0.1 (default)."),
          (Px4Param("EKF2_EV_CTRL", "int32", 15,
                    "fuse the motion capture the gateway forwards as ODOMETRY: horizontal and vertical position, "
                    "velocity and yaw (bits 0–3)", EKF2_EV,
                    Requirement(values=(15,), meanings={15: "all four bits"}, fix=15)),
           Px4Param("EKF2_HGT_REF", "int32", 3,
                    "height from the motion capture, not the barometer (it drifts indoors and in ground effect)",
                    EKF2_MODULE, Requirement(values=(3,), meanings={3: "Vision"}, fix=3)),
           Px4Param("EKF2_EV_DELAY", "float", 10.0,
                    "EKF2 fuses each sample this long before its timestamp. By default PX4 stamps each pose on "
                    "arrival, so this is the mocap-to-PX4 latency preflight measures (the world's 10 ms). With the "
                    "gateway's --time-sync it stamps ODOMETRY with the pose's capture time and answers PX4's time "
                    "sync, and PX4 uses that time once the sync has converged (measured in SITL: 9.4 s after the "
                    "first pose; then PX4 dates each sample 9.0 ms before its arrival): 0 then, as PX4's guide says "
                    "for synced timestamps", EKF2_EV,
                    Requirement(measured=True, unit="ms", severity="warning")),
           Px4Param("EKF2_EVP_NOISE", "float", 0.01, "the world's mocap position noise, at PX4's minimum", EKF2_EV),
           Px4Param("EKF2_EVV_NOISE", "float", 0.1, "the world's mocap velocity noise", EKF2_EV),
           Px4Param("EKF2_EVA_NOISE", "float", 0.05, "the world's mocap attitude noise, at PX4's minimum", EKF2_EV),
           Px4Param("EKF2_EV_QMIN", "int32", 1,
                    "while the motion capture is lost the gateway repeats the last pose with ODOMETRY quality -1 "
                    "(MAVLink: \"odometry has failed\"); EKF2 fuses a sample only at or above EKF2_EV_QMIN, and PX4's "
                    "default 0 checks nothing: it would fuse that stale pose (ev_control.cpp, quality_sufficient)",
                    EKF2_EV, Requirement(low=1, high=100, fix=1)))),
    Group(("--- failsafe: this runtime flies without an RC transmitter; what PX4 does when the offboard stream stops",
           "(the gateway or its link died: the gateway's own failsafe did not run). PX4's default action,",
           "Position mode (COM_OBL_RC_ACT 0), needs the sticks: measured here with the gateway killed at 1 m, PX4",
           "switched to Position 1.06 s later, its flight task could not run (\"Matching flight task was not able to",
           "run\"), and the vehicle fell and crashed 3.4 s after the kill. Land (4), measured: from a hover, AUTO.LAND",
           "1.07 s after the kill, no crash; from the lemniscate (0.25 m up, ~2 m/s) the vehicle crashed (one run).",
           "Hold (5) brakes at height and waits for an operator (the gateway's `land`, or its own failsafe); it needs",
           "a global position, which the gateway's SET_GPS_GLOBAL_ORIGIN gives PX4 indoors."),
          (Px4Param("COM_OBL_RC_ACT", "int32", 5,
                    "PX4's own action when the offboard stream stops: 0–2 need RC sticks (measured: Position mode, "
                    "no sticks, a crash 3.4 s after the gateway died); Hold brakes at height (measured: holding at "
                    "0.27 m, 0.05 m/s); Land from a hover lands (from the lemniscate: one crash)", COMMANDER,
                    Requirement(values=(5, 4), meanings=OBL_ACTIONS, fix=5)),
           Px4Param("COM_OF_LOSS_T", "float", 0.3,
                    "how long PX4 flies the last setpoint before that action. Measured with the gateway killed "
                    "mid-lemniscate: at 1 s (PX4's default) the vehicle touched the floor at 2.45 m/s 0.9 s after the "
                    "kill, before the failsafe; at 0.3 s (the gateway's own stale-setpoint hold) Hold came 0.35 s "
                    "after. Not under 0.1 s: MAVSDK re-sends the newest setpoint every 50 ms, one lost datagram "
                    "must not trip it", COMMANDER, Requirement(low=0.1, high=0.3, unit="s", fix=0.3)),
           Px4Param("NAV_RCL_ACT", "int32", 3,
                    "when a safety pilot's RC link is lost: Return (PX4's default, 2) first climbs, within "
                    "NAV_ACC_RAD (10 m) of home to twice the distance from home (src/modules/navigator/rtl.cpp, "
                    "calculate_return_alt_from_cone_half_angle): 2 m from home, 4 m up, through a room's ceiling",
                    COMMANDER, Requirement(values=(3, 1), meanings=RCL_ACTIONS, fix=3)),
           Px4Param("COM_RC_IN_MODE", "int32", None, "keep the safety pilot's RC kill switch and mode switch",
                    COMMANDER, advice="as your safety pilot needs (0 RC only, 3 RC or joystick; never 4: stick "
                                      "input disabled)"))),
    Group(("--- take-off height: PX4's AUTO.TAKEOFF climbs to MIS_TAKEOFF_ALT (default 2.5 m, an outdoor height; a "
           "motion-capture",
           "room is often under 3 m high). 1.0 m: the controller's own take-off height (flight.mission.MissionConfig)."),
          (Px4Param("MIS_TAKEOFF_ALT", "float", 1.0,
                    "PX4's own take-off (the gateway's `takeoff`) climbs there: PX4's default 2.5 m is an outdoor "
                    "height, a motion-capture room is often under 3 m", MISSION,
                    Requirement(low=0.3, high=2.0, unit="m", fix=1.0, severity="warning")),)),
)

HEADER = (
    f"{PX4_SOURCE} parameters of the world's quadrotor (sim/quadrotor.py) flown by PX4 SITL with our world as",
    "its simulator (PX4_SIM_MODEL=none_iris: airframe 10016, simulator_mavlink on TCP 4560 + instance).",
    "GENERATED from flight/px4_params.py by `neso preflight table --write`: edit the table there, not this file.",
    "One \"NAME VALUE\" a line (a float always with a point); each is set as PX4_PARAM_NAME=VALUE (PX4's rcS applies",
    "those after its parameter reset and before the airframe's defaults, so they win). Everything not here is PX4's",
    "default for a multicopter (rc.mc_defaults + the Iris airframe): its attitude and rate gains (MC_ROLL_P 6.5,",
    "MC_ROLLRATE_P 0.15, ...), its control allocation (CA_METHOD desaturation), its land detector and its",
    "hover-thrust estimator. Nothing here is tuned to how the flight goes; the failsafe choices are the setup's",
    "(no RC, flights 25 cm above the floor), each with what was measured either way.",
)


def rows() -> tuple[Px4Param, ...]:
    return tuple(p for g in GROUPS for p in g.rows)


def row(name: str) -> Px4Param:
    for p in rows():
        if p.name == name:
            return p
    raise KeyError(f"{name} is not in flight/px4_params.py")


def checked() -> tuple[Px4Param, ...]:
    """The rows preflight judges on every vehicle, in table order."""
    return tuple(p for p in rows() if p.required is not None)


def lab_rows() -> tuple[Px4Param, ...]:
    """What a lab sets: the checked rows and the advice rows."""
    return tuple(p for p in rows() if p.required is not None or p.advice)


def judge(p: Px4Param, value: float | None) -> tuple[bool, str]:
    """(holds, the fix in words) for the vehicle's ``value`` of checked row ``p`` (None: the vehicle has no such
    parameter). A measured row is judged by :mod:`flight.preflight` against its measurement."""
    r = p.required
    assert r is not None and not r.measured, p.name
    if value is None:
        return False, f"{p.name} does not exist on this vehicle: PX4 v1.14 or later has it ({p.source})"
    if r.holds(value):
        return True, ""
    return False, f"param set {p.name} {_value_text(r.fix, r.meanings)}"


def airframe_text() -> str:
    """``sim/px4/neso_quad.params`` as it must be: the header, then each group's comment and its rows that have a
    world value, each after a comment line with its reason."""
    out = [f"# {line}" for line in HEADER]
    for g in GROUPS:
        out.append("")
        out += [f"# {line}" for line in g.comment]
        for p in g.rows:
            if p.world is None:
                continue
            if p.required is not None:
                out += textwrap.wrap(f"required {p.required.text()}: {p.why} [{p.source}]", 116,
                                     initial_indent="# ", subsequent_indent="# ")
            out.append(f"{p.name} {p.world_text()}")
    return "\n".join(out) + "\n"


def lab_table() -> str:
    """The lab table of ``services/README.md``: one line per parameter a lab sets, with what it must be, why, and
    the PX4 source it was read from."""
    lines = [f"| parameter | required | why | {PX4_SOURCE} source |", "|---|---|---|---|"]
    for p in lab_rows():
        required = p.required.text() if p.required is not None else p.advice
        if p.required is not None and p.required.severity == "warning":
            required += " (a warning, not a no-go)"
        lines.append(f"| `{p.name}` | {required} | {p.why} | `{p.source}` |")
    return "\n".join(lines) + "\n"
