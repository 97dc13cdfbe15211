"""Control law and its mapping to a PX4 attitude setpoint."""
import math

import numpy as np
import pytest

from neso.control import ControlConfig, PositionController, attitude_from_force, nominal_acceleration
from neso.rotations import euler_zyx_from_world_from_body, world_from_body_zyx
from neso.types import Reference, VehicleModel
from tests.helpers import measurement


def test_hover_maps_to_level_attitude_and_thrust_mg():
    ctrl = PositionController(ControlConfig(vehicle=VehicleModel(mass_kg=1.3, hover_thrust_norm=0.42)))
    out = ctrl.step(measurement(pos=(0, 0, 1)), Reference(pos_enu_m=np.array([0, 0, 1.0])), np.zeros(3))
    sp = out.setpoint
    assert sp.roll_rad == pytest.approx(0, abs=1e-12) and sp.pitch_rad == pytest.approx(0, abs=1e-12)
    assert sp.thrust_n == pytest.approx(1.3 * 9.81)
    assert sp.thrust_norm == pytest.approx(0.42)
    assert np.allclose(out.applied.acc_cmd_enu_mps2, 0, atol=1e-12)


def test_disturbance_estimate_is_cancelled():
    ctrl = PositionController(ControlConfig(force_rate_limit_nps=1e6))
    out = ctrl.step(measurement(), Reference(pos_enu_m=np.array([0, 0, 1.0])), np.array([0, 0, 1.5]))
    assert out.setpoint.thrust_n == pytest.approx(1.0 * (9.81 - 1.5))


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.5])
def test_attitude_points_body_z_along_force(yaw):
    force = np.array([1.2, -0.8, 9.0])
    thrust, roll, pitch, yaw_out = attitude_from_force(force, yaw)
    z_body = world_from_body_zyx(roll, pitch, yaw_out)[:, 2]
    assert thrust == pytest.approx(np.linalg.norm(force))
    assert np.allclose(z_body * thrust, force)
    assert yaw_out == pytest.approx(yaw)


def test_positive_pitch_accelerates_towards_plus_x_in_enu():
    _, roll, pitch, _ = attitude_from_force(np.array([1.0, 0.0, 9.81]), 0.0)
    assert pitch > 0 and roll == pytest.approx(0, abs=1e-12)
    _, roll, pitch, _ = attitude_from_force(np.array([0.0, 1.0, 9.81]), 0.0)
    assert roll < 0  # +y (left) needs a negative roll about x forward


def test_force_increment_is_saturated_between_samples():
    cfg = ControlConfig(force_rate_limit_nps=10.0, dt_s=0.02)
    ctrl = PositionController(cfg)
    ref = Reference(pos_enu_m=np.array([0, 0, 5.0]))  # a 4 m step asks for a large force
    prev = ctrl.force_prev_enu_n.copy()
    for _ in range(5):
        out = ctrl.step(measurement(), ref, np.zeros(3))
        assert np.all(np.abs(out.force_enu_n - prev) <= 10.0 * 0.02 + 1e-12)
        prev = out.force_enu_n


def test_tilt_is_limited_and_nan_is_not_passed_on():
    cfg = ControlConfig(force_rate_limit_nps=1e6, max_tilt_rad=math.radians(20))
    ctrl = PositionController(cfg)
    out = ctrl.step(measurement(), Reference(pos_enu_m=np.array([50.0, 0, 1.0])), np.zeros(3))
    tilt = math.acos(world_from_body_zyx(out.setpoint.roll_rad, out.setpoint.pitch_rad, 0)[2, 2])
    assert tilt <= math.radians(20) + 1e-9
    out2 = ctrl.step(measurement(), Reference(pos_enu_m=np.array([0, 0, 1.0])), np.array([np.nan, 0, 0]))
    assert all(math.isfinite(v) for v in (out2.setpoint.roll_rad, out2.setpoint.pitch_rad, out2.setpoint.thrust_norm))


def test_nominal_acceleration_inverts_the_setpoint():
    ctrl = PositionController(ControlConfig(force_rate_limit_nps=1e6))
    out = ctrl.step(measurement(), Reference(pos_enu_m=np.array([0.1, -0.2, 1.3])), np.zeros(3))
    acc = nominal_acceleration(out.setpoint, ctrl.config.vehicle)
    assert np.allclose(acc, out.force_enu_n / 1.0 - np.array([0, 0, 9.81]), atol=1e-9)


def test_euler_round_trip():
    for r, p, y in [(0.1, -0.2, 0.3), (-0.5, 0.4, -2.0)]:
        assert np.allclose(euler_zyx_from_world_from_body(world_from_body_zyx(r, p, y)), (r, p, y))


def test_attitude_from_force_agrees_with_the_rotation_it_describes_over_random_forces():
    """The scalar mapping, checked against R_d rebuilt from its angles (tilts up to 60°, any heading)."""
    rng = np.random.default_rng(7)
    for _ in range(500):
        force = np.array([*rng.uniform(-8, 8, 2), rng.uniform(5, 20)])
        yaw = rng.uniform(-math.pi, math.pi)
        thrust, roll, pitch, yaw_out = attitude_from_force(force, yaw)
        np.testing.assert_allclose(world_from_body_zyx(roll, pitch, yaw_out)[:, 2] * thrust, force, atol=1e-12)
        assert math.remainder(yaw_out - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


def test_a_networks_slopes_on_the_state_are_the_gain_change_equivalent_gains_says():
    """Issue 32: the controller subtracts f̂, so f_N = f0 + s_p p_z + s_v v_z flies as k_p + s_p, k_d + s_v on
    e = z* − z (and a feed-forward s_p z* + s_v ż* that does not act on the error): the same command, sample for
    sample, over random states, references and slopes of both signs."""
    from dataclasses import replace

    from neso.learning import equivalent_gains

    rng = np.random.default_rng(7)
    base = ControlConfig(force_rate_limit_nps=1e6)
    for _ in range(50):
        s_p, s_v, f0 = rng.uniform(-4, 8), rng.uniform(-2, 3), rng.uniform(-1, 1)
        change = equivalent_gains({"pos_z_m": s_p, "vel_z_mps": s_v, "roll_rad": 0.3})
        kp, kd = change.gains(base.kp[2], base.kd[2])
        if kp <= 0 or kd <= 0:
            continue
        stiffer = replace(base, kp=(*base.kp[:2], kp), kd=(*base.kd[:2], kd))
        meas = measurement(pos=tuple(rng.uniform(-1, 1, 3) + (0, 0, 1)))
        meas = replace(meas, vel_enu_mps=rng.uniform(-1, 1, 3))
        ref = Reference(pos_enu_m=rng.uniform(-1, 1, 3) + (0, 0, 1), vel_enu_mps=rng.uniform(-1, 1, 3),
                        acc_enu_mps2=rng.uniform(-1, 1, 3))
        f_n = np.array([0.0, 0.0, f0 + s_p * meas.pos_enu_m[2] + s_v * meas.vel_enu_mps[2]])
        feed_forward = np.array([0.0, 0.0, f0 + s_p * ref.pos_enu_m[2] + s_v * ref.vel_enu_mps[2]])
        a = PositionController(base).step(meas, ref, f_n)
        b = PositionController(stiffer).step(meas, ref, feed_forward)
        assert a.setpoint.thrust_n == pytest.approx(b.setpoint.thrust_n, rel=1e-12)
        assert np.allclose(a.force_enu_n, b.force_enu_n, rtol=1e-12, atol=1e-12)
    assert equivalent_gains({"pos_z_m": 1.0}) is None  # without the velocity's slope there is no equivalence to say
