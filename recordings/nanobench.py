"""``neso recordings import FILE.csv``: a NanoBench flight (a Crazyflie 2.1 under Vicon) as a recording of this system.

NanoBench (Ullah & Baca, arXiv:2603.09908; github.com/syediu/nanobench-iros2026, BSD-3-Clause) keeps each flight
as one CSV on the 100 Hz Vicon grid, the onboard log interpolated onto it (its README, "CSV Column Reference").
The columns read (any others are ignored, so a file cut down to these imports the same):

- ``t`` (s, the Vicon host's clock), ``px py pz`` (m, Vicon's world frame, z up), ``qx qy qz qw`` (the body's
  attitude in that world, scalar last), ``vx vy vz`` (m/s: the dataset's Savitzky–Golay derivative of the
  position; centred, it lines up with the position's central difference, so it is a few samples ahead of a
  causal estimate);
- ``motor_motor_m1`` … ``m4``: the firmware's motor ratios (0–65535) as it set them, i.e. after its battery
  compensation (``motor.m1`` logs ``motor_ratios``, crazyflie-firmware ``src/drivers/src/motors.c``);
- ``pwr_pm_vbat`` (V): the battery, logged at 10 Hz.

``<stem>_metadata.yaml`` beside the file, when there, names the trajectory, the firmware version and the vehicle.

**Frames.** Vicon's world (z up) is taken as ENU and the Crazyflie's body (x forward, y left, z up) as FLU, so
nothing is rotated. z is measured from the rest height: where the Vicon origin of the vehicle sat on the floor
before the motors started (it differs between flights: 5.4 or 7.1 cm in the Vicon frame), so a height means the
same in every flight. The rest height in Vicon's frame is recorded.

**Thrust.** The firmware's own battery-compensated curve, per motor, in newtons:
``f(v) = c₀ + c₁v + c₂v² + c₃v³`` with the motor voltage ``v = ratio/65535 · V_bat`` (clipped at 0; 0 for a
stopped motor), from crazyflie-firmware tag 2025.12.1 (the ``firmware_version`` every NanoBench metadata file
states), ``src/platform/interface/platform_defaults_cf2.h``, 2.1+ propellers: the Kconfig default for the CF2
platform, where ``ENABLE_THRUST_BAT_COMPENSATED`` is on by default. The firmware computed every logged ratio
through this curve's inverse at its (filtered) battery voltage (``motorsCompensateBatteryVoltage``,
``batteryCompensation`` in ``src/modules/src/stabilizer.c``), so the curve is the thrust the firmware meant to
command. The thrust is ``T = s · Σᵢ f(vᵢ)`` with one dimensionless scale ``s`` per import (``thrust_scale`` given,
else the median over the command's flights of each flight's own least-squares fit of ``m (a_z + g) ≈ s Σf cosφ
cosθ`` above ``fit_height_m``; each flight's own fit is recorded either way), and the mass ``m`` the firmware's
``CF_MASS`` for the Crazyflie 2.1 (0.029 kg, the same file). Only ``T/m`` enters the observer and the labels in
m/s², so the mass only sets the newtons. Why this curve and not the hover-normalised one (thrust ∝ ratio,
through each flight's hover ratio): it contains the battery voltage the ratios were compensated for, and it leaves
the smaller residual above 10 cm in 62 of the 72 NanoBench flights that import (median 0.153 against 0.190 m/s²;
both are recorded per flight, ``thrust_model.residual_rms_mps2``); and a scale per flight would fit away each
flight's battery offset with the very acceleration the labels are made from.

**Motor lead.** The onboard columns reach the Vicon grid early: they lead the measured acceleration by tens of
milliseconds, differently in every flight (the logs' clocks are aligned by the dataset, not by the physics). The
lead ``d`` is estimated per flight on the grid ``0 … max_lead_s`` by the same fit (the one leaving the smallest
residual), and the thrust of sample k is the curve at the columns interpolated at ``t_k + Δ/2 − d`` (the middle of
the period it acts over). A lead at the grid's top end is refused (not aligned); at 0 it is kept and said so.

**What is left out.** Samples standing on the floor (motors stopped, or less than ``airborne_height_m`` above the
rest height; a touch shorter than ``ground_dwell_s`` is kept as flight) and airborne stretches shorter than
``min_stretch_s``: the floor's support is not a disturbance an observer or a network should learn, and a smoothed
label must not reach across it. ``seq`` is the CSV's row, so a stretch's first sample follows a gap; the setpoint of
the row before it (the thrust over the period ending at that sample) is written too.

**Refused** (one line, nothing written): not a readable CSV, a required column missing, times not increasing,
values not finite, a quaternion that is no rotation, motor ratios outside 0–65535 or the battery outside 2–4.5 V
(the dataset extrapolates its onboard columns past the end of the onboard log: some files do), never flown (motors never on, or never
``never_flown_height_m`` above the rest), too little flight above ``fit_height_m`` to fit, the thrust and the
acceleration inconsistent (residual RMS above ``max_residual_rms_mps2`` at the best scale and lead, or the best
lead at the top of its grid), and a file byte-identical to an earlier one of the same command (the dataset has 20).
"""
from __future__ import annotations

import gzip
import hashlib
import io
import lzma
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neso.learning import IDENTIFICATION_CUTOFF_HZ, smoothed_acceleration, zero_phase
from neso.types import GRAVITY_MPS2
from recordings.px4 import ImportRefused, body_z_enu
from recordings.px4_import import TELEMETRY_HZ, write_flight
from runtime.schema import SetpointMsg, StateMsg, TelemetryMsg, valid_name

SUFFIXES = (".csv", ".csv.gz", ".csv.xz")
POSITION = ("px", "py", "pz")
QUATERNION_XYZW = ("qx", "qy", "qz", "qw")
VELOCITY = ("vx", "vy", "vz")
MOTORS = ("motor_motor_m1", "motor_motor_m2", "motor_motor_m3", "motor_motor_m4")
BATTERY = "pwr_pm_vbat"
COLUMNS = ("t", *POSITION, *QUATERNION_XYZW, *VELOCITY, *MOTORS, BATTERY)
RATIO_MAX = 65535.0  # UINT16_MAX: the firmware's full motor ratio
BATTERY_RANGE_V = (2.0, 4.5)  # a 1S LiPo (the firmware stops compensating under 2 V)
DATASET = "NanoBench (Ullah & Baca 2026, github.com/syediu/nanobench-iros2026, BSD-3-Clause)"
FIRMWARE_SOURCE = ("bitcraze/crazyflie-firmware tag 2025.12.1 (252b41341a07), "
                   "src/platform/interface/platform_defaults_cf2.h")


@dataclass(frozen=True)
class ThrustCurve:
    """A motor's thrust (N) against its voltage (V): ``c₀ + c₁v + c₂v² + c₃v³``, increasing on ``v ≥ 0``."""

    coefficients: tuple[float, float, float, float]
    source: str

    def thrust_n(self, motor_v: np.ndarray) -> np.ndarray:
        """Per-motor thrust (N), same shape as ``motor_v`` (V); never negative."""
        c0, c1, c2, c3 = self.coefficients
        v = np.asarray(motor_v, dtype=float)
        return np.maximum(c0 + v * (c1 + v * (c2 + v * c3)), 0.0)

    def voltage_for(self, thrust_n: np.ndarray) -> np.ndarray:
        """The motor voltage (V) giving ``thrust_n`` per motor (the firmware's inversion, tabulated)."""
        grid = np.linspace(0.0, 2.0 * BATTERY_RANGE_V[1], 4001)
        return np.interp(thrust_n, self.thrust_n(grid), grid)


#: VMOTOR2THRUST0…3 for the 2.1+ propellers (CONFIG_CRAZYFLIE_21_PLUS, the default) and CF_MASS of the same file.
CRAZYFLIE_21_PLUS = ThrustCurve((-0.02476537915958403, 0.06523793527519485, -0.026792504967750107,
                                 0.006776789303971145), f"{FIRMWARE_SOURCE}, VMOTOR2THRUST0-3 (2.1+ propellers)")
CRAZYFLIE_MASS_KG = 0.029
CRAZYFLIE_MASS_SOURCE = f"CF_MASS of {FIRMWARE_SOURCE} (Crazyflie 2.1 without the thrust upgrade kit)"


@dataclass(frozen=True)
class NanoBenchConfig:
    """How a NanoBench CSV becomes a recording (module docstring). Heights above the rest height (m), times (s),
    accelerations (m/s²). ``thrust_scale``: None = the median of the command's flights' own fits."""

    vehicle: str = "uav1"
    mass_kg: float = CRAZYFLIE_MASS_KG
    thrust_scale: float | None = None
    airborne_height_m: float = 0.005
    ground_dwell_s: float = 0.1
    min_stretch_s: float = 0.5
    never_flown_height_m: float = 0.05
    fit_height_m: float = 0.10
    fit_edge_s: float = 0.5  # fit samples stay this far from a stretch's ends (the low-pass's edges)
    min_fit_s: float = 1.0
    max_lead_s: float = 0.2
    lead_step_s: float = 0.005
    max_residual_rms_mps2: float = 0.5
    min_rest_s: float = 0.1
    gravity_mps2: float = GRAVITY_MPS2

    def __post_init__(self) -> None:
        if not (0.0 < self.mass_kg < 10.0):
            raise ValueError(f"mass must be in (0, 10) kg, got {self.mass_kg}")
        if self.thrust_scale is not None and not (0.0 < self.thrust_scale < 100.0):
            raise ValueError(f"thrust scale must be in (0, 100), got {self.thrust_scale}")


@dataclass
class NanoBenchFlight:
    """One NanoBench flight on the Vicon grid: every row (R) of the CSV, ENU/FLU, SI; ``kept`` the airborne rows
    written. Thrusts are over the period after each row, with the motor lead taken out."""

    t_s: np.ndarray  # (R,) since the first row
    pos_enu_m: np.ndarray  # (R, 3) z above the rest height
    vel_enu_mps: np.ndarray  # (R, 3)
    attitude_rad: np.ndarray  # (R, 3) roll, pitch, yaw (ZYX)
    thrust_norm: np.ndarray  # (R,) mean motor ratio / 65535
    curve_thrust_n: np.ndarray  # (R,) Σ f(v_i), the firmware curve's thrust
    battery_v: np.ndarray  # (R,)
    kept: np.ndarray  # (R,) bool
    own_scale: float  # this flight's own least-squares thrust scale
    info: dict  # the recording's "import" property (thrust scale and newtons filled in by the import)
    skipped: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.kept.sum())


# -- reading ---------------------------------------------------------------------------------------
def is_nanobench_csv(path: str | Path) -> bool:
    return str(path).lower().endswith(SUFFIXES)


def read_bytes(path: Path) -> tuple[bytes, bytes]:
    """(the file's bytes, its text: ``.gz``/``.xz`` decompressed); :class:`ImportRefused` if unreadable."""
    if not path.is_file():
        raise ImportRefused(f"{path}: no such file")
    try:
        raw = path.read_bytes()
        name = path.name.lower()
        return raw, gzip.decompress(raw) if name.endswith(".gz") else lzma.decompress(raw) if name.endswith(".xz") else raw
    except (OSError, EOFError, lzma.LZMAError) as exc:
        raise ImportRefused(f"{path}: cannot read ({exc})") from None


def read_columns(path: Path, data: bytes) -> dict[str, np.ndarray]:
    """The columns this import reads (:data:`COLUMNS`), as float arrays; :class:`ImportRefused` naming what is wrong."""
    text = data.decode("utf-8", errors="replace")
    header = text.split("\n", 1)[0].strip().split(",")
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise ImportRefused(f"{path}: not a NanoBench CSV: lacks column(s) {', '.join(missing)}")
    try:
        values = np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, usecols=[header.index(c) for c in COLUMNS],
                            ndmin=2)
    except ValueError as exc:
        raise ImportRefused(f"{path}: unreadable row ({str(exc).splitlines()[0]})") from None
    if len(values) < 2:
        raise ImportRefused(f"{path}: {len(values)} data row(s)")
    return {c: values[:, i] for i, c in enumerate(COLUMNS)}


def read_metadata(path: Path) -> dict[str, str]:
    """Top-level ``key: value`` scalars of ``<stem>_metadata.yaml`` beside the CSV (empty when absent)."""
    stem = path.name
    for suffix in SUFFIXES[::-1]:
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    meta = path.with_name(f"{stem}_metadata.yaml")
    out: dict[str, str] = {}
    if meta.is_file():
        for line in meta.read_text(errors="replace").splitlines():
            if line and not line[0].isspace() and ":" in line:
                key, value = line.split(":", 1)
                if value.strip():
                    out[key.strip()] = value.strip()
    return out


def euler_zyx_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw (rad) of (N, 4) scalar-last quaternions (normalised here)."""
    q = np.asarray(q, dtype=float)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=1)


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of every run of True in ``mask``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]])))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def _airborne(on: np.ndarray, height_m: np.ndarray, dt_s: float, config: NanoBenchConfig) -> tuple[np.ndarray, int, int]:
    """(kept (R,), ground rows kept as a touch, rows of stretches too short) — module docstring."""
    air = on & (height_m > config.airborne_height_m)
    stretches = runs(air)
    touches = 0
    for (_, stop), (start, _) in zip(stretches[:-1], stretches[1:]):  # ground between two stretches
        if (start - stop) * dt_s < config.ground_dwell_s:
            air[stop:start] = True
            touches += start - stop
    short = 0
    for start, stop in runs(air):
        if (stop - start) * dt_s < config.min_stretch_s:
            air[start:stop] = False
            short += stop - start
    return air, touches, short


@dataclass(frozen=True)
class LeadFit:
    """The motor lead (s) and the thrust scale fitted together; residual RMS (m/s²) at each lead of the grid."""

    lead_s: float
    accel_per_curve_n: float  # (a_z + g) per newton of the curve: s/m
    residual_rms_mps2: float
    grid_s: np.ndarray
    rms_by_lead: np.ndarray


def fit_lead(t_s: np.ndarray, acc_plus_g: np.ndarray, curve_n: np.ndarray, tilt_cos: np.ndarray, fit: np.ndarray,
             config: NanoBenchConfig) -> LeadFit:
    """For each lead d of the grid: ``(a_z + g) ≈ k · zero_phase(Σf(t − d) cosφcosθ)`` by least squares through
    the origin on the ``fit`` rows (both through the same 5 Hz zero-phase low-pass as the acceleration); the lead
    with the smallest residual RMS."""
    dt = float(np.median(np.diff(t_s)))
    grid = np.arange(0.0, config.max_lead_s + 1e-9, config.lead_step_s)
    y = acc_plus_g[fit]
    rms, ks = np.empty(len(grid)), np.empty(len(grid))
    for i, d in enumerate(grid):
        x = zero_phase(np.interp(t_s - d, t_s, curve_n) * tilt_cos, dt, IDENTIFICATION_CUTOFF_HZ)[fit]
        ks[i] = float(x @ y) / float(x @ x)
        rms[i] = float(np.sqrt(np.mean((y - ks[i] * x) ** 2)))
    best = int(np.argmin(rms))
    return LeadFit(float(grid[best]), float(ks[best]), float(rms[best]), grid, rms)


def _linear_rms(t_s, acc_plus_g, ratio_mean, tilt_cos, fit, lead_s) -> float:
    """The residual RMS (m/s²) of the hover-normalised model (thrust ∝ mean ratio, one scale) at the same lead."""
    dt = float(np.median(np.diff(t_s)))
    x = zero_phase(np.interp(t_s - lead_s, t_s, ratio_mean) * tilt_cos, dt, IDENTIFICATION_CUTOFF_HZ)[fit]
    y = acc_plus_g[fit]
    k = float(x @ y) / float(x @ x)
    return float(np.sqrt(np.mean((y - k * x) ** 2)))


def nanobench_flight(path: str | Path, config: NanoBenchConfig = NanoBenchConfig(), *,
                     data: tuple[bytes, bytes] | None = None) -> NanoBenchFlight:
    """Read and check ``path`` (module docstring); :class:`ImportRefused` (one line) for a file that cannot be a
    flight. ``data``: :func:`read_bytes` of it when already read."""
    path = Path(path)
    raw, text = read_bytes(path) if data is None else data
    col = read_columns(path, text)
    t = col["t"]
    bad = {c: int(np.sum(~np.isfinite(v))) for c, v in col.items() if not np.all(np.isfinite(v))}
    if bad:
        raise ImportRefused(f"{path}: values not finite ({', '.join(f'{c}: {n}' for c, n in bad.items())})")
    if np.any(np.diff(t) <= 0):
        k = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise ImportRefused(f"{path}: times not increasing (row {k + 1}: t = {t[k]:.6f} after {t[k - 1]:.6f})")
    t = t - t[0]
    dt = float(np.median(np.diff(t)))
    ratios = np.stack([col[c] for c in MOTORS], axis=1)
    battery = col[BATTERY]
    for name, values, lo, hi in (("motor ratio", ratios, 0.0, RATIO_MAX), ("battery", battery[:, None], *BATTERY_RANGE_V)):
        outside = np.flatnonzero(np.any((values < lo) | (values > hi), axis=1))
        if len(outside):
            worst = values[outside].ravel()[np.argmax(np.abs(values[outside].ravel() - (lo + hi) / 2))]
            raise ImportRefused(f"{path}: {name} reaches {worst:.6g} (outside {lo:g}–{hi:g}) from "
                                f"t = {t[outside[0]]:.2f} s: the onboard columns run past the end of the onboard log "
                                "(extrapolated)")
    on = np.any(ratios > 0, axis=1)
    if not on.any():
        raise ImportRefused(f"{path}: never flew: the motors never ran ({t[-1]:.1f} s of rows)")
    first_on = int(np.argmax(on))
    if first_on * dt < config.min_rest_s:
        raise ImportRefused(f"{path}: no rest height: the motors run from {t[first_on]:.2f} s, before "
                            f"{config.min_rest_s:g} s on the floor")
    rest_m = float(np.median(col["pz"][:first_on]))
    pos = np.stack([col[c] for c in POSITION], axis=1)
    pos[:, 2] -= rest_m
    height = pos[:, 2]
    if np.max(height[on]) < config.never_flown_height_m:
        raise ImportRefused(f"{path}: never flew: {np.max(height[on]) * 100:.1f} cm at most above its rest height "
                            f"(the motors ran {on.sum() * dt:.1f} s)")
    quat = np.stack([col[c] for c in QUATERNION_XYZW], axis=1)
    norm = np.linalg.norm(quat, axis=1)
    if np.any(norm < 0.5):
        k = int(np.flatnonzero(norm < 0.5)[0])
        raise ImportRefused(f"{path}: {int(np.sum(norm < 0.5))} attitudes are no rotation (quaternion norm "
                            f"{norm[k]:.3g} at t = {t[k]:.2f} s)")
    attitude = euler_zyx_from_quat_xyzw(quat)
    tilt_cos = np.cos(attitude[:, 0]) * np.cos(attitude[:, 1])
    curve_raw = CRAZYFLIE_21_PLUS.thrust_n(ratios / RATIO_MAX * battery[:, None]).sum(axis=1)
    kept, touches, short = _airborne(on, height, dt, config)
    fit = kept & (height > config.fit_height_m)
    edge = int(round(config.fit_edge_s / dt))
    for start, stop in runs(kept):
        fit[start:start + edge] = False
        fit[max(start, stop - edge):stop] = False
    if fit.sum() * dt < config.min_fit_s:
        raise ImportRefused(f"{path}: too little flight above {config.fit_height_m * 100:g} cm to fit the thrust and "
                            f"the motor lead ({fit.sum() * dt:.1f} s, need {config.min_fit_s:g} s)")
    acc_plus_g = smoothed_acceleration(height, dt, IDENTIFICATION_CUTOFF_HZ) + config.gravity_mps2
    lead = fit_lead(t, acc_plus_g, curve_raw, tilt_cos, fit, config)
    if lead.lead_s >= config.max_lead_s - 1e-9:
        raise ImportRefused(f"{path}: thrust and acceleration inconsistent: the motor columns align best at the end of "
                            f"the {config.max_lead_s * 1e3:.0f} ms lead searched (not aligned)")
    if lead.residual_rms_mps2 > config.max_residual_rms_mps2:
        raise ImportRefused(f"{path}: thrust and acceleration inconsistent: residual RMS {lead.residual_rms_mps2:.2f} m/s² "
                            f"above {config.fit_height_m * 100:g} cm at the best scale and lead (limit "
                            f"{config.max_residual_rms_mps2:g})")
    ratio_mean = ratios.mean(axis=1) / RATIO_MAX
    linear_rms = _linear_rms(t, acc_plus_g, ratio_mean, tilt_cos, fit, lead.lead_s)
    # the period after each row, as the thrust acted on it: the columns at its middle, minus the lead
    t_mid = t + np.append(np.diff(t), dt) / 2.0 - lead.lead_s
    ratios_at = np.stack([np.interp(t_mid, t, ratios[:, i]) for i in range(len(MOTORS))], axis=1)
    battery_at = np.interp(t_mid, t, battery)
    curve_n = CRAZYFLIE_21_PLUS.thrust_n(ratios_at / RATIO_MAX * battery_at[:, None]).sum(axis=1)
    own_scale = config.mass_kg * lead.accel_per_curve_n

    skipped, notes = [], []
    ground = int((~kept).sum())
    if ground:
        skipped.append(f"{ground - short} rows on the floor (motors stopped or under {config.airborne_height_m * 1e3:g} mm "
                       "above the rest height)")
    if short:
        skipped.append(f"{short} rows of airborne stretches shorter than {config.min_stretch_s:g} s")
    if touches:
        notes.append(f"{touches} rows touching the floor for under {config.ground_dwell_s:g} s kept as flight")
    if lead.lead_s == 0.0:
        notes.append("the motor lead fits best at 0 (the columns as the dataset aligned them)")
    stretches = runs(kept)
    meta = read_metadata(path)
    info = {
        "format": "NanoBench CSV", "dataset": DATASET, "file": str(path.resolve()), "file_name": path.name,
        "file_bytes": len(raw), "sha256": hashlib.sha256(raw).hexdigest(),
        "hardware": "Crazyflie 2.1", "vehicle_id": meta.get("crazyflie_id", "unknown"),
        "firmware": meta.get("firmware_version", "unknown"), "trajectory": meta.get("trajectory_id", "unknown"),
        "metadata": meta,
        "topics": {"state": "Vicon px py pz (m), qx qy qz qw, vx vy vz (Savitzky-Golay, centred); world z up = ENU, "
                            "body = FLU",
                   "thrust": "motor_motor_m1-m4 ratios and pwr_pm_vbat through the firmware's curve",
                   "attitude_setpoint": "none in the dataset: the measured attitude"},
        "rest_height_vicon_m": rest_m,
        "mass_kg": float(config.mass_kg), "mass_assumed": False,
        "mass_source": CRAZYFLIE_MASS_SOURCE if config.mass_kg == CRAZYFLIE_MASS_KG else "given",
        "thrust_model": {
            "curve": "T = s * sum_i f(ratio_i / 65535 * V_bat), f(v) = c0 + c1 v + c2 v^2 + c3 v^3 (N per motor)",
            "coefficients": list(CRAZYFLIE_21_PLUS.coefficients), "source": CRAZYFLIE_21_PLUS.source,
            "flight_scale": own_scale,
            "residual_rms_mps2": {"firmware_curve": lead.residual_rms_mps2, "hover_normalised_linear": linear_rms},
            "fit": f"{int(fit.sum())} rows above {config.fit_height_m:g} m, {config.fit_edge_s:g} s from a stretch's "
                   f"ends, both sides through a {IDENTIFICATION_CUTOFF_HZ:g} Hz zero-phase low-pass",
        },
        "motor_lead_s": lead.lead_s,
        "motor_lead_grid_s": [0.0, config.max_lead_s, config.lead_step_s],
        "state_rate_hz": round(1.0 / dt, 3), "samples": int(kept.sum()), "rows": int(len(t)),
        "duration_s": float(sum(t[b - 1] - t[a] for a, b in stretches)),
        "stretches": [[round(float(t[a]), 3), round(float(t[b - 1]), 3)] for a, b in stretches],
        "time_base": "the Vicon rows; the onboard columns as the dataset interpolated them, taken at the middle of "
                     "each period minus the motor lead",
        "skipped": skipped, "notes": notes,
    }
    return NanoBenchFlight(t_s=t, pos_enu_m=pos, vel_enu_mps=np.stack([col[c] for c in VELOCITY], axis=1),
                           attitude_rad=attitude, thrust_norm=np.clip(np.interp(t_mid, t, ratio_mean), 0.0, 1.0),
                           curve_thrust_n=curve_n, battery_v=battery, kept=kept, own_scale=own_scale, info=info,
                           skipped=skipped, notes=notes)


# -- writing ---------------------------------------------------------------------------------------
def flight_messages(flight: NanoBenchFlight, *, scale: float, mass_kg: float, gravity_mps2: float = GRAVITY_MPS2
                    ) -> list[tuple[str, object]]:
    """(channel, message) in time order: per kept row its state and the setpoint answering it (the thrust over the
    next period), the setpoint of the row before each stretch, telemetry at ~10 Hz."""
    thrust_n = scale * flight.curve_thrust_n
    att = flight.attitude_rad
    acc = body_z_enu(att) * (thrust_n / mass_kg)[:, None] - np.array([0.0, 0.0, gravity_mps2])
    hover_v = CRAZYFLIE_21_PLUS.voltage_for(np.array(mass_kg * gravity_mps2 / 4.0 / scale))
    hover = np.clip(hover_v / np.maximum(flight.battery_v, BATTERY_RANGE_V[0]), 0.0, 1.0)
    t, pos, vel = flight.t_s.tolist(), flight.pos_enu_m.tolist(), flight.vel_enu_mps.tolist()
    every = max(1, int(round(flight.info["state_rate_hz"] / TELEMETRY_HZ)))
    autopilot = f"Crazyflie firmware {flight.info['firmware']}"[:64]
    mode = str(flight.info["metadata"].get("category", "flying"))[:32]

    def setpoint(k: int) -> SetpointMsg:
        return SetpointMsg(seq=k, stamp_s=t[k], state_stamp_s=t[k], t_s=t[k], roll_rad=float(att[k, 0]),
                           pitch_rad=float(att[k, 1]), yaw_rad=float(att[k, 2]), thrust_norm=float(flight.thrust_norm[k]),
                           thrust_n=float(thrust_n[k]), acc_cmd_enu_mps2=tuple(acc[k].tolist()),
                           estimate_source="crazyflie")

    out: list[tuple[str, object]] = []
    written = 0
    for start, stop in runs(flight.kept):
        if start > 0:
            out.append(("setpoint", setpoint(start - 1)))
        for k in range(start, stop):
            out.append(("state", StateMsg(seq=k, stamp_s=t[k], t_s=t[k], pos_enu_m=tuple(pos[k]),
                                          vel_enu_mps=tuple(vel[k]), roll_rad=float(att[k, 0]),
                                          pitch_rad=float(att[k, 1]), yaw_rad=float(att[k, 2]), source="mocap")))
            out.append(("setpoint", setpoint(k)))
            if written % every == 0:
                out.append(("telemetry", TelemetryMsg(
                    stamp_s=t[k], connected=True, armed=True, in_air=True, flight_mode=mode, roll_rad=float(att[k, 0]),
                    pitch_rad=float(att[k, 1]), yaw_rad=float(att[k, 2]), pos_enu_m=tuple(pos[k]),
                    vel_enu_mps=tuple(vel[k]), battery_v=float(flight.battery_v[k]), battery_remaining=-1.0,
                    hover_thrust_norm=float(hover[k]), setpoint_age_s=-1.0, failsafe="", autopilot=autopilot)))
            written += 1
    return out


@dataclass(frozen=True)
class Imported:
    path: Path  # the recording written
    flight: NanoBenchFlight

    def report(self) -> str:
        i = self.flight.info
        m = i["thrust_model"]
        lines = [f"imported {i['file_name']} → {self.path}: {i['samples']} samples at {i['state_rate_hz']:.0f} Hz in "
                 f"{len(i['stretches'])} stretch(es), {i['duration_s']:.1f} s; {i['hardware']} ({i['trajectory']}, "
                 f"firmware {i['firmware']}); motor lead {i['motor_lead_s'] * 1e3:.0f} ms; thrust scale "
                 f"{m['scale']:.4f} ({m['scale_source']}; this flight's own {m['flight_scale']:.4f}); mass "
                 f"{i['mass_kg']:g} kg"]
        lines += [f"  skipped: {s}" for s in i["skipped"]]
        lines += [f"  note: {n}" for n in i["notes"]]
        return "\n".join(lines)


@dataclass(frozen=True)
class ImportRun:
    """One import command: the flights written, the files refused (path, one-line reason), the scale used."""

    imported: list[Imported]
    refused: list[tuple[str, str]]
    scale: float | None
    seconds: float

    def report(self) -> str:
        return "\n".join([r.report() for r in self.imported] + [f"error: {why}" for _, why in self.refused])


def import_nanobench(paths, out: str | Path, config: NanoBenchConfig = NanoBenchConfig()) -> ImportRun:
    """Read every CSV of ``paths`` (module docstring), refuse the bad ones and the byte-identical copies (one line
    each, nothing written for them), fix one thrust scale (``config.thrust_scale`` or the median of the accepted
    flights' own) and write each accepted flight to ``out/<stem>.rrd`` (``out`` may be a ``.rrd`` path for one file)."""
    started = time.perf_counter()
    valid_name(config.vehicle, "vehicle")
    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    out = Path(out)
    if out.suffix == ".rrd" and len(paths) != 1:
        raise ValueError(f"{out}: one .rrd path for {len(paths)} files; give a folder")
    flights: list[NanoBenchFlight] = []
    refused: list[tuple[str, str]] = []
    first_of: dict[str, Path] = {}
    for path in paths:
        try:
            data = read_bytes(path)
            digest = hashlib.sha256(data[0]).hexdigest()
            if digest in first_of:
                raise ImportRefused(f"{path}: byte-identical to {first_of[digest]} (SHA-256 {digest[:12]}): a copy, "
                                    "not another flight")
            first_of[digest] = path
            flights.append(nanobench_flight(path, config, data=data))
        except ImportRefused as exc:
            refused.append((str(path), str(exc)))
    if config.thrust_scale is not None:
        scale, source = config.thrust_scale, "given"
    elif flights:
        scale = float(np.median([f.own_scale for f in flights]))
        source = f"median of the {len(flights)} flight(s) of this import's own fits"
    else:
        return ImportRun([], refused, None, time.perf_counter() - started)
    imported = []
    for flight in flights:
        flight.info["thrust_model"].update(scale=scale, scale_source=source)
        name = Path(flight.info["file_name"])
        stem = name.name[: -len(next(s for s in SUFFIXES[::-1] if name.name.lower().endswith(s)))]
        target = out if out.suffix == ".rrd" else out / f"{stem}.rrd"
        target.parent.mkdir(parents=True, exist_ok=True)
        messages = flight_messages(flight, scale=scale, mass_kg=config.mass_kg, gravity_mps2=config.gravity_mps2)
        write_flight(flight, target, vehicle=config.vehicle, flight_id=f"nanobench-{stem}", messages=messages,
                     source=f"NanoBench CSV {flight.info['file_name']}")
        imported.append(Imported(target, flight))
    return ImportRun(imported, refused, scale, time.perf_counter() - started)
