"""The world as PX4's simulator: what its sensors read, and the world stepped by PX4's motor outputs.

PX4 SITL with an external simulator (``simulator_mavlink``, the way Gazebo Classic and jMAVSim drive it)
runs in lockstep: the simulator sends ``HIL_SENSOR`` stamped with the world's time, PX4 runs its
estimator and controllers up to that time and answers ``HIL_ACTUATOR_CONTROLS`` (each motor 0–1), the
simulator applies them for one sensor period and sends the next. :class:`HilSensors` makes the sensor
readings from the true state, :class:`AutopilotInTheLoop` is a :class:`sim.quadrotor.QuadrotorSim`
stepped that way. No I/O here: the exchange with PX4 is a callable handed in (``sim.px4_link`` is the
TCP one).

Frames: the world is ENU / body FLU; PX4 is NED / body FRD. Sensor constants and their sources are
on :class:`HilSensorConfig`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from neso.types import AttitudeSetpoint, StateMeasurement
from sim.quadrotor import QuadrotorSim

# PX4's quad X motor order (its airframe 4001 / Iris: 1 front right CCW, 2 rear left CCW, 3 front left CW,
# 4 rear right CW) mapped onto the world's rotors (0 front left, 1 rear right, 2 front right, 3 rear left; 0
# and 1 clockwise): world rotor i is driven by PX4 motor PX4_MOTOR_OF_ROTOR[i] (0-based).
PX4_MOTOR_OF_ROTOR = (2, 3, 0, 1)

# HIL_SENSOR.fields_updated bits PX4's simulator_mavlink reads (SimulatorMavlink.hpp, SensorSource):
# accel 0b111, gyro 0b111000, mag 0b111000000, baro 0b1101000000000 (abs pressure, altitude, temperature).
HIL_FIELDS_IMU_MAG_BARO = 0b111 | 0b111000 | 0b111000000 | 0b1101000000000


@dataclass(frozen=True, slots=True)
class HilSensorConfig:
    """The simulated sensors PX4 reads. Sources:

    - ``rate_hz`` 250: PX4 SITL's ``IMU_INTEG_RATE`` default for simulators (px4-rc.simulator: "Simulator
      IMU data provided at 250 Hz"); the rate verified in ``../shared/px4/README.md``.
    - IMU (white noise density, bias random walk, turn-on bias σ): the defaults of PX4's Gazebo Classic
      IMU plugin (PX4-SITL_gazebo-classic ``gazebo_imu_plugin``, an ADIS16448): gyro 0.0003394 rad/s/√Hz,
      3.8785e-5 rad/s²/√Hz, 0.0087 rad/s; accelerometer 0.004 m/s²/√Hz, 0.006 m/s³/√Hz, 0.196 m/s². The
      turn-on bias is drawn once per flight; the plugin's bias correlation times (1000 s, 300 s) are
      longer than any flight here and left out.
    - ``accel_range_mps2`` 16 g, ``gyro_range_rps`` 2000 °/s: the full-scale ranges PX4 v1.16's driver sets on
      a common flight-controller IMU (ICM20602.hpp: ACCEL_FS_SEL_16G, FS_SEL_2000_DPS); a reading beyond
      clips there, as the chip's does (the world's hard floor stops a falling vehicle within one 2 ms step:
      a touch-down at 0.5 m/s is 25 g).
    - ``baro_noise_pa`` 1.0: PX4's own simulated barometer (``sensor_baro_sim``: "1 Pa RMS noise");
      pressure from the ISA at ``home_altitude_m`` + height (lapse 0.0065 K/m, 15 °C at sea level).
    - ``home_altitude_m`` 488: PX4 SITL's default home altitude (``PX4_HOME_ALT``, Zurich).
    - ``mag_noise_gauss`` (0.02, 0.02, 0.03): PX4's ``sensor_mag_sim``. ``mag_field_ned_gauss``: the
      Earth's field at PX4 SITL's default home (47.40° N, 8.55° E; WMM: ~0.48 G, inclination ~63°,
      declination ~3°), rounded. The airframe parameters do not fuse it (motion capture gives yaw, as in a
      lab: ``EKF2_MAG_TYPE`` 5); it is sent so PX4's sensor pipeline sees a complete vehicle.
    """

    rate_hz: float = 250.0
    gyro_noise_density: float = 0.0003394
    gyro_random_walk: float = 3.8785e-5
    gyro_turn_on_bias_sigma: float = 0.0087
    accel_noise_density: float = 0.004
    accel_random_walk: float = 0.006
    accel_turn_on_bias_sigma: float = 0.196
    accel_range_mps2: float = 16.0 * 9.80665
    gyro_range_rps: float = math.radians(2000.0)
    baro_noise_pa: float = 1.0
    home_altitude_m: float = 488.0
    mag_noise_gauss: tuple[float, float, float] = (0.02, 0.02, 0.03)
    mag_field_ned_gauss: tuple[float, float, float] = (0.215, 0.011, 0.43)


class HilSensor(NamedTuple):
    """One ``HIL_SENSOR`` (PX4's units and frames): accelerometer m/s² and gyro rad/s body FRD, magnetometer
    gauss body FRD, absolute pressure hPa, pressure altitude m, temperature °C, at ``time_usec``."""

    time_usec: int
    acc_frd_mps2: tuple[float, float, float]
    gyro_frd_rps: tuple[float, float, float]
    mag_frd_gauss: tuple[float, float, float]
    abs_pressure_hpa: float
    pressure_alt_m: float
    temperature_c: float
    fields_updated: int = HIL_FIELDS_IMU_MAG_BARO


def isa_pressure_pa(altitude_m: float) -> float:
    """International Standard Atmosphere pressure below 11 km (Pa)."""
    return 101325.0 * (1.0 - 2.25577e-5 * altitude_m) ** 5.25588


class HilSensors:
    """Sensor readings of the true state with noise and biases (seeded: bit-reproducible)."""

    def __init__(self, config: HilSensorConfig = HilSensorConfig(), *, seed: int) -> None:
        self.config = config
        self._rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E45]))
        self.gyro_bias_rps = self._rng.normal(0.0, config.gyro_turn_on_bias_sigma, 3)
        self.accel_bias_mps2 = self._rng.normal(0.0, config.accel_turn_on_bias_sigma, 3)
        dt = 1.0 / config.rate_hz
        self._gyro_sigma = config.gyro_noise_density / math.sqrt(dt)
        self._acc_sigma = config.accel_noise_density / math.sqrt(dt)
        self._gyro_walk = config.gyro_random_walk * math.sqrt(dt)
        self._acc_walk = config.accel_random_walk * math.sqrt(dt)
        n, e, d = config.mag_field_ned_gauss
        self._mag_enu = np.array([e, n, -d])

    def sample(self, sim: QuadrotorSim, time_usec: int) -> HilSensor:
        """The sensors now: specific force and body rates from the last physics step, field and pressure
        from the attitude and height."""
        c, rng = self.config, self._rng
        self.gyro_bias_rps += rng.normal(0.0, self._gyro_walk, 3)
        self.accel_bias_mps2 += rng.normal(0.0, self._acc_walk, 3)
        truth = sim.truth
        acc = sim.specific_force_body_flu_mps2 + self.accel_bias_mps2 + rng.normal(0.0, self._acc_sigma, 3)
        gyro = truth.body_rates_rps + self.gyro_bias_rps + rng.normal(0.0, self._gyro_sigma, 3)
        acc = np.clip(acc, -c.accel_range_mps2, c.accel_range_mps2)
        gyro = np.clip(gyro, -c.gyro_range_rps, c.gyro_range_rps)
        mag = truth.world_from_body.T @ self._mag_enu + rng.normal(0.0, 1.0, 3) * np.array(c.mag_noise_gauss)
        altitude = c.home_altitude_m + float(truth.pos_enu_m[2])
        pressure = isa_pressure_pa(altitude) + rng.normal(0.0, c.baro_noise_pa)
        pressure_alt = (1.0 - (pressure / 101325.0) ** (1.0 / 5.25588)) / 2.25577e-5
        return HilSensor(time_usec=time_usec, acc_frd_mps2=_frd(acc), gyro_frd_rps=_frd(gyro), mag_frd_gauss=_frd(mag),
                         abs_pressure_hpa=pressure / 100.0, pressure_alt_m=pressure_alt,
                         temperature_c=15.0 - 0.0065 * altitude)


def _frd(v_flu: np.ndarray) -> tuple[float, float, float]:
    return float(v_flu[0]), -float(v_flu[1]), -float(v_flu[2])


# exchange(sensor) → PX4's motor outputs (0–1, PX4's motor order, at least 4) for the next sensor period, or
# None when no autopilot answers (not connected, or it stopped answering): the motors are then off.
Exchange = Callable[[HilSensor], "tuple[float, ...] | None"]


class AutopilotInTheLoop:
    """A :class:`QuadrotorSim` whose rotors an autopilot commands: :meth:`step` has the simulator's
    interface (one control period under ``setpoint``, the mocap measurement back), but the setpoint only
    becomes the truth's reference (the controller's setpoint goes to the autopilot, which flies it); the
    period is ``control_period_s · rate_hz`` sensor exchanges, each followed by the physics steps of one
    sensor period under the motor outputs it returned. Everything else is the simulator's (``truth``,
    ``crashed``, ``config``, ...). ``time_offset_us`` is added to the world's time in the sensors' stamps
    (PX4 wants a clock that never starts at 0).

    Counts: ``exchanges`` (sensor messages answered), ``unanswered`` (sent while no autopilot answered:
    motors off), ``airborne`` (answered while flying: off the ground, not crashed) and ``saturated`` (of those, how
    many had some motor output within 1 % of 0 or 1): the saturation figure of issue 24."""

    def __init__(self, sim: QuadrotorSim, exchange: Exchange, sensors: HilSensors, *,
                 time_offset_us: int = 1_000_000) -> None:
        self.sim = sim
        self.exchange = exchange
        self.sensors = sensors
        self.time_offset_us = time_offset_us
        cfg = sim.config
        self._n_sub = round(1.0 / (sensors.config.rate_hz * cfg.dt_s))
        self._n_sensor = round(cfg.control_period_s * sensors.config.rate_hz)
        if abs(self._n_sub * cfg.dt_s * sensors.config.rate_hz - 1.0) > 1e-9 or abs(
                self._n_sensor - cfg.control_period_s * sensors.config.rate_hz) > 1e-9:
            raise ValueError(f"sensor rate {sensors.config.rate_hz} Hz must divide the control period "
                             f"{cfg.control_period_s} s and be a whole number of physics steps of {cfg.dt_s} s")
        self.exchanges = 0
        self.unanswered = 0
        self.airborne = 0
        self.saturated = 0
        self.motors: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)

    def __getattr__(self, name: str):  # the simulator's interface for everything not overridden
        return getattr(self.sim, name)

    def step(self, setpoint: AttitudeSetpoint) -> StateMeasurement:
        sim = self.sim
        sim.reference_setpoint(setpoint)
        for _ in range(self._n_sensor):
            outputs = self.exchange(self.sensors.sample(sim, self.time_offset_us + round(sim.t_s * 1e6)))
            if outputs is None or len(outputs) < 4:
                self.unanswered += 1
                motors = (0.0, 0.0, 0.0, 0.0)
            else:
                self.exchanges += 1
                motors = tuple(float(outputs[i]) for i in range(4))
                if not (sim.truth.on_ground or sim.crashed or sim.diverged):
                    self.airborne += 1
                    self.saturated += any(u <= 0.01 or u >= 0.99 for u in motors)
            self.motors = motors
            sim.step_rotors(tuple(motors[PX4_MOTOR_OF_ROTOR[i]] for i in range(4)), self._n_sub)
        return sim._measurement()
