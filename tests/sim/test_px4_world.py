"""The world as PX4's simulator (sim.px4_hil): the per-rotor input path of the simulator, the sensors PX4
reads, and the airframe parameter file checked against the world's geometry. PX4 itself flies in tests/px4/."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from neso.types import GRAVITY_MPS2, AttitudeSetpoint
from sim.px4_hil import PX4_MOTOR_OF_ROTOR, AutopilotInTheLoop, HilSensorConfig, HilSensors, isa_pressure_pa
from sim.px4_sitl import load_params
from sim.quadrotor import QuadrotorParams, QuadrotorSim
from sim.scenarios import make_scenario
from sim.turbulence import NO_TURBULENCE


def calm_world(z_m: float = 2.0, seed: int = 1) -> QuadrotorSim:
    sim = QuadrotorSim(replace(make_scenario("nominal_landing"), turbulence=NO_TURBULENCE), seed=seed)
    sim.reset(pos_enu_m=(0.0, 0.0, z_m))
    return sim


def test_rotors_commanded_at_the_true_hover_thrust_hold_the_vehicle_out_of_ground_effect():
    sim = calm_world()
    u = sim.config.params.hover_thrust_norm
    for _ in range(500):  # 2 s
        sim.step_rotors((u, u, u, u), 2)
    truth = sim.truth
    assert abs(truth.pos_enu_m[2] - 2.0) < 0.01 and np.abs(truth.vel_enu_mps).max() < 0.02
    assert sim.rotor_thrusts_n == pytest.approx((0.25 * truth.thrust_n,) * 4, rel=1e-3)
    assert sim.specific_force_body_flu_mps2 == pytest.approx([0.0, 0.0, GRAVITY_MPS2], abs=0.05)


def test_each_rotor_follows_its_command_with_the_motor_lags_and_no_delay():
    sim = calm_world()
    p = sim.config.params
    sim.step_rotors((1.0, 1.0, 1.0, 1.0), 1)  # from hover thrust towards the maximum: spin-up lag
    f_max = 0.25 * p.max_thrust_n * (1.0 - p.battery_sag_per_min * sim.t_s / 60.0)
    hover = 0.25 * p.mass_kg * GRAVITY_MPS2 / 1.0013  # reset's hover at 2 m: the ground-effect ratio there
    expected = hover + (f_max - hover) * (1 - math.exp(-sim.config.dt_s / p.rotor_time_constant_up_s))
    assert sim.rotor_thrusts_n[0] == pytest.approx(expected, rel=2e-3)
    before = sim.rotor_thrusts_n[0]
    sim.step_rotors((0.0, 0.0, 0.0, 0.0), 1)  # spinning down is the slower lag
    assert sim.rotor_thrusts_n[0] == pytest.approx(before * math.exp(-sim.config.dt_s / p.rotor_time_constant_down_s))


def test_more_thrust_on_the_left_rotors_rolls_the_vehicle_right_side_down():
    sim = calm_world()
    u = sim.config.params.hover_thrust_norm
    for _ in range(10):
        sim.step_rotors((u + 0.05, u - 0.05, u - 0.05, u + 0.05), 2)  # rotors 0 (front left), 3 (rear left) up
    wx, wy, wz = sim.truth.body_rates_rps
    assert wx > 0.1 and abs(wy) < 1e-6 and abs(wz) < 1e-6  # FLU roll: the left side rises


def test_a_vehicle_on_its_legs_does_not_roll_until_the_rotors_moment_can_lift_a_leg():
    """The floor holds roll and pitch while |M| < (m g - T) a (a: hub offset along an axis); PX4 idling on the
    ground commands such moments, and without this the world let a landed vehicle roll through the floor."""
    def roll_after(u: float, steps: int) -> float:
        sim = calm_world(z_m=0.0)  # on the floor, motors off
        for _ in range(steps):  # left rotors (0 front left, 3 rear left) at u, right ones off
            sim.step_rotors((u, 0.0, 0.0, u), 2)
        assert not sim.crashed
        return sim.truth.body_rates_rps[0]

    # u 0.2: T 3.9 N, M 0.50 N·m below (9.81 - 3.9) · 0.127 = 0.75 N·m; u 0.7: M 1.75 above 0.37 N·m
    assert roll_after(0.2, 200) == 0.0  # 0.8 s
    assert roll_after(0.7, 10) > 0.5  # tips over its right legs within 40 ms


def test_a_bad_rotor_command_is_refused_and_the_last_one_held():
    sim = calm_world()
    u = sim.config.params.hover_thrust_norm
    sim.step_rotors((u, u, u, u), 5)
    sim.step_rotors((math.nan, u, u, u), 5)
    sim.step_rotors((u, u, u), 5)
    assert sim.rejected_setpoints == 2 and abs(sim.truth.vel_enu_mps[2]) < 0.01


def test_the_attitude_setpoint_path_comes_back_after_rotor_commands():
    sim = calm_world()
    sim.step_rotors((0.0,) * 4, 10)
    sim.step(AttitudeSetpoint(0.0, 0.0, 0.0, sim.config.params.hover_thrust_norm, 0.0))
    assert sim._rotor_cmd is None  # the built-in inner loop flies again


def test_the_airframe_file_puts_each_px4_motor_where_the_world_has_the_rotor_it_drives():
    """CA_ROTORi_PX/PY (body FRD) and the sign of CA_ROTORi_KM (+: counter-clockwise) of
    sim/px4/neso_quad.params against the world's rotor hubs and yaw signs, through PX4_MOTOR_OF_ROTOR."""
    params = {k: float(v) for k, v in load_params().items()}
    p = QuadrotorParams()
    a = p.arm_length_m / math.sqrt(2.0)
    # the world's rotors (sim/quadrotor.py): hub (x, y) body FLU, yaw moment sign (+: the body yaws left)
    world = {0: ((a, a), +1), 1: ((-a, -a), +1), 2: ((a, -a), -1), 3: ((-a, a), -1)}
    assert params["CA_ROTOR_COUNT"] == 4
    for rotor, ((x, y), yaw_sign) in world.items():
        m = PX4_MOTOR_OF_ROTOR[rotor]
        assert (params[f"CA_ROTOR{m}_PX"], -params[f"CA_ROTOR{m}_PY"]) == pytest.approx((x, y), abs=5e-4)
        # a counter-clockwise rotor (KM > 0) yaws the body clockwise seen from above: negative FLU yaw
        assert math.copysign(1.0, params[f"CA_ROTOR{m}_KM"]) == -yaw_sign
        assert abs(params[f"CA_ROTOR{m}_KM"]) == pytest.approx(p.yaw_moment_per_thrust_m)


def test_the_sensors_at_rest_read_gravity_upwards_in_frd_and_the_home_pressure():
    sim = calm_world(z_m=-1.0)  # on the ground
    sensors = HilSensors(seed=3)
    readings = []
    for k in range(250):
        sim.step_rotors((0.0,) * 4, 2)
        readings.append(sensors.sample(sim, 1_000_000 + 4000 * k))
    acc = np.array([r.acc_frd_mps2 for r in readings]).mean(0)
    gyro = np.array([r.gyro_frd_rps for r in readings]).mean(0)
    bias_frd = sensors.accel_bias_mps2 * np.array([1.0, -1.0, -1.0])
    assert acc == pytest.approx(np.array([0.0, 0.0, -GRAVITY_MPS2]) + bias_frd, abs=0.02)
    assert np.abs(gyro).max() < 0.05
    height = sim.config.params.contact_height_m
    c = HilSensorConfig()
    assert np.mean([r.abs_pressure_hpa for r in readings]) == pytest.approx(isa_pressure_pa(c.home_altitude_m + height) / 100,
                                                                           abs=0.002)
    assert np.mean([r.pressure_alt_m for r in readings]) == pytest.approx(c.home_altitude_m + height, abs=0.1)
    assert [r.time_usec for r in readings[:2]] == [1_000_000, 1_004_000]


def test_a_hard_touch_down_clips_the_accelerometer_at_its_range():
    sim = calm_world(z_m=0.09)  # 4 cm above the feet: touch-down at 0.89 m/s, under the world's 1 m/s crash speed
    sensors = HilSensors(seed=1)
    peak = 0.0
    for _ in range(200):
        sim.step_rotors((0.0,) * 4, 2)  # motors off: it falls and hits the floor
        peak = max(peak, np.abs(sensors.sample(sim, 0).acc_frd_mps2).max())
    assert not sim.crashed and peak == pytest.approx(HilSensorConfig().accel_range_mps2)
    assert sim.specific_force_body_flu_mps2[2] == pytest.approx(GRAVITY_MPS2, abs=0.01)  # at rest after it


def test_a_crashed_world_reads_gravity_not_its_impact():
    sim = calm_world(z_m=0.5)
    for _ in range(200):
        sim.step_rotors((0.0,) * 4, 2)  # falls at 2.8 m/s: a crash, the state freezes
    assert sim.crashed and sim.specific_force_body_flu_mps2 == pytest.approx(
        sim.truth.world_from_body.T @ np.array([0.0, 0.0, GRAVITY_MPS2]))


def test_the_autopilot_in_the_loop_drives_the_world_rotor_by_px4_motor_and_counts_what_it_gets():
    sim = calm_world()
    u = sim.config.params.hover_thrust_norm
    sent = []

    def autopilot(sensor):  # answers the first 10 exchanges with PX4's motor order, then stops answering
        sent.append(sensor.time_usec)
        if len(sent) > 10:
            return None
        motors = [u] * 16
        motors[2] = u + 0.05  # PX4 motor 3: front left
        return tuple(motors)
    world = AutopilotInTheLoop(sim, autopilot, HilSensors(seed=1))
    world.step(AttitudeSetpoint(0.1, 0.0, 0.0, 0.5, 0.0))  # 20 ms: 5 exchanges at 250 Hz
    assert world.exchanges == 5 and world.unanswered == 0 and world.airborne == 5 and world.saturated == 0
    assert sent == [1_000_000 + 4000 * k for k in range(5)]
    assert sim.rotor_thrusts_n[0] > sim.rotor_thrusts_n[1]  # world rotor 0 is PX4's motor 3
    assert sim.truth.body_rates_rps[0] > 0 and sim.truth.body_rates_rps[1] < 0  # left and front up
    assert sim._cmd[0] == 0.1  # the setpoint is only the truth's reference
    world.step(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, 0.0))
    world.step(AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, 0.0))
    assert world.exchanges == 10 and world.unanswered == 5 and world.motors == (0.0,) * 4
