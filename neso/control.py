"""The outer-loop control law (paper eq. 2, 3, 9) and its mapping to a PX4 attitude setpoint.

    a_d = q̈* + k_p (q* − q) + k_d (q̇* − q̇) − f̂           (ENU, m/s²)
    F_d = m (a_d − g)    with g = (0, 0, −9.81)             (N)

The increment of F_d between two samples is saturated (paper Remark 2: this is what makes
Assumption 2, ‖u̇‖ ≤ L_u, true), its tilt is limited, then T_d = ‖F_d‖ and R_d has its
z axis along F_d and its heading at ψ_d (Lee, Leok & McClamroch 2010); roll and pitch are
read off R_d. PX4 takes normalised thrust, here T_d / (m g) · hover_thrust_norm: linear
in force through the hover-thrust estimate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from neso.estimator import AppliedControl
from neso.rotations import world_from_body_zyx
from neso.types import LOOP_PERIOD_S, AttitudeSetpoint, Reference, StateMeasurement, VehicleModel


# Named start-up gain sets, (kp, kd) per axis (x, y, z). "paper": the paper's gains, ControlConfig's defaults, tuned
# on an inner loop answering in ~50 ms. "px4": softer xy for PX4's default attitude loop (160–200 ms from setpoint to
# attitude, measured with PX4 v1.16.0 SITL): at the paper's xy gains the position loop limit-cycles ±0.2 m there
# (tilt at the 35° limit), at kp_xy 2, kd_xy 2 it hovers at 1.8 cm. z is the paper's in both (the z loop and its
# certificate are the method's).
GAIN_SETS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "paper": ((6.0, 6.0, 10.0), (4.5, 4.5, 6.0)),
    "px4": ((2.0, 2.0, 10.0), (2.0, 2.0, 6.0)),
}


@dataclass(frozen=True, slots=True)
class ControlConfig:
    """Gains per axis (x, y, z): ``kp`` in 1/s², ``kd`` in 1/s.

    ``force_rate_limit_nps``: the largest change of each component of F_d per second
    (N/s); at 50 Hz and 40 N/s that is 0.8 N per sample. ``max_tilt_rad``: tilt limit.
    """

    kp: tuple[float, float, float] = GAIN_SETS["paper"][0]
    kd: tuple[float, float, float] = GAIN_SETS["paper"][1]
    dt_s: float = LOOP_PERIOD_S
    force_rate_limit_nps: float = 40.0
    max_tilt_rad: float = math.radians(35.0)
    min_thrust_fraction: float = 0.1
    vehicle: VehicleModel = field(default_factory=VehicleModel)

    def __post_init__(self) -> None:
        for name in ("kp", "kd"):
            gains = getattr(self, name)
            if len(gains) != 3 or not all(g > 0 and math.isfinite(g) for g in gains):
                raise ValueError(f"{name} must be three positive finite gains, got {gains}")
        if not self.force_rate_limit_nps > 0:
            raise ValueError("force_rate_limit_nps must be positive")

    @property
    def force_step_limit_n(self) -> float:
        """The largest change of each component of F_d from one sample to the next, N."""
        return self.force_rate_limit_nps * self.dt_s


@dataclass(frozen=True, slots=True)
class ControlOutput:
    setpoint: AttitudeSetpoint
    applied: AppliedControl  # what the estimator must be told acted over the next period
    force_enu_n: np.ndarray  # F_d after saturation (3,)
    acc_desired_enu_mps2: np.ndarray  # a_d before saturation (3,)


def hover_force(vehicle: VehicleModel) -> np.ndarray:
    return np.array([0.0, 0.0, vehicle.mass_kg * vehicle.gravity_mps2])


def _floats(v) -> list[float]:
    """A (3,) vector as Python floats (``tolist`` for float arrays: no per-element conversion)."""
    return v.tolist() if isinstance(v, np.ndarray) and v.dtype == np.float64 else [float(x) for x in v]


def limit_tilt(force_enu_n, max_tilt_rad: float, min_up_n: float) -> tuple[float, float, float]:
    """Keep the vertical component ≥ ``min_up_n`` and the tilt from vertical ≤ ``max_tilt_rad`` (3 floats)."""
    fz = max(float(force_enu_n[2]), min_up_n)
    horizontal = math.hypot(float(force_enu_n[0]), float(force_enu_n[1]))
    max_horizontal = fz * math.tan(max_tilt_rad)
    scale = 1.0 if horizontal <= max_horizontal else max_horizontal / horizontal
    return force_enu_n[0] * scale, force_enu_n[1] * scale, fz


def attitude_from_force(force_enu_n, yaw_rad: float) -> tuple[float, float, float, float]:
    """(thrust N, roll rad, pitch rad, yaw rad) with the body z axis along ``force_enu_n`` (3,).

    On scalars: numpy's per-call overhead on 3-vectors was most of the controller's time per sample."""
    fx, fy, fz = float(force_enu_n[0]), float(force_enu_n[1]), float(force_enu_n[2])
    thrust_n = math.sqrt(fx * fx + fy * fy + fz * fz)
    zx, zy, zz = fx / thrust_n, fy / thrust_n, fz / thrust_n  # z_b
    # x_b ⟂ the horizontal y axis at ψ_d keeps x_b in the vertical plane of heading ψ_d,
    # so the ZYX yaw of R_d is exactly ψ_d (building from x_c instead drifts it when tilted):
    # x_b = y_c × z_b with y_c = (−sin ψ_d, cos ψ_d, 0), normalised
    cx, cy = -math.sin(yaw_rad), math.cos(yaw_rad)
    xx, xy, xz = cy * zz, -(cx * zz), cx * zy - cy * zx
    norm = math.sqrt(xx * xx + xy * xy + xz * xz)
    xx, xy, xz = xx / norm, xy / norm, xz / norm
    # R_d = [x_b, z_b × x_b, z_b]; ZYX angles read off R[2,0], R[2,1] (= z of z_b × x_b), R[2,2], R[1,0], R[0,0]
    pitch = -math.asin(max(-1.0, min(1.0, xz)))
    roll = math.atan2(zx * xy - zy * xx, zz)
    yaw = math.atan2(xy, xx)
    return thrust_n, roll, pitch, yaw


def normalised_thrust(thrust_n: float, vehicle: VehicleModel) -> float:
    """PX4 normalised thrust in [0, 1] for ``thrust_n`` through the hover-thrust estimate."""
    return min(1.0, max(0.0, thrust_n / vehicle.hover_thrust_n * vehicle.hover_thrust_norm))


def nominal_acceleration(setpoint: AttitudeSetpoint, vehicle: VehicleModel) -> np.ndarray:
    """g + R·[0, 0, T]/m (3,): what ``setpoint`` accelerates the nominal model by (the ESO's input)."""
    thrust_n = setpoint.thrust_norm / vehicle.hover_thrust_norm * vehicle.hover_thrust_n
    z_body = world_from_body_zyx(setpoint.roll_rad, setpoint.pitch_rad, setpoint.yaw_rad)[:, 2]
    return z_body * (thrust_n / vehicle.mass_kg) - np.array([0.0, 0.0, vehicle.gravity_mps2])


class PositionController:
    """PD + feed-forward − f̂, with the force increment saturated between samples."""

    def __init__(self, config: ControlConfig = ControlConfig()) -> None:
        self.config = config
        self._max_step_n = config.force_step_limit_n
        self._min_up_n = config.min_thrust_fraction * config.vehicle.hover_thrust_n
        self.force_prev_enu_n = hover_force(config.vehicle)
        self._gravity_mps2 = config.vehicle.gravity_mps2
        self._gravity_enu = np.array([0.0, 0.0, config.vehicle.gravity_mps2])

    def reset(self, force_enu_n: np.ndarray | None = None) -> None:
        self.force_prev_enu_n = hover_force(self.config.vehicle) if force_enu_n is None else np.array(force_enu_n, float)

    def hover_output(self, yaw_rad: float = 0.0) -> ControlOutput:
        """The setpoint that holds the nominal model in hover (used before the first sample)."""
        return self._output(hover_force(self.config.vehicle), yaw_rad, np.zeros(3))

    def step(self, meas: StateMeasurement, ref: Reference, f_hat_mps2: np.ndarray) -> ControlOutput:
        # per axis on floats, the same operations in the same order as on the (3,) arrays
        m, (kpx, kpy, kpz), (kdx, kdy, kdz) = self.config.vehicle.mass_kg, self.config.kp, self.config.kd
        (rax, ray, raz), (rpx, rpy, rpz), (rvx, rvy, rvz) = (_floats(ref.acc_enu_mps2), _floats(ref.pos_enu_m),
                                                             _floats(ref.vel_enu_mps))
        (px, py, pz), (vx, vy, vz) = _floats(meas.pos_enu_m), _floats(meas.vel_enu_mps)
        fhx, fhy, fhz = _floats(f_hat_mps2)
        acc_desired = (rax + kpx * (rpx - px) + kdx * (rvx - vx) - fhx,
                       ray + kpy * (rpy - py) + kdy * (rvy - vy) - fhy,
                       raz + kpz * (rpz - pz) + kdz * (rvz - vz) - fhz)
        force = (m * acc_desired[0], m * acc_desired[1], m * (acc_desired[2] + self._gravity_mps2))
        prev = self.force_prev_enu_n.tolist()
        if not all(map(math.isfinite, force)):
            force = prev
        lim = self._max_step_n
        force = limit_tilt([p + min(lim, max(-lim, f - p)) for f, p in zip(force, prev)],
                           self.config.max_tilt_rad, self._min_up_n)
        self.force_prev_enu_n = force_arr = np.array(force)
        return self._output(force_arr, ref.yaw_rad, np.array(acc_desired))

    def _output(self, force: np.ndarray, yaw_rad: float, acc_desired: np.ndarray) -> ControlOutput:
        vehicle = self.config.vehicle
        thrust_n, roll, pitch, yaw = attitude_from_force(force, yaw_rad)
        thrust_norm = normalised_thrust(thrust_n, vehicle)
        setpoint = AttitudeSetpoint(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, thrust_norm=thrust_norm, thrust_n=thrust_n)
        # what nominal_acceleration(setpoint) gives, without rebuilding R_d: the body z axis is
        # force/‖force‖ and the thrust sent is the normalised one mapped back (clamping included)
        thrust_sent_n = thrust_norm / vehicle.hover_thrust_norm * vehicle.hover_thrust_n
        acc_cmd = force * (thrust_sent_n / (thrust_n * vehicle.mass_kg)) - self._gravity_enu
        applied = AppliedControl(acc_cmd_enu_mps2=acc_cmd, thrust_n=thrust_n)
        return ControlOutput(setpoint=setpoint, applied=applied, force_enu_n=force, acc_desired_enu_mps2=acc_desired)
