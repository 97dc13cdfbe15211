"""The simulated world: physics, inner loop, delay, ground effect, slope, gusts, mocap, scenarios."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from neso.types import GRAVITY_MPS2, AttitudeSetpoint
from sim.ground_effect import (
    GROUND_EFFECT_MODELS,
    ExponentialGroundEffect,
    NoGroundEffect,
    make_ground_effect,
)
from sim.mocap import NOISELESS_MOCAP, MocapConfig
from sim.quadrotor import QuadrotorParams, QuadrotorSim, SimConfig
from sim.scenarios import SCENARIOS, make_scenario
from sim.terrain import FlatGround, SlopeTerrain
from sim.turbulence import NO_TURBULENCE, DrydenGusts, TurbulenceConfig, gust_sigma_mps

PARAMS = QuadrotorParams(battery_sag_per_min=0.0)
CLEAN = SimConfig(
    params=PARAMS,
    ground_effect=NoGroundEffect(),
    turbulence=NO_TURBULENCE,
    mocap=NOISELESS_MOCAP,
    initial_pos_enu_m=(0.0, 0.0, 1.0),
)
HOVER = AttitudeSetpoint(0.0, 0.0, 0.0, PARAMS.hover_thrust_norm, 0.0)


def _roll(sim: QuadrotorSim) -> float:
    r = sim.truth.world_from_body
    return math.atan2(r[2, 1], r[2, 2])


# ---------------------------------------------------------------- physics and truth != model
def test_true_hover_thrust_holds_position_within_1mm_for_5s():
    sim = QuadrotorSim(CLEAN, seed=0)
    assert PARAMS.hover_thrust_norm == pytest.approx(0.525)
    for _ in range(250):
        meas = sim.step(HOVER)
    assert sim.truth.t_s == pytest.approx(5.0)
    assert np.max(np.abs(sim.truth.pos_enu_m - [0.0, 0.0, 1.0])) < 1e-3
    assert np.max(np.abs(meas.pos_enu_m - [0.0, 0.0, 1.0])) < 1e-3


def test_believed_hover_thrust_sinks_and_disturbance_is_reported():
    sim = QuadrotorSim(CLEAN, seed=0)
    believed = AttitudeSetpoint(0.0, 0.0, 0.0, 0.5, 1.0 * GRAVITY_MPS2)
    for _ in range(50):
        sim.step(believed)
    truth = sim.truth
    assert truth.pos_enu_m[2] < 0.95  # sinks: true thrust 0.5 * 19.62 N < 1.05 kg * g
    # The nominal model predicts zero acceleration at thrust 0.5; the truth falls at
    # (0.5 * 19.62 / 1.05 - g) plus drag: f_z is that (negative) acceleration.
    expected = 0.5 * PARAMS.max_thrust_n / PARAMS.mass_kg - GRAVITY_MPS2
    drag = -PARAMS.drag_coeff_per_s[2] * truth.vel_enu_mps[2]
    assert truth.disturbance_acc_enu_mps2[2] == pytest.approx(expected + drag, abs=2e-3)


def test_attitude_step_is_first_order_like_with_30_to_70ms_time_constant():
    cfg = replace(CLEAN, control_period_s=0.002, command_delay_s=0.0)
    sim = QuadrotorSim(cfg, seed=0)
    step = AttitudeSetpoint(0.1, 0.0, 0.0, PARAMS.hover_thrust_norm, 0.0)
    t, roll = [], []
    for _ in range(200):
        sim.step(step)
        t.append(sim.truth.t_s)
        roll.append(_roll(sim))
    roll_a = np.array(roll)
    tau = t[int(np.argmax(roll_a >= 0.1 * (1 - math.exp(-1))))]
    assert 0.030 <= tau <= 0.070
    assert roll_a.max() < 0.1 * 1.05  # no large overshoot
    assert roll_a[-1] == pytest.approx(0.1, abs=1e-3)


def test_setpoint_acts_exactly_after_the_transport_delay():
    cfg = replace(CLEAN, control_period_s=0.002, command_delay_s=0.010)
    sim = QuadrotorSim(cfg, seed=0)
    step = AttitudeSetpoint(0.1, 0.0, 0.0, PARAMS.hover_thrust_norm, 0.0)
    sim.step(step)  # given at t = 0
    rates = [(sim.truth.t_s, sim.truth.body_rates_rps[0])]
    hold = AttitudeSetpoint(0.1, 0.0, 0.0, PARAMS.hover_thrust_norm, 0.0)
    for _ in range(10):
        sim.step(hold)
        rates.append((sim.truth.t_s, sim.truth.body_rates_rps[0]))
    for t, wx in rates:
        if t <= 0.010 + 1e-12:
            assert wx == 0.0, t
    assert rates[5][0] == pytest.approx(0.012) and rates[5][1] > 0.0


def test_thrust_norm_is_clamped_and_nan_setpoint_is_not_integrated():
    sim = QuadrotorSim(CLEAN, seed=0)
    for _ in range(5):
        sim.step(HOVER)
    before = sim.truth
    bad = [
        AttitudeSetpoint(float("nan"), 0.0, 0.0, 0.9, 0.0),
        AttitudeSetpoint(0.0, 0.0, 0.0, float("inf"), 0.0),
        AttitudeSetpoint(0.0, float("-inf"), 0.0, 0.5, 0.0),
    ]
    for sp in bad:
        sim.step(sp)
    after = sim.truth
    assert sim.rejected_setpoints == 3
    assert np.all(np.isfinite(after.pos_enu_m)) and not after.diverged
    assert np.max(np.abs(after.pos_enu_m - before.pos_enu_m)) < 1e-6  # held the hover command

    over, full = QuadrotorSim(CLEAN, seed=0), QuadrotorSim(CLEAN, seed=0)
    for _ in range(10):
        over.step(AttitudeSetpoint(0.0, 0.0, 0.0, 5.0, 0.0))
        full.step(AttitudeSetpoint(0.0, 0.0, 0.0, 1.0, 0.0))
    assert np.array_equal(over.truth.pos_enu_m, full.truth.pos_enu_m)
    assert full.truth.thrust_n <= PARAMS.max_thrust_n + 1e-9


def test_ground_is_a_hard_floor_and_hard_impact_is_a_crash():
    sim = QuadrotorSim(CLEAN, seed=0)
    cut = AttitudeSetpoint(0.0, 0.0, 0.0, 0.0, 0.0)
    for _ in range(100):
        meas = sim.step(cut)
    truth = sim.truth
    assert truth.pos_enu_m[2] == pytest.approx(PARAMS.contact_height_m)
    assert truth.on_ground and truth.crashed  # falls from 1 m: > 1 m/s at impact
    assert meas.pos_enu_m[2] >= PARAMS.contact_height_m - 1e-9

    gentle = QuadrotorSim(replace(CLEAN, initial_pos_enu_m=(0.0, 0.0, 0.0)), seed=0)
    assert gentle.truth.on_ground and gentle.truth.thrust_n == 0.0
    for _ in range(25):
        gentle.step(AttitudeSetpoint(0.0, 0.0, 0.0, 0.3, 0.0))
    assert gentle.truth.pos_enu_m[2] == pytest.approx(PARAMS.contact_height_m)
    assert not gentle.truth.crashed
    for _ in range(50):
        gentle.step(AttitudeSetpoint(0.0, 0.0, 0.0, 0.6, 0.0))
    assert gentle.truth.pos_enu_m[2] > 0.1 and not gentle.truth.on_ground


def test_divergence_is_flagged_and_integration_stops():
    sim = QuadrotorSim(CLEAN, seed=0)
    full = AttitudeSetpoint(0.0, 0.0, 0.0, 1.0, 0.0)
    for _ in range(400):
        sim.step(full)
    truth = sim.truth
    assert truth.diverged
    assert np.linalg.norm(truth.pos_enu_m) < 51.0
    assert truth.t_s == pytest.approx(8.0)


def test_battery_sag_reduces_thrust_at_fixed_command():
    cfg = replace(CLEAN, params=QuadrotorParams(battery_sag_per_min=0.02))
    sim = QuadrotorSim(cfg, seed=0)
    for _ in range(150):
        sim.step(AttitudeSetpoint(0.0, 0.0, 0.0, cfg.params.hover_thrust_norm, 0.0))
    assert sim.truth.battery_factor == pytest.approx(1.0 - 0.02 * 3.0 / 60.0)
    assert sim.truth.pos_enu_m[2] < 1.0 - 0.01


# ---------------------------------------------------------------- ground effect and terrain
def test_exponential_ground_effect_matches_formula():
    ge = ExponentialGroundEffect()
    for h in (0.1, 0.5):
        assert ge.thrust_ratio(h, 0.0635, 0.18) == pytest.approx(1.0 + 0.215 * math.exp(-h / 0.195))
    assert ge.thrust_ratio(0.1, 0.0635, 0.18) == pytest.approx(1.1288, abs=1e-4)
    assert ge.thrust_ratio(3.0, 0.0635, 0.18) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("name", sorted(GROUND_EFFECT_MODELS))
def test_ground_effect_contract(name):
    ge = make_ground_effect(name)
    r, arm = 0.0635, 0.18
    heights = np.concatenate([[-0.05, 0.0, 0.01], np.linspace(0.02, 5.0, 300)])
    ratios = [ge.thrust_ratio(float(h), r, arm) for h in heights]
    assert all(math.isfinite(x) and x >= 1.0 for x in ratios)
    assert ge.thrust_ratio(5.0, r, arm) == pytest.approx(1.0, abs=2e-3)
    assert np.all(np.diff(ratios[2:]) <= 1e-12)  # non-increasing with height


def test_sanchez_cuevas_exceeds_cheeseman_bennett_near_ground():
    sc, cb = make_ground_effect("sanchez_cuevas"), make_ground_effect("cheeseman_bennett")
    assert sc.thrust_ratio(0.1, 0.0635, 0.18) > cb.thrust_ratio(0.1, 0.0635, 0.18) > 1.0


def test_slope_distances():
    slope = SlopeTerrain(slope_deg=30.0, edge_offset_m=0.1)
    assert slope.height_m(0.0, 0.0) == 0.0
    assert slope.height_m(0.3, 0.0) == pytest.approx(math.tan(math.radians(30.0)) * 0.2)
    assert slope.distance_m(-0.5, 0.0, 0.2) == pytest.approx(0.2)  # over the flat floor
    # over the ramp: perpendicular distance to the plane
    x, z = 0.3, 0.3
    expected = (z - math.tan(math.radians(30.0)) * 0.2) * math.cos(math.radians(30.0))
    assert slope.distance_m(x, 0.0, z) == pytest.approx(expected)
    assert FlatGround().distance_m(1.0, 2.0, 0.4) == 0.4


def test_slope_changes_total_ratio_and_adds_a_torque_away_from_the_slope():
    """Sign convention: the ramp rises along +x beside the landing point. The two rotors on the
    +x side are closer to a surface and gain thrust, lifting that side: a NEGATIVE moment about
    body y (FLU), which tilts the thrust vector towards -x, i.e. away from the slope."""
    base = replace(CLEAN, ground_effect=ExponentialGroundEffect(), initial_pos_enu_m=(0.0, 0.0, 0.1),
                   control_period_s=0.002, command_delay_s=0.0)
    flat = QuadrotorSim(base, seed=0)
    sloped = QuadrotorSim(replace(base, terrain=SlopeTerrain()), seed=0)
    sp = AttitudeSetpoint(0.0, 0.0, 0.0, PARAMS.hover_thrust_norm, 0.0)
    flat.step(sp)
    sloped.step(sp)
    assert sloped.truth.ground_effect_ratio > flat.truth.ground_effect_ratio > 1.0
    assert flat.truth.body_rates_rps[1] == pytest.approx(0.0, abs=1e-12)
    assert sloped.truth.body_rates_rps[1] < 0.0  # pitch moment is negative
    # before the inner loop has corrected it, the thrust vector tilts towards -x
    for _ in range(5):
        sloped.step(sp)
    assert sloped.truth.world_from_body[0, 2] < 0.0


# ---------------------------------------------------------------- turbulence
def _gust_std(dt: float, sigma0: float, seconds: float = 400.0, seed: int = 1) -> np.ndarray:
    cfg = TurbulenceConfig(sigma0_mps=sigma0, k_speed=0.0)
    gusts = DrydenGusts(cfg, dt, np.random.default_rng(seed))
    samples = np.array([gusts.step(1.0, 0.0) for _ in range(int(seconds / dt))])
    return samples.std(axis=0)


def test_gust_variance_does_not_depend_on_dt():
    s1 = _gust_std(0.001, 0.3)
    s4 = _gust_std(0.004, 0.3)
    assert np.all(np.abs(s1 / s4 - 1.0) < 0.10)
    assert np.all(np.abs(s1 / 0.3 - 1.0) < 0.10)


def test_gusts_are_stronger_near_the_ground_at_speed():
    cfg = TurbulenceConfig(sigma0_mps=0.02, k_speed=1.0, h0_m=0.2)
    assert gust_sigma_mps(cfg, 0.1, 1.5) > 10 * gust_sigma_mps(cfg, 0.1, 0.0)
    assert gust_sigma_mps(cfg, 0.1, 1.5) > 5 * gust_sigma_mps(cfg, 2.0, 1.5)

    def std_at(h, speed):
        g = DrydenGusts(cfg, 0.002, np.random.default_rng(3))
        return np.array([g.step(h, speed) for _ in range(50_000)]).std()

    assert std_at(0.1, 1.5) > 5 * std_at(1.5, 1.5)
    assert std_at(0.1, 1.5) > 5 * std_at(0.1, 0.0)


# ---------------------------------------------------------------- mocap
def test_mocap_noise_latency_and_rate():
    cfg = replace(CLEAN, mocap=MocapConfig())
    sim = QuadrotorSim(cfg, seed=5)
    meas = [sim.step(HOVER) for _ in range(400)]
    pos = np.array([m.pos_enu_m for m in meas])
    assert np.allclose(pos.std(axis=0), 1e-3, rtol=0.2)
    rolls = np.array([m.roll_rad for m in meas])
    assert rolls.std() == pytest.approx(math.radians(0.1), rel=0.2)
    # latency: the sample handed over at t describes t - 10 ms (100 Hz samples)
    assert [round(m.t_s, 6) for m in meas[:3]] == [0.01, 0.03, 0.05]
    vel = np.array([m.vel_enu_mps for m in meas[20:]])
    assert np.all(vel.std(axis=0) < 0.2) and np.all(vel.std(axis=0) > 0.01)


def test_mocap_velocity_tracks_motion():
    sim = QuadrotorSim(replace(CLEAN, mocap=NOISELESS_MOCAP), seed=0)
    up = AttitudeSetpoint(0.0, 0.0, 0.0, 0.6, 0.0)
    for _ in range(50):
        meas = sim.step(up)
    assert meas.vel_enu_mps[2] == pytest.approx(sim.truth.vel_enu_mps[2], rel=0.1)


# ---------------------------------------------------------------- determinism and scenarios
def _trajectory(seed: int, name: str = "lemniscate_near_ground") -> np.ndarray:
    cfg = make_scenario(name)
    sim = QuadrotorSim(cfg, seed=seed)
    out = []
    for k in range(100):
        sp = AttitudeSetpoint(0.05 * math.sin(0.1 * k), 0.05 * math.cos(0.1 * k), 0.0,
                              cfg.params.hover_thrust_norm, 0.0)
        m = sim.step(sp)
        out.append(np.concatenate([m.pos_enu_m, m.vel_enu_mps, sim.truth.pos_enu_m]))
    return np.array(out)


def test_same_seed_is_bit_identical_and_different_seed_differs():
    a, b, c = _trajectory(7), _trajectory(7), _trajectory(8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_each_scenario_constructs_and_runs_1s(name):
    cfg = make_scenario(name)
    sim = QuadrotorSim(cfg, seed=0)
    sp = AttitudeSetpoint(0.0, 0.0, 0.0, cfg.params.hover_thrust_norm, 0.0)
    for _ in range(50):
        meas = sim.step(sp)
    truth = sim.truth
    assert truth.t_s == pytest.approx(1.0)
    assert np.all(np.isfinite(meas.pos_enu_m)) and not truth.diverged and not truth.crashed
    assert cfg.name == name and cfg.reference_height_m > 0.0


def test_reset_hovers_in_equilibrium_inside_ground_effect():
    cfg = replace(CLEAN, ground_effect=ExponentialGroundEffect(), initial_pos_enu_m=(0.0, 0.0, 0.3))
    sim = QuadrotorSim(cfg, seed=0)
    ratio = 1.0 + 0.215 * math.exp(-0.3 / 0.195)
    hover = AttitudeSetpoint(0.0, 0.0, 0.0, PARAMS.hover_thrust_norm / ratio, 0.0)
    for _ in range(50):
        sim.step(hover)
    assert sim.truth.ground_effect_ratio == pytest.approx(ratio)
    assert abs(sim.truth.pos_enu_m[2] - 0.3) < 1e-6


def test_make_scenario_overrides_and_unknown_names():
    cfg = make_scenario("nominal_landing", initial_pos_enu_m=(0.0, 0.0, 0.5))
    assert cfg.initial_pos_enu_m == (0.0, 0.0, 0.5)
    assert make_scenario("lemniscate_near_ground").reference_height_m == 0.25
    with pytest.raises(KeyError):
        make_scenario("nope")
    with pytest.raises(KeyError):
        make_ground_effect("nope")


def test_timing_must_be_integer_multiples_of_dt():
    with pytest.raises(ValueError):
        QuadrotorSim(replace(CLEAN, control_period_s=0.021), seed=0)
