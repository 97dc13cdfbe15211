"""Speed- and thrust-dependent rotor aerodynamics (sim.rotor_aero) and the simulator's branch:
each effect checked for sign and size at a documented operating point against its source's
number."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from neso.types import GRAVITY_MPS2, AttitudeSetpoint
from sim.ground_effect import CheesemanBennettGroundEffect, ExponentialGroundEffect, NoGroundEffect
from sim.mocap import NOISELESS_MOCAP
from sim.quadrotor import InnerLoopParams, QuadrotorParams, QuadrotorSim, SimConfig
from sim.rotor_aero import (
    GROUND_EFFECT_WASHOUTS,
    ROTOR_DRAG_SCALINGS,
    TRANSLATIONAL_LIFT_MODELS,
    CheesemanBennettWashout,
    FaesslerTranslationalLift,
    RotorSpeedDrag,
    ThrustProportionalDrag,
    hover_induced_velocity_mps,
    make_rotor_aero,
    washed_out_ratio,
)
from sim.scenarios import make_scenario
from sim.turbulence import NO_TURBULENCE

PARAMS = QuadrotorParams(battery_sag_per_min=0.0)
CALM = SimConfig(params=PARAMS, ground_effect=NoGroundEffect(), turbulence=NO_TURBULENCE, mocap=NOISELESS_MOCAP)
F_HOVER = 0.25 * PARAMS.mass_kg * GRAVITY_MPS2


def test_hover_induced_velocity_is_momentum_theory():
    # sqrt(T / (2 rho A)), T = 1.05 * 9.81 / 4 N per rotor, A = pi 0.0635^2
    expected = math.sqrt(1.05 * 9.81 / 4 / (2 * 1.225 * math.pi * 0.0635**2))
    assert PARAMS.hover_induced_velocity_mps == pytest.approx(expected)
    assert PARAMS.hover_induced_velocity_mps == pytest.approx(9.11, abs=0.01)


@pytest.mark.parametrize("name", sorted(ROTOR_DRAG_SCALINGS))
def test_rotor_drag_scalings_are_one_at_hover(name):
    assert make_rotor_aero("rotor_drag", name).factor(F_HOVER, F_HOVER, F_HOVER, F_HOVER, F_HOVER) == pytest.approx(1.0)


def test_rotor_speed_drag_follows_rotor_speed_and_thrust_drag_follows_thrust():
    """H ~ omega (Mahony 2012, Svacha 2017, RotorPy): 21 % more thrust is 10 % more rotor speed,
    so 10 % more drag; drag ~ T (Kai et al. 2017): 21 % more."""
    f = 1.21 * F_HOVER
    assert RotorSpeedDrag().factor(f, f, f, f, F_HOVER) == pytest.approx(1.10)
    assert ThrustProportionalDrag().factor(f, f, f, f, F_HOVER) == pytest.approx(1.21)
    # unequal rotors: the mean of the square roots, below the thrust ratio
    assert RotorSpeedDrag().factor(0.0, 2 * F_HOVER, F_HOVER, F_HOVER, F_HOVER) == pytest.approx(
        0.25 * (math.sqrt(2.0) + 2.0))


def test_faessler_translational_lift_reproduces_the_identified_coefficient_and_scales_with_v_h():
    lift = FaesslerTranslationalLift()
    v_ref = hover_induced_velocity_mps(0.6, 0.0635)
    assert lift.k_h_per_m(v_ref) == pytest.approx(0.009)  # Faessler et al. 2018, Sec. VII-C
    assert lift.k_h_per_m(v_ref) * 5.0**2 == pytest.approx(0.225)  # at 5 m/s on their vehicle: 0.225 m/s^2
    ours = lift.k_h_per_m(PARAMS.hover_induced_velocity_mps)
    assert ours == pytest.approx(0.009 * (v_ref / PARAMS.hover_induced_velocity_mps) ** 2)
    assert 0.004 < ours < 0.006  # heavier disc loading: less lift per (m/s)^2
    assert make_rotor_aero("translational_lift", "none").k_h_per_m(9.0) == 0.0


def test_cheeseman_bennett_washout_reproduces_their_forward_flight_formula():
    """C&B 1955: T/T_inf = 1 / (1 - (R/4z)^2 / (1 + (V/v_i)^2)). At z = R: 16/15 in hover,
    32/31 at V = v_i."""
    r = 0.0635
    hover = CheesemanBennettGroundEffect().thrust_ratio(r, r, 0.18)
    assert hover == pytest.approx(16 / 15)
    w = CheesemanBennettWashout().weight(9.0**2, 9.0)
    assert w == pytest.approx(0.5)
    assert washed_out_ratio(hover, w) == pytest.approx(32 / 31)
    assert washed_out_ratio(hover, CheesemanBennettWashout().weight(0.0, 9.0)) == pytest.approx(hover)


@pytest.mark.parametrize("name", sorted(GROUND_EFFECT_WASHOUTS))
def test_washouts_are_one_at_rest_and_never_grow_with_speed(name):
    washout = make_rotor_aero("washout", name)
    weights = [washout.weight(v * v, 9.11) for v in np.linspace(0.0, 20.0, 50)]
    assert weights[0] == 1.0 and all(0.0 < w <= 1.0 for w in weights)
    assert np.all(np.diff(weights) <= 0.0)


def test_unknown_parts_are_refused_with_the_known_names():
    with pytest.raises(KeyError, match="rotor_speed"):
        make_rotor_aero("rotor_drag", "nope")
    with pytest.raises(KeyError, match="washout"):
        make_rotor_aero("nope", "none")
    assert set(TRANSLATIONAL_LIFT_MODELS) == {"none", "faessler"}


# ------------------------------------------------------------------- the parts in the simulator
def _pitch_forward(cfg: SimConfig, ticks: int = 40) -> QuadrotorSim:
    """Pitch 15 deg with the thrust that holds altitude: the vehicle speeds up along +x."""
    sim = QuadrotorSim(cfg, seed=0)
    pitch = math.radians(15.0)
    sp = AttitudeSetpoint(0.0, pitch, 0.0, PARAMS.hover_thrust_norm / math.cos(pitch), 0.0)
    for _ in range(ticks):
        sim.step(sp)
    return sim


def _branch_f(sim: QuadrotorSim, cfg: SimConfig) -> np.ndarray:
    twin = sim.branch(cfg)
    twin.step(AttitudeSetpoint(0.0, math.radians(15.0), 0.0, PARAMS.hover_thrust_norm / math.cos(math.radians(15.0)), 0.0))
    return twin.truth.disturbance_acc_enu_mps2


def test_translational_lift_in_the_sim_adds_k_h_v_bh_squared_along_body_z():
    sim = _pitch_forward(CALM)
    v = sim.truth.vel_enu_mps
    assert v[0] > 1.0
    with_lift = replace(CALM, translational_lift=FaesslerTranslationalLift())
    d = _branch_f(sim, with_lift) - _branch_f(sim, CALM)
    r = sim.truth.world_from_body
    v_body = r.T @ v
    k_h = FaesslerTranslationalLift().k_h_per_m(PARAMS.hover_induced_velocity_mps)
    expected = k_h * (v_body[0] ** 2 + v_body[1] ** 2) * r[:, 2]
    assert d[2] > 0.0
    np.testing.assert_allclose(d, expected, rtol=0.05, atol=1e-12)  # speed grows within the step


def test_rotor_drag_scaling_in_the_sim_changes_the_drag_by_the_rotor_speed_factor():
    sim = _pitch_forward(CALM)
    no_drag = replace(CALM, params=replace(PARAMS, drag_coeff_per_s=(0.0, 0.0, 0.0)))
    drag = _branch_f(sim, CALM) - _branch_f(sim, no_drag)
    scaled = _branch_f(sim, replace(CALM, rotor_drag=ThrustProportionalDrag())) - _branch_f(sim, no_drag)
    assert drag[0] < 0.0  # opposes the motion along +x
    # thrust 1/cos(15 deg) of hover: the drag grows by that factor (Kai et al.)
    np.testing.assert_allclose(scaled, drag / math.cos(math.radians(15.0)), rtol=0.03)


def test_washout_in_the_sim_weakens_the_ground_effect_by_the_cheeseman_bennett_weight():
    cfg = replace(CALM, ground_effect=ExponentialGroundEffect(), initial_pos_enu_m=(0.0, 0.0, 0.6))
    sim = _pitch_forward(cfg, ticks=35)
    washed = sim.branch(replace(cfg, ground_effect_washout=CheesemanBennettWashout()))
    plain = sim.branch(cfg)
    sp = AttitudeSetpoint(0.0, math.radians(15.0), 0.0, PARAMS.hover_thrust_norm / math.cos(math.radians(15.0)), 0.0)
    washed.step(sp)
    plain.step(sp)
    r_plain, r_washed = plain.truth.ground_effect_ratio, washed.truth.ground_effect_ratio
    v_body = plain.truth.world_from_body.T @ plain.truth.vel_enu_mps
    w = CheesemanBennettWashout().weight(v_body[0] ** 2 + v_body[1] ** 2, PARAMS.hover_induced_velocity_mps)
    assert 1.0 < r_washed < r_plain
    assert r_washed == pytest.approx(washed_out_ratio(r_plain, w), rel=2e-3)


def test_ground_effect_at_the_hub_ignores_tilt():
    cfg = replace(CALM, ground_effect=ExponentialGroundEffect(), initial_pos_enu_m=(0.0, 0.0, 0.3))
    sim = _pitch_forward(cfg, ticks=5)
    per_rotor, hub = sim.branch(cfg), sim.branch(replace(cfg, ground_effect_per_rotor=False))
    sp = AttitudeSetpoint(0.0, math.radians(15.0), 0.0, PARAMS.hover_thrust_norm, 0.0)
    per_rotor.step(sp)
    hub.step(sp)
    # (the ratio is taken at the start of the last 2 ms sub-step, the position at its end)
    assert hub.truth.ground_effect_ratio == pytest.approx(ExponentialGroundEffect().thrust_ratio(
        hub.truth.pos_enu_m[2], 0.0635, 0.18), rel=1e-4)
    # tilted, two rotors are lower and two higher; e^(-h/L) is convex, so the mean ratio is higher
    assert per_rotor.truth.ground_effect_ratio > hub.truth.ground_effect_ratio + 1e-4


def test_rotor_thrust_limits_clip_the_collective_and_lifting_them_does_not():
    cfg = replace(CALM, control_period_s=0.002, command_delay_s=0.0)
    step = AttitudeSetpoint(0.6, 0.0, 0.0, 0.95, 0.0)  # near full thrust and a hard roll: rotors clip
    clipped = QuadrotorSim(cfg, seed=0)
    free = QuadrotorSim(replace(cfg, inner_loop=InnerLoopParams(rotor_thrust_limits=False)), seed=0)
    lost = []
    for _ in range(40):
        clipped.step(step)
        free.step(step)
        lost.append(free.truth.thrust_n - clipped.truth.thrust_n)
    assert clipped.truth.thrust_n <= PARAMS.max_thrust_n + 1e-9
    assert max(lost) > 0.5  # clipping costs collective thrust


# ------------------------------------------------------------------------------------ branch
def test_branch_continues_bit_identically_and_leaves_the_original_alone():
    cfg = make_scenario("lemniscate_near_ground")
    sp = AttitudeSetpoint(0.05, -0.03, 0.0, cfg.params.hover_thrust_norm, 0.0)
    a, b = QuadrotorSim(cfg, seed=4), QuadrotorSim(cfg, seed=4)
    for k in range(60):
        if k % 3 == 0:
            twin = a.branch(cfg)
            ref = a.branch(cfg)
            for _ in range(2):
                ma, mb = twin.step(sp), ref.step(sp)
            assert np.array_equal(twin.truth.pos_enu_m, ref.truth.pos_enu_m)
            assert np.array_equal(ma.pos_enu_m, mb.pos_enu_m)
        m1, m2 = a.step(sp), b.step(sp)
    assert np.array_equal(a.truth.pos_enu_m, b.truth.pos_enu_m)
    assert np.array_equal(m1.pos_enu_m, m2.pos_enu_m) and np.array_equal(m1.vel_enu_mps, m2.vel_enu_mps)
    with pytest.raises(ValueError, match="timing"):
        a.branch(replace(cfg, dt_s=0.001))
