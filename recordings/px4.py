"""A PX4 flight log (ULog ``.ulg``) read into this system's terms: ENU state, thrust in newtons, status.

Written from PX4's own message definitions (``msg/*.msg`` in PX4-Autopilot), not from sample logs:

- ``vehicle_local_position``: ``x y z`` (m, NED), ``vx vy vz`` (m/s, NED), ``z_valid``/``v_z_valid``
  (and ``xy_valid``/``v_xy_valid``), ``timestamp`` (µs since boot). NED → ENU: (x, y, z) → (y, x, −z).
- ``vehicle_attitude``: ``q[4]`` (w, x, y, z; Hamilton; FRD body → NED world). FRD → FLU:
  ``R_enu_flu = T · R_ned_frd · B`` with ``T`` swapping x/y and flipping z and ``B = diag(1, −1, −1)``
  (:mod:`neso.frames`), then ZYX Euler.
- thrust, normalised, along body −z (FRD), the first of (``thrust_source`` picks another):
  ``vehicle_thrust_setpoint.xyz[2]`` (v1.13+: what the rate controller hands to control allocation;
  ``NaN`` = motors stopped = 0), ``actuator_controls_0.control[3]`` (≤ v1.13: the same signal, 0–1),
  ``vehicle_attitude_setpoint.thrust_body[2]`` (v1.10+, [−1, 1], negative up) or its scalar ``thrust``
  (older PX4, 0–1 despite the "Newton" in its comment).
- ``vehicle_attitude_setpoint.q_d`` (else ``roll_body``/``pitch_body``/``yaw_body``): the attitude setpoint.
- ``hover_thrust_estimate.hover_thrust`` (when ``valid``), else the parameter ``MPC_THR_HOVER``, else the
  mean normalised thrust over steady hover (in air, |v| < 0.2 m/s, at least 1 s), or the value given.
- ``vehicle_status.arming_state`` (2 = armed in every PX4 version) and ``nav_state`` (flight mode);
  ``vehicle_land_detected.landed`` (in air); ``battery_status`` (voltage, remaining).

Time base, as the estimator would see it: the state is ``vehicle_local_position`` at the rate the log
has it (``timestamp``: when PX4 published it). Every other topic is sampled onto those times from the
past only: the attitude, attitude setpoint, status and battery are the newest message at or before
each state (zero-order hold, no interpolation, no look-ahead); the thrust of sample k is the
time-average of the zero-order-held thrust over [t_k, t_{k+1}): what acted over the period the
estimator integrates, known when sample k+1 arrives (the last sample before a gap: the thrust at t_k).

Dropouts: a state sample whose ``z_valid``/``v_z_valid`` is false, or a value that is not finite or
outside the schema's range, is skipped and counted; so are samples before the first attitude and
thrust message and repeated or out-of-order timestamps. A gap in the state longer than
``gap_periods`` median periods (the logger's dropouts, a topic logged in bursts) is kept as a gap:
nothing is invented across it, and the offline teacher (:mod:`recordings.teacher`) restarts its
observer after it. ULog appended data is read with the rest; a message torn by the end of the file
(power lost while logging) is skipped and said so.

Newtons: ``thrust_n = thrust_norm · m · g / hover_thrust``; the mass is the user's or, flagged as
assumed, the controller's nominal model's (:class:`neso.types.VehicleModel`). The ESO's input
``g + R e₃ T/m`` does not depend on the mass (it cancels); the network's thrust input does.
"""
from __future__ import annotations

import contextlib
import io
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neso.types import GRAVITY_MPS2, VehicleModel
from recordings.offline import split_at_gaps
from recordings.reader import RecordingError
from runtime.schema import LIMIT_M, LIMIT_MPS

STATE_TOPIC = "vehicle_local_position"
ATTITUDE_TOPIC = "vehicle_attitude"
SETPOINT_TOPIC = "vehicle_attitude_setpoint"
# (topic, field, sign): normalised thrust = sign · field (body FRD z is down, so −z is up)
THRUST_SOURCES = (("vehicle_thrust_setpoint", "xyz[2]", -1.0), ("actuator_controls_0", "control[3]", 1.0),
                  (SETPOINT_TOPIC, "thrust_body[2]", -1.0), (SETPOINT_TOPIC, "thrust", 1.0))
TOPICS_READ = (STATE_TOPIC, ATTITUDE_TOPIC, SETPOINT_TOPIC, "vehicle_thrust_setpoint", "actuator_controls_0",
               "hover_thrust_estimate", "vehicle_status", "vehicle_land_detected", "battery_status")
STATE_FIELDS = ("timestamp", "x", "y", "z", "vx", "vy", "vz")
ATTITUDE_FIELDS = ("timestamp", "q[0]", "q[1]", "q[2]", "q[3]")
ARMED = 2  # vehicle_status.ARMING_STATE_ARMED, the same value in every PX4 version
# vehicle_status.nav_state (PX4 v1.14 names; values 6–9 and 11 were other auto modes before v1.14)
NAV_STATES = {0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
              6: "AUTO_RCRECOVER", 7: "AUTO_RTGS", 8: "AUTO_LANDENGFAIL", 9: "AUTO_LANDGPSFAIL", 10: "ACRO",
              11: "AUTO_LAND_OLD", 12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD", 15: "STAB", 16: "RATTITUDE",
              17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET", 20: "AUTO_PRECLAND", 21: "ORBIT",
              22: "AUTO_VTOL_TAKEOFF"}
EVENT_LEVELS = {"EMERGENCY": "error", "ALERT": "error", "CRITICAL": "error", "ERROR": "error", "WARNING": "warning"}
MAX_ANGLE_RAD = 4.0
MAX_FLIGHT_S = 1e7  # state timestamps beyond this from the log's start are not one flight


class ImportRefused(RecordingError):
    """A file that cannot become a recording; the text (one line) says why."""


@dataclass(frozen=True)
class ImportConfig:
    """``mass_kg``/``hover_thrust_norm``: None = assumed (the nominal model's mass, flagged) / from the
    log. ``gap_periods``: a state gap longer than this many median periods is a dropout."""

    vehicle: str = "uav1"
    mass_kg: float | None = None
    hover_thrust_norm: float | None = None
    gravity_mps2: float = GRAVITY_MPS2
    gap_periods: float = 5.0
    thrust_source: str | None = None  # "topic.field" from THRUST_SOURCES; None: the first the log has

    def __post_init__(self) -> None:
        if self.mass_kg is not None and not (0.0 < self.mass_kg < 1e3):
            raise ValueError(f"mass must be in (0, 1000) kg, got {self.mass_kg}")
        if self.hover_thrust_norm is not None and not (0.0 < self.hover_thrust_norm <= 1.0):
            raise ValueError(f"hover thrust must be in (0, 1] (normalised), got {self.hover_thrust_norm}")
        if self.thrust_source is not None and self.thrust_source not in {f"{t}.{f}" for t, f, _ in THRUST_SOURCES}:
            raise ValueError(f"thrust source must be one of {[f'{t}.{f}' for t, f, _ in THRUST_SOURCES]}")


@dataclass
class PX4Flight:
    """A PX4 log on the state's time base: N samples, ENU/FLU, SI (see the module docstring)."""

    t_s: np.ndarray  # (N,) since the log's start
    pos_enu_m: np.ndarray  # (N, 3)
    vel_enu_mps: np.ndarray  # (N, 3)
    attitude_rad: np.ndarray  # (N, 3) roll, pitch, yaw (ZYX, ENU/FLU)
    setpoint_rad: np.ndarray  # (N, 3) the attitude setpoint, same convention
    thrust_norm: np.ndarray  # (N,) over [t_k, t_{k+1})
    thrust_n: np.ndarray  # (N,)
    acc_cmd_enu_mps2: np.ndarray  # (N, 3) g + R e3 T/m: the ESO's known input
    hover_thrust_norm: np.ndarray  # (N,)
    armed: np.ndarray  # (N,) bool
    in_air: np.ndarray  # (N,) bool
    mode: list[str]  # (N,)
    battery_v: np.ndarray  # (N,) 0 when not logged
    battery_remaining: np.ndarray  # (N,) −1 when not logged
    events: list[tuple[float, str, str]]  # (t_s, level, text): PX4's own log messages
    info: dict  # what was imported from where (the recording's "import" property)
    skipped: list[str] = field(default_factory=list)  # what was left out, and why
    notes: list[str] = field(default_factory=list)  # what is worth knowing but was kept

    def __len__(self) -> int:
        return len(self.t_s)


# -- reading the file ---------------------------------------------------------------------------
def torn_tail(data: bytes, start: int = 16) -> int | None:
    """Where the last message starts if the file ends inside it (cut while logging), else None:
    the ULog framing (``uint16 size, uint8 type, payload``) walked from the end of the header."""
    size = struct.Struct("<H").unpack_from
    i, n, last = start, len(data), start
    while i + 3 <= n:
        last = i
        i += 3 + size(data, i)[0]
    if i == n:
        return None
    return last if i > n else i


def read_ulog(path: str | Path, topics=TOPICS_READ):
    """(pyulog ``ULog`` with ``topics`` parsed, offset of a message torn by the end of the file or None);
    :class:`ImportRefused` for a file that is not a readable ULog."""
    from pyulog import ULog
    from pyulog.core import ULogException

    path = Path(path)
    if not path.is_file():
        raise ImportRefused(f"{path}: no such file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImportRefused(f"{path}: cannot read ({exc.strerror or exc})") from None
    size = len(data)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints its warnings
            log = ULog(io.BytesIO(data), list(topics))
    except ULogException as exc:
        raise ImportRefused(f"{path}: not a PX4 ULog file ({exc})") from None
    except Exception as exc:  # pyulog raises what its parsing hits on garbage (struct, index, unicode…)
        raise ImportRefused(f"{path}: not a readable PX4 ULog ({type(exc).__name__}: {exc})") from None
    if not log.message_formats:
        raise ImportRefused(f"{path}: truncated or corrupt: its {size} bytes end before the message formats "
                            "(no data section)")
    if not log.data_list:
        corrupt = " and is corrupt" if log.file_corruption else ""
        raise ImportRefused(f"{path}: truncated or corrupt: no data messages in its {size} bytes (the file ends "
                            f"inside its definitions section{corrupt})")
    return log, (None if log.file_corruption else torn_tail(data))


@dataclass
class _Topic:
    """One topic's fields (instance 0), every part of the log together, in time order."""

    name: str
    data: dict[str, np.ndarray]


def _dataset(log, name: str) -> _Topic | None:
    """The topic's instance 0; data logged under several subscriptions (appended data brings its own)
    is joined, fields they all have, sorted by ``timestamp``."""
    parts = [d for d in log.data_list if d.name == name and d.multi_id == 0]
    if not parts:
        return None
    if len(parts) == 1:
        data = dict(parts[0].data)
    else:
        common = [k for k in parts[0].data if all(k in p.data for p in parts[1:])]
        data = {k: np.concatenate([p.data[k] for p in parts]) for k in common}
    if "timestamp" in data and len(data["timestamp"]) > 1 and np.any(np.diff(data["timestamp"].astype(np.int64)) < 0):
        order = np.argsort(data["timestamp"], kind="stable")
        data = {k: v[order] for k, v in data.items()}
    return _Topic(name, data)


def _missing(ds, fields) -> list[str]:
    return [f for f in fields if ds is None or f not in ds.data]


def _thrust_source(log, wanted: str | None):
    """(topic, field, sign, dataset) of the thrust used, or None."""
    for topic, fld, sign in THRUST_SOURCES:
        if wanted is not None and wanted != f"{topic}.{fld}":
            continue
        ds = _dataset(log, topic)
        if ds is not None and fld in ds.data and "timestamp" in ds.data and len(ds.data["timestamp"]):
            return topic, fld, sign, ds
    return None


def _check_contents(path, log, config: ImportConfig):
    """The datasets the method needs, or :class:`ImportRefused` naming every missing topic and field."""
    state, att = _dataset(log, STATE_TOPIC), _dataset(log, ATTITUDE_TOPIC)
    thrust = _thrust_source(log, config.thrust_source)
    missing = []
    for topic, ds, fields in ((STATE_TOPIC, state, STATE_FIELDS), (ATTITUDE_TOPIC, att, ATTITUDE_FIELDS)):
        if ds is None:
            missing.append(f"topic {topic} ({', '.join(fields[1:])})")
        elif _missing(ds, fields):
            missing.append(f"{topic} fields {', '.join(_missing(ds, fields))}")
    if thrust is None:
        wanted = [config.thrust_source] if config.thrust_source else [f"{t}.{f}" for t, f, _ in THRUST_SOURCES]
        missing.append(f"thrust (one of {', '.join(wanted)})")
    if missing:
        raise ImportRefused(f"{path}: lacks what the method needs: {'; '.join(missing)}")
    return state, att, thrust


# -- frames -------------------------------------------------------------------------------------
def enu_from_ned(v: np.ndarray) -> np.ndarray:
    """(N, 3) NED vectors → ENU: (n, e, d) → (e, n, −d)."""
    v = np.asarray(v, dtype=float)
    return np.stack([v[:, 1], v[:, 0], -v[:, 2]], axis=1)


def euler_enu_flu_from_quat_ned_frd(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 3) ZYX roll, pitch, yaw (rad) of the FLU body in ENU, from PX4's (N, 4) FRD→NED quaternions."""
    q = np.asarray(q_wxyz, dtype=float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0], r[:, 0, 1], r[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r[:, 1, 0], r[:, 1, 1], r[:, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r[:, 2, 0], r[:, 2, 1], r[:, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    # T·R·B with T = [[0,1,0],[1,0,0],[0,0,−1]] (ENU↔NED) and B = diag(1,−1,−1) (FLU↔FRD), written out
    e = np.empty_like(r)
    e[:, 0, 0], e[:, 0, 1], e[:, 0, 2] = r[:, 1, 0], -r[:, 1, 1], -r[:, 1, 2]
    e[:, 1, 0], e[:, 1, 1], e[:, 1, 2] = r[:, 0, 0], -r[:, 0, 1], -r[:, 0, 2]
    e[:, 2, 0], e[:, 2, 1], e[:, 2, 2] = -r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    roll = np.arctan2(e[:, 2, 1], e[:, 2, 2])
    pitch = -np.arcsin(np.clip(e[:, 2, 0], -1.0, 1.0))
    yaw = np.arctan2(e[:, 1, 0], e[:, 0, 0])
    return np.stack([roll, pitch, yaw], axis=1)


def euler_enu_flu_from_euler_ned_frd(rpy: np.ndarray) -> np.ndarray:
    """(N, 3) ENU/FLU ZYX Euler of PX4's (N, 3) NED/FRD ZYX Euler (``roll_body`` …)."""
    r, p, y = np.asarray(rpy, dtype=float).T
    cr, sr, cp, sp, cy, sy = np.cos(r / 2), np.sin(r / 2), np.cos(p / 2), np.sin(p / 2), np.cos(y / 2), np.sin(y / 2)
    q = np.stack([cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                  cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy], axis=1)
    return euler_enu_flu_from_quat_ned_frd(q)


def body_z_enu(attitude_rad: np.ndarray) -> np.ndarray:
    """(N, 3) the FLU body z axis in ENU for (N, 3) ZYX roll, pitch, yaw."""
    r, p, y = np.asarray(attitude_rad, dtype=float).T
    return np.stack([np.cos(y) * np.sin(p) * np.cos(r) + np.sin(y) * np.sin(r),
                     np.sin(y) * np.sin(p) * np.cos(r) - np.cos(y) * np.sin(r), np.cos(p) * np.cos(r)], axis=1)


def thrust_newtons(thrust_norm, hover_thrust_norm, mass_kg: float, gravity_mps2: float = GRAVITY_MPS2):
    """Normalised thrust → N, linear through the hover thrust: ``T = u · m g / u_hover``."""
    return np.asarray(thrust_norm, dtype=float) * mass_kg * gravity_mps2 / np.asarray(hover_thrust_norm, dtype=float)


# -- onto the state's time base ----------------------------------------------------------------
def _seconds(ds, t0_us: int) -> np.ndarray:
    return (ds.data["timestamp"].astype(np.int64) - t0_us) / 1e6


def held(t_src: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The newest of ``values`` at or before each of ``t`` (zero-order hold; the first value before it)."""
    i = np.searchsorted(t_src, t, side="right") - 1
    return values[np.clip(i, 0, len(t_src) - 1)]


def period_average(t_src: np.ndarray, values: np.ndarray, t: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Mean over [t_k, t_{k+1}) of the zero-order hold of (``t_src``, ``values``) for each sample of ``t``;
    where ``last`` (N,) is true (before a gap, the final sample) the held value at t_k."""
    dt = np.diff(t_src, append=t_src[-1])
    integral = np.concatenate([[0.0], np.cumsum(values[:-1] * dt[:-1])])

    def area(x):
        i = np.clip(np.searchsorted(t_src, x, side="right") - 1, 0, len(t_src) - 1)
        return integral[i] + values[i] * (x - t_src[i])

    out = held(t_src, values, t)
    nxt = np.append(t[1:], t[-1])
    span = nxt - t
    ok = ~last & (span > 0)
    out[ok] = (area(nxt[ok]) - area(t[ok])) / span[ok]
    return out


def _hover_thrust(log, t, t0_us, u, in_air, vel, config: ImportConfig) -> tuple[np.ndarray, str, str]:
    """(hover thrust (N,), its source in a word, what exactly was taken)."""
    if config.hover_thrust_norm is not None:
        return np.full(len(t), config.hover_thrust_norm), "given", f"given: {config.hover_thrust_norm:g}"
    ds = _dataset(log, "hover_thrust_estimate")
    if ds is not None and "hover_thrust" in ds.data:
        h = ds.data["hover_thrust"].astype(float)
        ok = np.isfinite(h) & (h > 0.0) & (h <= 1.0)
        if "valid" in ds.data:
            ok &= ds.data["valid"].astype(bool)
        if ok.any():
            th, hv = _seconds(ds, t0_us)[ok], h[ok]
            return held(th, hv, t), "hover_thrust_estimate", (f"hover_thrust_estimate.hover_thrust ({int(ok.sum())} valid samples held; "
                                     f"{hv.min():.4f}–{hv.max():.4f}; before the first valid one its value)")
    param = log.initial_parameters.get("MPC_THR_HOVER")
    if isinstance(param, (int, float)) and 0.0 < float(param) <= 1.0:
        return np.full(len(t), float(param)), "MPC_THR_HOVER", f"parameter MPC_THR_HOVER = {float(param):.4g} (no valid hover_thrust_estimate)"
    steady = in_air & (np.linalg.norm(vel, axis=1) < 0.2) & (u > 0.05)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    if steady.sum() * dt >= 1.0:
        h = float(np.mean(u[steady]))
        return np.full(len(t), h), "steady hover", f"mean normalised thrust over {steady.sum() * dt:.1f} s of steady hover = {h:.4f}"
    raise ImportRefused("no hover thrust: no valid hover_thrust_estimate, no MPC_THR_HOVER parameter and under 1 s "
                        "of steady hover; pass --hover-thrust")


def _version(log) -> str:
    v = log.get_version_info_str()
    info = log.msg_info_dict
    if v is None:
        rel = log.get_version_info()
        v = f"v{rel[0]}.{rel[1]}.{rel[2]} (development)" if rel is not None and any(rel[:3]) else "unknown"
    branch = info.get("ver_sw_branch")
    return v + (f", branch {branch}" if branch else "") + (f", git {str(info['ver_sw'])[:10]}" if "ver_sw" in info else "")


def px4_flight(path: str | Path, config: ImportConfig = ImportConfig()) -> PX4Flight:
    """Read ``path`` and put it on the state's time base (see the module docstring);
    :class:`ImportRefused` (one line) for a file that cannot give state and thrust."""
    path = Path(path)
    log, torn = read_ulog(path)
    state, att, (thrust_topic, thrust_field, thrust_sign, thrust_ds) = _check_contents(path, log, config)
    skipped: list[str] = []
    notes: list[str] = []
    if torn is not None:
        skipped.append(f"the file ends inside a message at byte {torn} (cut while logging): that message")
    used = [ds for ds in (state, att, thrust_ds) if len(ds.data["timestamp"])]
    t0_us = int(min([log.start_timestamp] + [int(ds.data["timestamp"].min()) for ds in used]))

    # state samples: valid, finite, in range, strictly increasing in time
    t = _seconds(state, t0_us)
    ned_p = np.stack([state.data[k].astype(float) for k in ("x", "y", "z")], axis=1)
    ned_v = np.stack([state.data[k].astype(float) for k in ("vx", "vy", "vz")], axis=1)
    keep = np.ones(len(t), dtype=bool)

    def drop(mask, why):
        n = int(np.sum(mask & keep))
        if n:
            skipped.append(f"{n} {STATE_TOPIC} samples {why}")
        keep[mask] = False

    for flag in ("z_valid", "v_z_valid"):
        if flag in state.data:
            drop(~state.data[flag].astype(bool), f"with {flag} false")
    drop(~(np.all(np.isfinite(ned_p), axis=1) & np.all(np.isfinite(ned_v), axis=1)), "not finite")
    drop((np.abs(ned_p) > LIMIT_M).any(axis=1) | (np.abs(ned_v) > LIMIT_MPS).any(axis=1), "outside ±10 km / ±1 km/s")
    t_att = _seconds(att, t0_us)
    t_thr = _seconds(thrust_ds, t0_us)
    drop(t < max(t_att[0], t_thr[0]), f"before the first {ATTITUDE_TOPIC} and thrust message")
    order = np.argsort(t, kind="stable")
    keep_sorted = keep[order]
    ts = t[order]
    repeated = np.zeros(len(ts), dtype=bool)
    if len(ts) > 1:
        kept_t = np.where(keep_sorted, ts, np.nan)
        last_kept = np.fmax.accumulate(np.concatenate([[-np.inf], kept_t[:-1]]))
        repeated = keep_sorted & (ts <= last_kept)
    n_rep = int(repeated.sum())
    if n_rep:
        skipped.append(f"{n_rep} {STATE_TOPIC} samples with a repeated timestamp")
    idx = order[keep_sorted & ~repeated]
    if len(idx) and float(t[idx].max()) > MAX_FLIGHT_S:
        raise ImportRefused(f"{path}: its {STATE_TOPIC} timestamps span {float(t[idx].max()):.3g} s from the log's start: "
                            "not one flight (corrupt timestamps?)")
    if len(idx) < 2:
        raise ImportRefused(f"{path}: fewer than 2 usable {STATE_TOPIC} samples ({'; '.join(skipped) or 'none logged'})")
    t = t[idx]
    pos, vel = enu_from_ned(ned_p[idx]), enu_from_ned(ned_v[idx])
    for flag in ("xy_valid", "v_xy_valid"):
        if flag in state.data and not state.data[flag][idx].all():
            notes.append(f"{int((~state.data[flag][idx].astype(bool)).sum())} samples have {flag} false "
                         "(horizontal kept as logged; the method uses z)")

    # attitude (held), attitude setpoint (held), thrust (period average), status (held)
    q = np.stack([att.data[f"q[{i}]"].astype(float) for i in range(4)], axis=1)
    q_ok = np.all(np.isfinite(q), axis=1) & (np.linalg.norm(q, axis=1) > 0.5)
    if not q_ok.any():
        raise ImportRefused(f"{path}: no valid {ATTITUDE_TOPIC}.q quaternion in the log")
    attitude = held(t_att[q_ok], euler_enu_flu_from_quat_ned_frd(q[q_ok]), t)
    setpoint = attitude.copy()
    sp = _dataset(log, SETPOINT_TOPIC)
    sp_source = f"{ATTITUDE_TOPIC} (no {SETPOINT_TOPIC})"
    if sp is not None and all(f"q_d[{i}]" in sp.data for i in range(4)):
        qd = np.stack([sp.data[f"q_d[{i}]"].astype(float) for i in range(4)], axis=1)
        ok = np.all(np.isfinite(qd), axis=1) & (np.linalg.norm(qd, axis=1) > 0.5)
        if ok.any():
            setpoint = held(_seconds(sp, t0_us)[ok], euler_enu_flu_from_quat_ned_frd(qd[ok]), t)
            sp_source = f"{SETPOINT_TOPIC}.q_d"
    elif sp is not None and all(k in sp.data for k in ("roll_body", "pitch_body", "yaw_body")):
        e = np.stack([sp.data[k].astype(float) for k in ("roll_body", "pitch_body", "yaw_body")], axis=1)
        ok = np.all(np.isfinite(e), axis=1)
        if ok.any():
            setpoint = held(_seconds(sp, t0_us)[ok], euler_enu_flu_from_euler_ned_frd(e[ok]), t)
            sp_source = f"{SETPOINT_TOPIC}.roll_body/pitch_body/yaw_body"

    runs = split_at_gaps(t, config.gap_periods)
    last = np.zeros(len(t), dtype=bool)
    last[[r.stop - 1 for r in runs]] = True
    raw_u = thrust_sign * thrust_ds.data[thrust_field].astype(float)
    raw_u = np.clip(np.nan_to_num(raw_u, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)  # NaN: motors stopped
    u = period_average(t_thr, raw_u, t, last)

    status = _dataset(log, "vehicle_status")
    armed = np.ones(len(t), dtype=bool)
    mode = ["unknown"] * len(t)
    if status is not None and "arming_state" in status.data:
        ts_status = _seconds(status, t0_us)
        armed = held(ts_status, status.data["arming_state"].astype(int) == ARMED, t)
        if "nav_state" in status.data:
            nav = held(ts_status, status.data["nav_state"].astype(int), t)
            names = {n: NAV_STATES.get(int(n), f"nav_state {int(n)}") for n in np.unique(nav)}
            mode = [names[n] for n in nav]
    land = _dataset(log, "vehicle_land_detected")
    if land is not None and "landed" in land.data:
        in_air = ~held(_seconds(land, t0_us), land.data["landed"].astype(bool), t) & armed
        in_air_source = "vehicle_land_detected.landed"
    else:
        in_air = armed & (u > 0.05)
        in_air_source = "armed and thrust > 0.05 (no vehicle_land_detected)"
    battery = _dataset(log, "battery_status")
    battery_v, battery_rem = np.zeros(len(t)), np.full(len(t), -1.0)
    if battery is not None and "voltage_v" in battery.data:
        tb = _seconds(battery, t0_us)
        battery_v = np.clip(np.nan_to_num(held(tb, battery.data["voltage_v"].astype(float), t)), 0.0, 100.0)
        if "remaining" in battery.data:
            battery_rem = np.clip(np.nan_to_num(held(tb, battery.data["remaining"].astype(float), t), nan=-1.0), -1.0, 1.0)

    hover, hover_topic, hover_source = _hover_thrust(log, t, t0_us, u, in_air, vel, config)
    mass = config.mass_kg if config.mass_kg is not None else VehicleModel().mass_kg
    thrust_n = thrust_newtons(u, hover, mass, config.gravity_mps2)
    acc_cmd = body_z_enu(attitude) * (thrust_n / mass)[:, None] - np.array([0.0, 0.0, config.gravity_mps2])
    bad_angle = (np.abs(attitude) > MAX_ANGLE_RAD).any(axis=1) | (np.abs(setpoint) > MAX_ANGLE_RAD).any(axis=1)
    if bad_angle.any():
        raise ImportRefused(f"{path}: {int(bad_angle.sum())} attitudes outside ±{MAX_ANGLE_RAD} rad (not a quaternion log?)")

    events = []
    for m in log.logged_messages:
        events.append(((int(m.timestamp) - t0_us) / 1e6, EVENT_LEVELS.get(m.log_level_str(), "info"), str(m.message)))
    dropouts = log.dropouts
    if dropouts:
        notes.append(f"the logger reported {len(dropouts)} dropouts ({sum(d.duration for d in dropouts)} ms in all)")
    if log.has_data_appended:
        notes.append(f"the log has appended data (from byte {min(o for o in log._appended_offsets if o) if any(log._appended_offsets) else '?'}): "
                     "read with the rest, in time order")
    if log.file_corruption:
        notes.append("pyulog found corrupt bytes and resynchronised past them")
    gaps = [(float(t[r.start - 1]), float(t[r.start] - t[r.start - 1])) for r in runs[1:]]
    rate = 1.0 / float(np.median(np.diff(t)))
    info = {
        "format": "PX4 ULog", "file": str(path.resolve()), "file_name": path.name, "file_bytes": path.stat().st_size,
        "px4_version": _version(log), "hardware": str(log.msg_info_dict.get("ver_hw", "unknown")),
        "sys_name": str(log.msg_info_dict.get("sys_name", "")), "os": str(log.msg_info_dict.get("sys_os_name", "")),
        "log_start_us": int(t0_us),
        "topics": {"state": f"{STATE_TOPIC} (x y z vx vy vz, NED → ENU)",
                   "attitude": f"{ATTITUDE_TOPIC}.q (FRD→NED → FLU→ENU)", "attitude_setpoint": sp_source,
                   "thrust": f"{thrust_topic}.{thrust_field}", "hover_thrust": hover_topic,
                   "status": "vehicle_status (arming_state, nav_state)" if status is not None else "none",
                   "in_air": in_air_source, "battery": "battery_status" if battery is not None else "none"},
        "hover_thrust_source": hover_source,
        "hover_thrust_norm_median": float(np.median(hover)),
        "mass_kg": float(mass), "mass_assumed": config.mass_kg is None, "gravity_mps2": config.gravity_mps2,
        "state_rate_hz": round(rate, 3), "samples": int(len(t)), "duration_s": float(t[-1] - t[0]),
        "time_base": "vehicle_local_position timestamps; others held (newest at or before), thrust averaged "
                     "over each period",
        "gaps": {"count": len(gaps), "longest_s": max((g[1] for g in gaps), default=0.0),
                 "first": [[round(a, 4), round(b, 4)] for a, b in gaps[:20]], "gap_periods": config.gap_periods},
        "appended_data": bool(log.has_data_appended),
        "sdlog_profile": log.initial_parameters.get("SDLOG_PROFILE"),
        "skipped": skipped,
        "notes": notes,
    }
    return PX4Flight(t_s=t, pos_enu_m=pos, vel_enu_mps=vel, attitude_rad=attitude, setpoint_rad=setpoint,
                     thrust_norm=u, thrust_n=thrust_n, acc_cmd_enu_mps2=acc_cmd, hover_thrust_norm=hover,
                     armed=armed, in_air=in_air, mode=mode, battery_v=battery_v, battery_remaining=battery_rem,
                     events=events, info=info, skipped=skipped, notes=notes)
