"""Quadrotor truth simulator: 6-DoF rigid body, PX4-like inner loop, delay, ground effect, gusts, mocap.

Frames and units: world ENU (z up), body FLU, SI units, radians. ``world_from_body`` rotates body
vectors into the world. Rigid body (paper eq. 14)::

    P' = V,   m V' = m g + R F^B + d,   R' = R [Omega]x,   I Omega' = -Omega x I Omega + M^B

with ``g = (0, 0, -9.81)``, ``F^B = (0, 0, sum_i T_i)`` and ``d`` = rotor drag on the air-relative
velocity (gusts enter here) + ground contact. The rotor thrusts ``T_i`` come from a PX4-like inner
loop (attitude P -> body-rate P -> moments, first-order actuator lags, per-rotor allocation with
saturation) and are multiplied per rotor by the ground-effect ratio at that rotor's height.
Optional rotor aerodynamics (``sim.rotor_aero``, chosen on ``SimConfig``, off by default) scale
the rotor drag with the rotors' thrust, add translational lift along body z, and wash the
ground effect out with edgewise speed.

The truth differs from the controller's nominal model (mass 1.0 kg, hover thrust_norm 0.5,
thrust linear in the command, no delay): true mass 1.05 kg, thrust = thrust_norm * max thrust *
battery factor (true hover thrust_norm 0.525, slowly rising as the battery sags), a command
transport delay, actuator lags, rotor drag, ground effect, gusts, mocap noise and latency.

Integration: semi-implicit (symplectic) Euler at ``dt_s`` (default 2 ms = 500 Hz), quaternion
attitude renormalised every sub-step; the sub-step is written with plain Python floats for speed
(see ``sim_speed_x_real_time``).
"""
from __future__ import annotations

import copy
import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from neso.rotations import world_from_body_zyx
from neso.types import GRAVITY_MPS2, LOOP_PERIOD_S, AttitudeSetpoint, StateMeasurement
from sim.ground_effect import ExponentialGroundEffect, GroundEffectModel, NoGroundEffect
from sim.mocap import MocapConfig, MocapFilter, MocapSample
from sim.rotor_aero import (
    ConstantRotorDrag,
    GroundEffectWashout,
    NoTranslationalLift,
    NoWashout,
    RotorDragScaling,
    TranslationalLift,
    hover_induced_velocity_mps,
)
from sim.terrain import FlatGround, Terrain
from sim.turbulence import MILD_TURBULENCE, DrydenGusts, TurbulenceConfig

# The controller's nominal model (neso.types.VehicleModel defaults); used only to define the
# "disturbance the nominal model does not explain" reported in TruthState.
NOMINAL_MASS_KG = 1.0
NOMINAL_HOVER_THRUST_NORM = 0.5

_NEURAL_LANDER_LAG_S = -0.01 / math.log(0.8)  # u <- 0.8 u + 0.2 u_d at 100 Hz: 44.8 ms


@dataclass(frozen=True, slots=True)
class QuadrotorParams:
    """The true vehicle (X configuration). Constants and sources:

    - ``mass_kg`` 1.05: 5 % heavier than the controller's 1.0 kg (battery/payload mismatch;
      brief's choice).
    - ``inertia_kgm2`` (0.0105, 0.0105, 0.020): PX4 SITL Iris (1.5 kg, 0.25 m arms: 0.029,
      0.029, 0.055) scaled by m l^2 to 1.05 kg and 0.18 m arms.
    - ``arm_length_m`` 0.18: rotor hub to centre (360 mm motor-to-motor diagonal; assumed for a
      ~1 kg vehicle such as the paper's ModalAI Seeker class).
    - ``rotor_radius_m`` 0.0635: 5-inch propellers (assumed), used by Cheeseman-Bennett and
      Sanchez-Cuevas.
    - ``yaw_moment_per_thrust_m`` 0.016: rotor drag torque / thrust (typical 0.01-0.025 m; RotorPy
      Hummingbird k_m/k_eta = 0.024 m).
    - ``max_thrust_n`` 2 * 9.81 * 1.0 = 19.62 N: thrust-to-weight 2 for the nominal mass, so the
      TRUE hover thrust_norm is 1.05 g / 19.62 = 0.525 (controller believes 0.5).
    - ``min_thrust_norm`` 0.0: PX4 offboard may command zero thrust (motors idle).
    - ``battery_sag_per_min`` 0.02: fractional thrust loss per minute at a fixed command. A LiPo
      goes from ~4.2 V to ~3.7 V per cell over a ~10 min flight (-12 %), and static thrust at a
      fixed duty cycle scales roughly with V^2 (-20 % over the flight): ~2 %/min. PX4 can
      compensate (MC_BAT_SCALE_EN), here it does not.
    - ``drag_coeff_per_s`` (0.4, 0.4, 0.5): linear rotor drag, body frame, mass-normalised
      (acceleration per m/s of air-relative velocity). x, y: Faessler, Franchi, Scaramuzza
      (RA-L 2018) identified 0.54 and 0.39 s^-1 on a ~1 kg quadrotor. z: axial inflow changes
      thrust at fixed rotor speed by ~ -T V / (2 v_h) (momentum theory), v_h ~ 9 m/s for these
      rotors gives ~0.54 s^-1; blade-element corrections reduce it; 0.5 taken.
    - ``contact_height_m`` 0.05: height of the body origin (rotor plane) above the feet; the
      body origin cannot go below terrain + this. Assumed (landing gear / protective frame).
    - ``rotor_time_constant_up_s`` 0.0125, ``rotor_time_constant_down_s`` 0.025: first-order lag of
      one rotor's thrust to its command, spinning up / down; used only when an autopilot commands
      each rotor (:meth:`QuadrotorSim.step_rotors`, PX4 in the loop), the built-in inner loop has its
      own lags (``InnerLoopParams``). Source: the motor model of PX4's Gazebo Classic Iris
      (PX4-SITL_gazebo-classic, models/iris: ``timeConstantUp`` 0.0125, ``timeConstantDown`` 0.025).
    """

    mass_kg: float = 1.05
    inertia_kgm2: tuple[float, float, float] = (0.0105, 0.0105, 0.020)
    arm_length_m: float = 0.18
    rotor_radius_m: float = 0.0635
    yaw_moment_per_thrust_m: float = 0.016
    max_thrust_n: float = 2.0 * GRAVITY_MPS2 * 1.0
    min_thrust_norm: float = 0.0
    battery_sag_per_min: float = 0.02
    drag_coeff_per_s: tuple[float, float, float] = (0.4, 0.4, 0.5)
    contact_height_m: float = 0.05
    rotor_time_constant_up_s: float = 0.0125
    rotor_time_constant_down_s: float = 0.025

    @property
    def hover_thrust_norm(self) -> float:
        """True normalised hover thrust out of ground effect with a full battery."""
        return self.mass_kg * GRAVITY_MPS2 / self.max_thrust_n

    @property
    def hover_induced_velocity_mps(self) -> float:
        """Momentum-theory induced velocity of one rotor in hover (9.11 m/s), the speed scale
        of the edgewise-flow effects in ``sim.rotor_aero``."""
        return hover_induced_velocity_mps(self.mass_kg, self.rotor_radius_m)


@dataclass(frozen=True, slots=True)
class InnerLoopParams:
    """PX4-like inner loop standing in for the autopilot.

    ``attitude_p_per_s`` (roll/pitch 22, yaw 5): quaternion attitude-error P gains (rate setpoint
    = 2 K sign(q_e,w) q_e,xyz, as PX4's AttitudeControl). PX4's default MC_ROLL_P is 6.5; we use
    a stiffer gain so the closed loop is ~first order with a ~45 ms time constant, matching
    Neural-Lander's simulator (u <- 0.8 u + 0.2 u_d at 100 Hz): with the rate loop below the
    closed-loop poles are -24.7 and -88 +- 167j rad/s (63 % rise at ~48 ms, checked in the tests).
    ``rate_p_per_s`` (200, 200, 40):
    body-rate P as angular acceleration per rad/s (inertia-scaled). ``rate_d``: derivative gain
    on the measured rate (s), 0 by default. ``max_rate_rps`` (220, 220, 200 deg/s): PX4
    MC_ROLLRATE_MAX / MC_PITCHRATE_MAX / MC_YAWRATE_MAX defaults. ``torque_time_constant_s``
    0.005: motor lag seen by the moments (assumed; small brushless motors, 5-20 ms).
    ``thrust_time_constant_s`` 0.0448: Neural-Lander's u <- 0.8u + 0.2u_d at 100 Hz.
    ``rotor_thrust_limits`` (True): each rotor's thrust is clipped to [0, max/4] after the
    allocation, with no desaturation; False lifts the limits (an audit switch: what the
    clipping costs, not a physical vehicle).
    """

    attitude_p_per_s: tuple[float, float, float] = (22.0, 22.0, 5.0)
    rate_p_per_s: tuple[float, float, float] = (200.0, 200.0, 40.0)
    rate_d: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_rate_rps: tuple[float, float, float] = (math.radians(220.0), math.radians(220.0), math.radians(200.0))
    torque_time_constant_s: float = 0.005
    thrust_time_constant_s: float = _NEURAL_LANDER_LAG_S
    rotor_thrust_limits: bool = True


@dataclass(frozen=True, slots=True)
class SimConfig:
    """Everything that defines a simulated world.

    ``dt_s`` physics step (2 ms), ``control_period_s`` (20 ms = the paper's 50 Hz outer loop),
    ``command_delay_s`` transport delay of a setpoint (10 ms: MAVLink + PX4 scheduling; with the
    10 ms mocap latency it makes the ~20 ms loop delay of DESIGN.md). All three (and the mocap
    period and latency) must be integer multiples of ``dt_s``. ``reference_height_m`` is
    informational for experiments (the scenario's target height; paper: 0.1 m landing).

    Rotor aerodynamics (``sim.rotor_aero``): ``rotor_drag`` scales the linear rotor drag with
    the rotors' thrust, ``translational_lift`` adds thrust with edgewise speed,
    ``ground_effect_washout`` weakens the ground effect with it. ``ground_effect_per_rotor``
    (default True) evaluates the ground effect at each rotor hub's own height, so tilt and a
    slope change it; False evaluates every rotor at the body origin's height (an audit switch:
    ground effect without its attitude dependence).
    """

    params: QuadrotorParams = field(default_factory=QuadrotorParams)
    inner_loop: InnerLoopParams = field(default_factory=InnerLoopParams)
    dt_s: float = 0.002
    control_period_s: float = LOOP_PERIOD_S
    command_delay_s: float = 0.010
    ground_effect: GroundEffectModel = field(default_factory=ExponentialGroundEffect)
    ground_effect_washout: GroundEffectWashout = field(default_factory=NoWashout)
    ground_effect_per_rotor: bool = True
    rotor_drag: RotorDragScaling = field(default_factory=ConstantRotorDrag)
    translational_lift: TranslationalLift = field(default_factory=NoTranslationalLift)
    terrain: Terrain = field(default_factory=FlatGround)
    turbulence: TurbulenceConfig = MILD_TURBULENCE
    mocap: MocapConfig = field(default_factory=MocapConfig)
    initial_pos_enu_m: tuple[float, float, float] = (0.0, 0.0, 1.0)
    initial_yaw_rad: float = 0.0
    reference_height_m: float = 0.1
    name: str = "custom"


@dataclass(frozen=True, slots=True)
class TruthState:
    """The simulator's true state at ``t_s`` (s).

    ``pos_enu_m``, ``vel_enu_mps`` (3,) world ENU; ``world_from_body`` (3, 3);
    ``body_rates_rps`` (3,) FLU; ``thrust_n`` total rotor thrust actually produced (after
    saturation, battery and ground effect); ``ground_effect_ratio`` = thrust_n / the thrust the
    same rotor commands would give out of ground effect (1 = none).

    ``disturbance_acc_enu_mps2`` (3,) is the acceleration the controller's nominal model does not
    explain, over the last physics sub-step::

        f = a_true - (g + R_cmd e3 T_nom / m_nom),   T_nom = thrust_norm_cmd / 0.5 * 1.0 * 9.81

    where ``a_true = (v(t) - v(t - dt)) / dt`` (includes contact forces), ``g = (0, 0, -9.81)``,
    ``m_nom = 1.0 kg`` and ``R_cmd``, ``thrust_norm_cmd`` are the roll/pitch/yaw/thrust of the
    last valid setpoint given to ``step`` (the command the controller believes acts now; before
    the first step, the reset hover command). It lumps everything: mass and thrust-curve
    mismatch, delay, lags, battery, drag, gusts, ground effect. This is the "true f" of tests.
    """

    t_s: float
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    world_from_body: np.ndarray
    body_rates_rps: np.ndarray
    thrust_n: float
    disturbance_acc_enu_mps2: np.ndarray
    ground_effect_ratio: float
    gust_vel_enu_mps: np.ndarray
    battery_factor: float
    on_ground: bool
    crashed: bool
    diverged: bool


def _ticks(value_s: float, dt_s: float, what: str) -> int:
    n = round(value_s / dt_s)
    if abs(n * dt_s - value_s) > 1e-9 * max(1.0, abs(value_s)):
        raise ValueError(f"{what} = {value_s} s is not an integer multiple of dt_s = {dt_s} s")
    return n


def _quat_from_euler_zyx(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def _rot_from_quat(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )


class _Physics(NamedTuple):
    """One configuration's constants in the order the hot loop unpacks them into locals (SI units;
    the inner loop's gains per axis; ``c_t``/``c_m``: the thrust and moment lags' per-step factors;
    the ground effect, washout, rotor drag and terrain as the functions the loop calls)."""

    dt: float
    g: float
    m: float
    ixx: float
    iyy: float
    izz: float
    kax: float
    kay: float
    kaz: float
    krx: float
    kry: float
    krz: float
    kdx: float
    kdy: float
    kdz: float
    mrx: float
    mry: float
    mrz: float
    c_t: float
    c_m: float
    dx: float
    dy: float
    dz: float
    a: float
    inv4a: float
    kq: float
    inv4kq: float
    t_max: float
    sag: float
    contact: float
    rr: float
    arm: float
    flat: bool
    terrain_distance: Callable
    terrain_height: Callable
    use_ge: bool
    ratio: Callable
    a_ge: float
    v_i: float
    use_washout: bool
    washout_weight: Callable
    scale_drag: bool
    drag_factor: Callable
    f_hover: float
    k_h: float
    limits: bool
    f_min: float
    c_up: float
    c_dn: float


class QuadrotorSim:
    """The simulated vehicle. ``step(setpoint)`` advances one control period and returns the
    motion-capture measurement available then; ``truth`` is the true state.

    ``seed`` seeds the gusts and the mocap noise (independent streams from one
    ``numpy.random.SeedSequence``): the same seed reproduces a trajectory bit-exactly.
    Setpoints with a non-finite roll, pitch, yaw or thrust_norm are rejected (the last valid one
    is held; ``rejected_setpoints`` counts them); ``thrust_n`` is never acted on. Once
    ``crashed`` or ``diverged`` is set the state freezes (time still advances).
    """

    def __init__(self, config: SimConfig, *, seed: int) -> None:
        self.config = config
        dt = config.dt_s
        self._dt = dt
        self._n_sub = _ticks(config.control_period_s, dt, "control_period_s")
        if self._n_sub < 1:
            raise ValueError("control_period_s must be >= dt_s")
        self._delay_ticks = _ticks(config.command_delay_s, dt, "command_delay_s")
        self._mocap_ticks = _ticks(1.0 / config.mocap.rate_hz, dt, "mocap period")
        self._latency_ticks = _ticks(config.mocap.latency_s, dt, "mocap latency_s")
        self._seed = seed
        self._physics = self._physics_constants()
        self.mocap_out: list[MocapSample] | None = None  # a list here receives every mocap sample taken (a NatNet stream)
        self.reset(pos_enu_m=config.initial_pos_enu_m, yaw_rad=config.initial_yaw_rad)

    def _physics_constants(self) -> _Physics:
        cfg = self.config
        p, il, ge = cfg.params, cfg.inner_loop, cfg.ground_effect
        dt = self._dt
        a = p.arm_length_m / math.sqrt(2.0)
        use_ge = not isinstance(ge, NoGroundEffect)
        limits = il.rotor_thrust_limits
        return _Physics(
            dt=dt, g=GRAVITY_MPS2, m=p.mass_kg, ixx=p.inertia_kgm2[0], iyy=p.inertia_kgm2[1], izz=p.inertia_kgm2[2],
            kax=il.attitude_p_per_s[0], kay=il.attitude_p_per_s[1], kaz=il.attitude_p_per_s[2],
            krx=il.rate_p_per_s[0], kry=il.rate_p_per_s[1], krz=il.rate_p_per_s[2],
            kdx=il.rate_d[0], kdy=il.rate_d[1], kdz=il.rate_d[2],
            mrx=il.max_rate_rps[0], mry=il.max_rate_rps[1], mrz=il.max_rate_rps[2],
            c_t=1.0 - math.exp(-dt / il.thrust_time_constant_s), c_m=1.0 - math.exp(-dt / il.torque_time_constant_s),
            dx=p.drag_coeff_per_s[0], dy=p.drag_coeff_per_s[1], dz=p.drag_coeff_per_s[2],
            a=a, inv4a=1.0 / (4.0 * a), kq=p.yaw_moment_per_thrust_m, inv4kq=1.0 / (4.0 * p.yaw_moment_per_thrust_m),
            t_max=p.max_thrust_n, sag=p.battery_sag_per_min / 60.0, contact=p.contact_height_m, rr=p.rotor_radius_m,
            arm=p.arm_length_m, flat=isinstance(cfg.terrain, FlatGround), terrain_distance=cfg.terrain.distance_fn(),
            terrain_height=cfg.terrain.height_fn(), use_ge=use_ge, ratio=ge.thrust_ratio,
            a_ge=a if cfg.ground_effect_per_rotor else 0.0,  # hub offset seen by the ground effect
            v_i=p.hover_induced_velocity_mps,
            use_washout=use_ge and not isinstance(cfg.ground_effect_washout, NoWashout),
            washout_weight=cfg.ground_effect_washout.weight, scale_drag=not isinstance(cfg.rotor_drag, ConstantRotorDrag),
            drag_factor=cfg.rotor_drag.factor, f_hover=0.25 * p.mass_kg * GRAVITY_MPS2,
            k_h=cfg.translational_lift.k_h_per_m(p.hover_induced_velocity_mps), limits=limits,
            f_min=0.0 if limits else -math.inf,
            c_up=1.0 - math.exp(-dt / p.rotor_time_constant_up_s), c_dn=1.0 - math.exp(-dt / p.rotor_time_constant_down_s))

    # ------------------------------------------------------------------ public API
    def reset(self, *, pos_enu_m: tuple[float, float, float] | np.ndarray, yaw_rad: float = 0.0) -> StateMeasurement:
        """Start at rest and level at ``pos_enu_m`` (m, ENU) with yaw ``yaw_rad``.

        Airborne (body origin above terrain + contact height): motors at the true hover thrust
        there (m g divided by the level vehicle's ground-effect ratio at that point) and the held
        command is that hover command. Otherwise: placed on the ground, motors
        at zero thrust. Re-seeds the random streams from the constructor's seed. Returns the
        first measurement (noisy sample at t = 0).
        """
        cfg = self.config
        p = cfg.params
        ss = np.random.SeedSequence(self._seed)
        turb_ss, mocap_ss = ss.spawn(2)
        self._gusts = DrydenGusts(cfg.turbulence, self._dt, np.random.default_rng(turb_ss))
        self._mocap = MocapFilter(cfg.mocap, np.random.default_rng(mocap_ss))
        x, y, z = (float(v) for v in pos_enu_m)
        floor = cfg.terrain.height_m(x, y) + p.contact_height_m
        self._on_ground = z <= floor
        if self._on_ground:
            z = floor
        self._n = 0
        self._pos = [x, y, z]
        self._vel = [0.0, 0.0, 0.0]
        self._q = list(_quat_from_euler_zyx(0.0, 0.0, yaw_rad))
        self._w = [0.0, 0.0, 0.0]
        hover_norm = 0.0 if self._on_ground else p.hover_thrust_norm / self._level_ge_ratio(x, y, z, yaw_rad)
        self._thrust_act_n = hover_norm * p.max_thrust_n
        self._moment_act = [0.0, 0.0, 0.0]
        self._rotor_cmd: tuple[float, float, float, float] | None = None  # per-rotor commands (step_rotors)
        self._rotor_act = [0.25 * self._thrust_act_n] * 4  # each rotor's lagged thrust, N (step_rotors)
        self._active = (tuple(self._q), hover_norm)
        self._pending: deque[tuple[int, tuple[float, float, float, float], float]] = deque()
        self._cmd = (0.0, 0.0, float(yaw_rad), hover_norm)
        self._acc = [0.0, 0.0, 0.0]
        self._thrust_n = self._thrust_act_n
        self._ge_ratio = 1.0
        self._gust = (0.0, 0.0, 0.0)
        self._crashed = False
        self._diverged = False
        self.rejected_setpoints = 0
        self._samples: deque[tuple[int, MocapSample]] = deque(
            maxlen=self._latency_ticks // self._mocap_ticks + 3
        )
        self._record_sample()
        return self._measurement()

    @property
    def t_s(self) -> float:
        return self._n * self._dt

    @property
    def crashed(self) -> bool:
        return self._crashed

    @property
    def diverged(self) -> bool:
        return self._diverged

    def step(self, setpoint: AttitudeSetpoint) -> StateMeasurement:
        """Take ``setpoint`` at the current time t, advance one control period, and return the
        latest mocap sample taken at or before (t + period - latency). The setpoint acts on
        the vehicle from t + command_delay_s."""
        r, pi, ya, tn = setpoint.roll_rad, setpoint.pitch_rad, setpoint.yaw_rad, setpoint.thrust_norm
        if math.isfinite(r) and math.isfinite(pi) and math.isfinite(ya) and math.isfinite(tn):
            tmin = self.config.params.min_thrust_norm
            tn = tmin if tn < tmin else (1.0 if tn > 1.0 else float(tn))
            self._cmd = (float(r), float(pi), float(ya), tn)
            self._pending.append((self._n + self._delay_ticks, _quat_from_euler_zyx(r, pi, ya), tn))
        else:
            self.rejected_setpoints += 1
        self._rotor_cmd = None
        self._advance(self._n_sub)
        return self._measurement()

    def step_rotors(self, rotor_cmd: tuple[float, float, float, float], n_steps: int) -> None:
        """Advance ``n_steps`` physics steps with each rotor commanded directly, as an autopilot's
        motor outputs do (PX4 in the loop): ``rotor_cmd`` is rotor i's thrust as a fraction 0–1 of its
        maximum (``max_thrust_n`` / 4, times the battery factor), in the world's rotor order (0: front
        left, 1: rear right, 2: front right, 3: rear left, body FLU; 0 and 1 turn clockwise seen from
        above). Each rotor follows its command with the lags of ``QuadrotorParams`` and no transport
        delay; the built-in inner loop and its setpoint are bypassed until :meth:`step` is called again.
        A command that is not four finite numbers is rejected (``rejected_setpoints``; the last one is
        held); values are clipped to [0, 1]."""
        cmd = tuple(float(u) for u in rotor_cmd)
        if len(cmd) == 4 and all(math.isfinite(u) for u in cmd):
            self._rotor_cmd = tuple(0.0 if u < 0.0 else (1.0 if u > 1.0 else u) for u in cmd)
        else:
            self.rejected_setpoints += 1
            if self._rotor_cmd is None:
                self._rotor_cmd = (0.0, 0.0, 0.0, 0.0)
        self._advance(n_steps)

    def reference_setpoint(self, setpoint: AttitudeSetpoint) -> None:
        """Take ``setpoint`` as the command the nominal model believes acts now (the reference of
        ``TruthState.disturbance_acc_enu_mps2``) without flying it: with an autopilot in the loop
        (:meth:`step_rotors`) the controller's setpoint goes to the autopilot, not to the world."""
        r, pi, ya, tn = setpoint.roll_rad, setpoint.pitch_rad, setpoint.yaw_rad, setpoint.thrust_norm
        if math.isfinite(r) and math.isfinite(pi) and math.isfinite(ya) and math.isfinite(tn):
            self._cmd = (float(r), float(pi), float(ya), min(max(float(tn), self.config.params.min_thrust_norm), 1.0))

    @property
    def specific_force_body_flu_mps2(self) -> np.ndarray:
        """What an accelerometer on the body origin measures over the last physics step (3,), body
        FLU, m/s²: R^T (a - g), contact forces included (at rest on the ground: (0, 0, +9.81)). Once
        ``crashed`` or ``diverged`` the state is frozen at rest: gravity alone."""
        r = _rot_from_quat(*self._q)
        if self._crashed or self._diverged:
            return r.T @ np.array([0.0, 0.0, GRAVITY_MPS2])
        return r.T @ np.array([self._acc[0], self._acc[1], self._acc[2] + GRAVITY_MPS2])

    @property
    def rotor_thrusts_n(self) -> tuple[float, float, float, float]:
        """Each rotor's lagged thrust out of ground effect under :meth:`step_rotors` (N, world rotor order)."""
        return tuple(self._rotor_act)

    def branch(self, config: SimConfig) -> "QuadrotorSim":
        """A copy of this simulator in its current state (time, vehicle, lags, commands in
        flight, random streams) that continues under ``config``: the world's physics may differ
        (vehicle, inner loop, ground effect, rotor aerodynamics, terrain, gust intensity, command
        delay), its timing may not (``dt_s``, ``control_period_s``, mocap rate and latency raise
        ``ValueError``). Both continue from the same state, so one step of each with the same
        setpoint measures what the difference between the worlds does there."""
        old = self.config
        if (config.dt_s, config.control_period_s, config.mocap.rate_hz, config.mocap.latency_s) != (
                old.dt_s, old.control_period_s, old.mocap.rate_hz, old.mocap.latency_s):
            raise ValueError("a branch keeps the simulator's timing (dt_s, control_period_s, mocap rate and latency)")
        twin = copy.copy(self)  # the state lists are replaced, never mutated, by _advance
        twin.config = config
        twin._delay_ticks = _ticks(config.command_delay_s, config.dt_s, "command_delay_s")
        twin._pending = deque(self._pending)
        twin._samples = deque(self._samples, maxlen=self._samples.maxlen)
        twin._gusts = self._gusts.reconfigured(config.turbulence)
        twin._mocap = self._mocap.copy()
        twin._physics = twin._physics_constants()
        return twin

    @property
    def truth(self) -> TruthState:
        """The true state now (see ``TruthState`` for the disturbance definition)."""
        r_now = _rot_from_quat(*self._q)
        roll, pitch, yaw, tn = self._cmd
        r_cmd = world_from_body_zyx(roll, pitch, yaw)
        t_nom = tn / NOMINAL_HOVER_THRUST_NORM * NOMINAL_MASS_KG * GRAVITY_MPS2
        a_nom = r_cmd[:, 2] * (t_nom / NOMINAL_MASS_KG) + np.array([0.0, 0.0, -GRAVITY_MPS2])
        return TruthState(
            t_s=self.t_s,
            pos_enu_m=np.array(self._pos),
            vel_enu_mps=np.array(self._vel),
            world_from_body=r_now,
            body_rates_rps=np.array(self._w),
            thrust_n=self._thrust_n,
            disturbance_acc_enu_mps2=np.array(self._acc) - a_nom,
            ground_effect_ratio=self._ge_ratio,
            gust_vel_enu_mps=np.array(self._gust),
            battery_factor=self._battery(self.t_s),
            on_ground=self._on_ground,
            crashed=self._crashed,
            diverged=self._diverged,
        )

    @property
    def applied_thrust_nominal_n(self) -> float:
        """The thrust the rotors are being driven to after the command's delay and lag, in the
        controller's nominal Newtons (thrust_norm / 0.5 · 1.0 kg · g): what a perfect model of the
        vehicle's thrust response would say is applied, before battery, ground effect and rotor
        saturation (N)."""
        full = self.config.params.max_thrust_n * self._battery(self.t_s)
        tn = self._thrust_act_n / full if full > 0 else 0.0
        return tn / NOMINAL_HOVER_THRUST_NORM * NOMINAL_MASS_KG * GRAVITY_MPS2

    # ------------------------------------------------------------------ internals
    def _level_ge_ratio(self, x: float, y: float, z: float, yaw_rad: float) -> float:
        """Total ground-effect ratio of the level vehicle at (x, y, z) with yaw ``yaw_rad``."""
        p = self.config.params
        dist = self.config.terrain.distance_fn()
        ge = self.config.ground_effect
        a = p.arm_length_m / math.sqrt(2.0)
        cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
        total = 0.0
        for bx, by in ((a, a), (-a, -a), (a, -a), (-a, a)):
            if not self.config.ground_effect_per_rotor:
                bx = by = 0.0
            h = dist(x + cy * bx - sy * by, y + sy * bx + cy * by, z)
            total += ge.thrust_ratio(h, p.rotor_radius_m, p.arm_length_m)
        return 0.25 * total

    def _battery(self, t_s: float) -> float:
        f = 1.0 - self.config.params.battery_sag_per_min * t_s / 60.0
        return f if f > 0.0 else 0.0

    def _record_sample(self) -> None:
        qw, qx, qy, qz = self._q
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r00 = 1 - 2 * (qy * qy + qz * qz)
        rpy = (
            math.atan2(r21, r22),
            -math.asin(max(-1.0, min(1.0, r20))),
            math.atan2(r10, r00),
        )
        s = self._mocap.sample(self._n * self._dt, (self._pos[0], self._pos[1], self._pos[2]), rpy)
        self._samples.append((self._n, s))
        if self.mocap_out is not None:
            self.mocap_out.append(s)

    def _measurement(self) -> StateMeasurement:
        limit = self._n - self._latency_ticks
        chosen = self._samples[0][1]
        for tick, s in self._samples:
            if tick <= limit:
                chosen = s
            else:
                break
        return StateMeasurement(
            t_s=chosen.t_s,
            pos_enu_m=np.array(chosen.pos_enu_m),
            vel_enu_mps=np.array(chosen.vel_enu_mps),
            roll_rad=chosen.roll_rad,
            pitch_rad=chosen.pitch_rad,
            yaw_rad=chosen.yaw_rad,
        )

    def _advance(self, n_steps: int) -> None:
        if self._crashed or self._diverged:
            self._advance_frozen(n_steps)
        else:
            self._advance_flying(n_steps)

    def _advance_frozen(self, n_steps: int) -> None:
        """After a crash or divergence: time advances, the state stays, the mocap keeps sampling it."""
        for _ in range(n_steps):
            self._n += 1
            if self._n % self._mocap_ticks == 0:
                self._record_sample()

    def _advance_flying(self, n_steps: int) -> None:  # noqa: C901 - the hot loop
        """``n_steps`` physics steps: inner attitude loop, rotor allocation and limits, ground effect,
        gusts and rotor drag, rigid-body integration, ground contact. The loop body is one piece of
        scalar arithmetic on locals on purpose: it runs 10 times per control period, and Python
        function calls there would be a visible share of its cost (``python -m bench``, simulator
        speed); the configuration's constants come unpacked from :meth:`_physics_constants`."""
        (dt, g, m, ixx, iyy, izz, kax, kay, kaz, krx, kry, krz, kdx, kdy, kdz, mrx, mry, mrz, c_t, c_m, dx, dy, dz,
         a, inv4a, kq, inv4kq, t_max, sag, contact, rr, arm, flat, terrain_distance, terrain_height, use_ge, ratio,
         a_ge, v_i, use_washout, washout_weight, scale_drag, drag_factor, f_hover, k_h, limits, f_min, c_up,
         c_dn) = self._physics
        gust_step = self._gusts.step
        mocap_ticks = self._mocap_ticks
        pending = self._pending

        n = self._n
        n_end = n + n_steps
        px, py, pz = self._pos
        vx, vy, vz = self._vel
        qw, qx, qy, qz = self._q
        wx, wy, wz = self._w
        t_act = self._thrust_act_n
        mx_act, my_act, mz_act = self._moment_act
        (qdw, qdx, qdy, qdz), tn = self._active
        on_ground = self._on_ground
        ax = ay = az = 0.0
        thrust = self._thrust_n
        ge_total = self._ge_ratio
        gwx, gwy, gwz = self._gust
        direct = self._rotor_cmd is not None  # an autopilot commands the rotors (step_rotors)
        u0, u1, u2, u3 = self._rotor_cmd if direct else (0.0, 0.0, 0.0, 0.0)
        r0, r1, r2, r3 = self._rotor_act
        crashed = diverged = False
        wx_prev, wy_prev, wz_prev = wx, wy, wz

        for _ in range(n_steps):
            while pending and pending[0][0] <= n:
                _, (qdw, qdx, qdy, qdz), tn = pending.popleft()
            t_now = n * dt
            batt = 1.0 - sag * t_now
            if batt < 0.0:
                batt = 0.0
            # --- rotation matrix (world_from_body)
            xx, yy, zz = qx * qx, qy * qy, qz * qz
            xy, xz, yz = qx * qy, qx * qz, qy * qz
            wxq, wyq, wzq = qw * qx, qw * qy, qw * qz
            r00 = 1.0 - 2.0 * (yy + zz)
            r01 = 2.0 * (xy - wzq)
            r02 = 2.0 * (xz + wyq)
            r10 = 2.0 * (xy + wzq)
            r11 = 1.0 - 2.0 * (xx + zz)
            r12 = 2.0 * (yz - wxq)
            r20 = 2.0 * (xz - wyq)
            r21 = 2.0 * (yz + wxq)
            r22 = 1.0 - 2.0 * (xx + yy)
            if direct:  # --- each rotor follows its command (fraction of its maximum), first-order lags
                f_max = 0.25 * t_max * batt
                d = u0 * f_max - r0
                r0 += (c_up if d > 0.0 else c_dn) * d
                d = u1 * f_max - r1
                r1 += (c_up if d > 0.0 else c_dn) * d
                d = u2 * f_max - r2
                r2 += (c_up if d > 0.0 else c_dn) * d
                d = u3 * f_max - r3
                r3 += (c_up if d > 0.0 else c_dn) * d
                f0, f1, f2, f3 = r0, r1, r2, r3
            else:
                # --- attitude P: q_e = conj(q) * q_d, rate setpoint in body frame
                ew = qw * qdw + qx * qdx + qy * qdy + qz * qdz
                ex = qw * qdx - qx * qdw - qy * qdz + qz * qdy
                ey = qw * qdy - qy * qdw - qz * qdx + qx * qdz
                ez = qw * qdz - qz * qdw - qx * qdy + qy * qdx
                s2 = 2.0 if ew >= 0.0 else -2.0
                rsx = s2 * kax * ex
                rsy = s2 * kay * ey
                rsz = s2 * kaz * ez
                rsx = mrx if rsx > mrx else (-mrx if rsx < -mrx else rsx)
                rsy = mry if rsy > mry else (-mry if rsy < -mry else rsy)
                rsz = mrz if rsz > mrz else (-mrz if rsz < -mrz else rsz)
                # --- rate P(+D) -> moment commands, first-order actuator lags
                mx_cmd = ixx * (krx * (rsx - wx) - kdx * (wx - wx_prev) / dt)
                my_cmd = iyy * (kry * (rsy - wy) - kdy * (wy - wy_prev) / dt)
                mz_cmd = izz * (krz * (rsz - wz) - kdz * (wz - wz_prev) / dt)
                mx_act += c_m * (mx_cmd - mx_act)
                my_act += c_m * (my_cmd - my_act)
                mz_act += c_m * (mz_cmd - mz_act)
                t_act += c_t * (tn * t_max * batt - t_act)
                # --- allocation (X quad), per-rotor saturation
                # rotors: 0 (+a,+a) ccw-ish c=+1, 1 (-a,-a) c=+1, 2 (+a,-a) c=-1, 3 (-a,+a) c=-1
                f_max = 0.25 * t_max * batt if limits else math.inf
                tq = 0.25 * t_act
                mxa = mx_act * inv4a
                mya = my_act * inv4a
                mza = mz_act * inv4kq
                f0 = tq + mxa - mya + mza
                f1 = tq - mxa + mya + mza
                f2 = tq - mxa - mya - mza
                f3 = tq + mxa + mya - mza
                f0 = f_min if f0 < f_min else (f_max if f0 > f_max else f0)
                f1 = f_min if f1 < f_min else (f_max if f1 > f_max else f1)
                f2 = f_min if f2 < f_min else (f_max if f2 > f_max else f2)
                f3 = f_min if f3 < f_min else (f_max if f3 > f_max else f3)
            # --- gusts and the air-relative velocity, body frame
            h_terrain = pz if flat else pz - terrain_height(px, py)
            gwx, gwy, gwz = gust_step(h_terrain, math.sqrt(vx * vx + vy * vy))
            rx, ry, rz = vx - gwx, vy - gwy, vz - gwz
            bvx = r00 * rx + r10 * ry + r20 * rz
            bvy = r01 * rx + r11 * ry + r21 * rz
            bvz = r02 * rx + r12 * ry + r22 * rz
            edgewise_sq = bvx * bvx + bvy * bvy
            drag_scale = drag_factor(f0, f1, f2, f3, f_hover) if scale_drag else 1.0
            # --- ground effect per rotor (height = perpendicular distance to terrain)
            if use_ge:
                # hub offsets in world: R (+-a, +-a, 0)
                hz0 = r20 * a_ge + r21 * a_ge
                hz2 = r20 * a_ge - r21 * a_ge
                if flat:
                    g0 = ratio(pz + hz0, rr, arm)
                    g1 = ratio(pz - hz0, rr, arm)
                    g2 = ratio(pz + hz2, rr, arm)
                    g3 = ratio(pz - hz2, rr, arm)
                else:
                    hx0 = r00 * a_ge + r01 * a_ge
                    hy0 = r10 * a_ge + r11 * a_ge
                    hx2 = r00 * a_ge - r01 * a_ge
                    hy2 = r10 * a_ge - r11 * a_ge
                    dist = terrain_distance
                    g0 = ratio(dist(px + hx0, py + hy0, pz + hz0), rr, arm)
                    g1 = ratio(dist(px - hx0, py - hy0, pz - hz0), rr, arm)
                    g2 = ratio(dist(px + hx2, py + hy2, pz + hz2), rr, arm)
                    g3 = ratio(dist(px - hx2, py - hy2, pz - hz2), rr, arm)
                if use_washout:  # rotor_aero.washed_out_ratio, inlined
                    w = washout_weight(edgewise_sq, v_i)
                    g0 = 1.0 / (1.0 - (1.0 - 1.0 / g0) * w)
                    g1 = 1.0 / (1.0 - (1.0 - 1.0 / g1) * w)
                    g2 = 1.0 / (1.0 - (1.0 - 1.0 / g2) * w)
                    g3 = 1.0 / (1.0 - (1.0 - 1.0 / g3) * w)
                f_oge = f0 + f1 + f2 + f3
                f0 *= g0
                f1 *= g1
                f2 *= g2
                f3 *= g3
                thrust = f0 + f1 + f2 + f3
                ge_total = thrust / f_oge if f_oge > 0.0 else 1.0
            else:
                thrust = f0 + f1 + f2 + f3
            mx = a * (f0 - f1 - f2 + f3)
            my = -a * (f0 - f1 + f2 - f3)
            mz = kq * (f0 + f1 - f2 - f3)
            # --- rotor drag on the air-relative velocity, translational lift
            if scale_drag:
                dbx = -(dx * drag_scale) * bvx
                dby = -(dy * drag_scale) * bvy
                dbz = -(dz * drag_scale) * bvz
            else:
                dbx = -dx * bvx
                dby = -dy * bvy
                dbz = -dz * bvz
            tm = thrust / m
            if k_h:
                tm += k_h * edgewise_sq
                thrust = tm * m
            ax = r02 * tm + r00 * dbx + r01 * dby + r02 * dbz
            ay = r12 * tm + r10 * dbx + r11 * dby + r12 * dbz
            az = r22 * tm + r20 * dbx + r21 * dby + r22 * dbz - g
            # --- semi-implicit Euler
            vx0, vy0, vz0 = vx, vy, vz
            vx += ax * dt
            vy += ay * dt
            vz += az * dt
            px += vx * dt
            py += vy * dt
            pz += vz * dt
            wx_prev, wy_prev, wz_prev = wx, wy, wz
            wx += (mx - (wy * izz * wz - wz * iyy * wy)) / ixx * dt
            wy += (my - (wz * ixx * wx - wx * izz * wz)) / iyy * dt
            wz += (mz - (wx * iyy * wy - wy * ixx * wx)) / izz * dt
            hx, hy, hz = 0.5 * wx * dt, 0.5 * wy * dt, 0.5 * wz * dt
            nqw = qw - qx * hx - qy * hy - qz * hz
            nqx = qx + qw * hx + qy * hz - qz * hy
            nqy = qy + qw * hy + qz * hx - qx * hz
            nqz = qz + qw * hz + qx * hy - qy * hx
            inv = 1.0 / math.sqrt(nqw * nqw + nqx * nqx + nqy * nqy + nqz * nqz)
            qw, qx, qy, qz = nqw * inv, nqx * inv, nqy * inv, nqz * inv
            # --- ground contact (hard floor)
            floor = contact if flat else terrain_height(px, py) + contact
            if pz <= floor:
                pz = floor
                if vz < 0.0:
                    if vx * vx + vy * vy + vz * vz > 1.0:
                        crashed = True
                    vz = 0.0
                if az <= 0.0:  # resting: static friction holds it
                    vx = vy = 0.0
                    on_ground = True
                    # standing on its legs (under the hubs, a from the centre along each axis) the floor's
                    # reaction also holds roll and pitch while the rotors' moment cannot lift a leg:
                    # |M| below what is left of the weight times a (statics of a body on its support square)
                    hold = (m * g - thrust) * a
                    if -hold < mx < hold and -hold < my < hold:
                        wx = wy = 0.0
                else:
                    on_ground = False
            else:
                on_ground = False
            ax = (vx - vx0) / dt
            ay = (vy - vy0) / dt
            az = (vz - vz0) / dt
            n += 1
            if r22 < 0.5:  # tilt beyond 60 deg
                crashed = True
            if not (px * px + py * py + pz * pz <= 2500.0 and qw == qw and vx == vx and vy == vy
                    and vz == vz and wx == wx and wy == wy and wz == wz):
                diverged = True
            self._n = n
            if n % mocap_ticks == 0:
                self._pos = [px, py, pz]
                self._q = [qw, qx, qy, qz]
                self._record_sample()
            if crashed or diverged:
                break

        self._pos = [px, py, pz]
        self._vel = [vx, vy, vz]
        self._q = [qw, qx, qy, qz]
        self._w = [wx, wy, wz]
        self._thrust_act_n = t_act
        self._moment_act = [mx_act, my_act, mz_act]
        self._rotor_act = [r0, r1, r2, r3]
        self._active = ((qdw, qdx, qdy, qdz), tn)
        self._on_ground = on_ground
        self._acc = [ax, ay, az]
        self._thrust_n = thrust
        self._ge_ratio = ge_total
        self._gust = (gwx, gwy, gwz)
        self._crashed = self._crashed or crashed
        self._diverged = self._diverged or diverged
        if n < n_end:  # stopped early (crashed / diverged): time still advances, frozen
            self._advance(n_end - n)


def z_disturbance_slopes(config: SimConfig, height_m: float, *, dh_m: float = 1e-4) -> tuple[float, float]:
    """The world's own slopes of the z disturbance at a level hover ``height_m`` over flat ground:
    ``(∂f/∂p_z in 1/s², ∂f/∂v_z in 1/s)``. Height: the ground effect's ratio r(h) on the thrust that holds the
    vehicle (T = m g / r), so ``∂f/∂h = r'(h) g / r`` (central difference); vertical speed: the rotor drag's
    mass-normalised z coefficient (the slope of ``−d_z v_z``; thrust-scaled drag is at hover here). What a
    network that learned the disturbance's physics would have for slopes (issue 32's table)."""
    p = config.params

    def ratio(h: float) -> float:
        return config.ground_effect.thrust_ratio(h, p.rotor_radius_m, p.arm_length_m)

    r = ratio(height_m)
    dr = (ratio(height_m + dh_m) - ratio(height_m - dh_m)) / (2 * dh_m)
    return dr * GRAVITY_MPS2 / r, -p.drag_coeff_per_s[2]


def sim_speed_x_real_time(duration_s: float = 20.0, *, config: SimConfig | None = None, seed: int = 0) -> float:
    """Multiple of real time of a hover of ``duration_s`` (default config: 500 Hz physics,
    exponential ground effect, mild gusts, noisy mocap), held at the true hover command."""
    cfg = config if config is not None else SimConfig()
    sim = QuadrotorSim(cfg, seed=seed)
    sp = AttitudeSetpoint(0.0, 0.0, cfg.initial_yaw_rad, cfg.params.hover_thrust_norm, 0.0)
    n = round(duration_s / cfg.control_period_s)
    t0 = time.perf_counter()
    for _ in range(n):
        sim.step(sp)
    wall = time.perf_counter() - t0
    return n * cfg.control_period_s / wall
