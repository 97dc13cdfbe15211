"""The Experiment 3 audit (sim.aero_audit): the applied-thrust estimate against the simulator,
the predictability fit on known functions and on noise, and the audit on the lemniscate."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from neso.types import AttitudeSetpoint
from neso.features import ThrustLag, applied_thrust_series
from sim.aero_audit import EFFECTS, audit_effects, disturbance_predictability
from sim.experiments import PaperConfig
from sim.ground_effect import NoGroundEffect
from sim.mocap import NOISELESS_MOCAP
from sim.quadrotor import QuadrotorParams, QuadrotorSim, SimConfig
from sim.runner import FlightLog
from sim.turbulence import NO_TURBULENCE

CALM = SimConfig(params=QuadrotorParams(battery_sag_per_min=0.0), ground_effect=NoGroundEffect(),
                 turbulence=NO_TURBULENCE, mocap=NOISELESS_MOCAP)


def test_applied_thrust_estimate_matches_the_simulated_thrust_through_delay_and_lag():
    sim = QuadrotorSim(CALM, seed=0)
    cmds = np.array([9.81 * 1.05] * 5 + [12.0] * 10 + [8.0] * 10)  # nominal N = true N (pre ground effect)
    truth = []
    for c in cmds:
        sim.step(AttitudeSetpoint(0.0, 0.0, 0.0, c / 9.81 * 0.5, c))
        truth.append(sim.truth.thrust_n)
    # sample k (after step k) was driven by the commands up to cmds[k]: the estimator's "thrust before"
    lag = ThrustLag(CALM.inner_loop.thrust_time_constant_s, CALM.command_delay_s)
    est = applied_thrust_series(cmds, lag, 0.02)
    np.testing.assert_allclose(est, truth, rtol=1e-9)
    assert truth[6] < 12.0 and truth[-1] < 8.1  # it really lags


def _synthetic_log(rng, n, f_z):
    z = np.column_stack([rng.normal(size=n), rng.normal(size=n), 9.81 + rng.normal(size=n),
                         rng.normal(size=n) * 0.1, rng.normal(size=n) * 0.1])
    t = np.arange(n) * 0.02 + 3.0
    vel = np.column_stack([rng.normal(size=n), rng.normal(size=n), z[:, 1]])
    pos = np.column_stack([np.zeros(n), np.zeros(n), z[:, 0]])
    f = np.zeros((n, 3))
    f[:, 2] = f_z(z, vel)
    three = np.zeros((n, 3))
    att = np.column_stack([z[:, 3], z[:, 4], np.zeros(n)])
    return FlightLog(t_s=t, pos_true_m=pos, pos_meas_m=pos, vel_meas_mps=vel, att_meas_rad=att, pos_ref_m=pos,
                     f_hat=three, f_n=three, delta_f_hat=three, z=z, thrust_n=z[:, 2], thrust_prev_n=z[:, 2],
                     acc_cmd_mps2=three, f_true=f, vel_true_mps=vel, thrust_applied_true_n=z[:, 2])


def test_predictability_finds_a_function_of_the_inputs_and_not_noise():
    rng = np.random.default_rng(0)
    sets = {"state + v_h": ("p_z", "v_z", "roll", "pitch", "v_h")}
    exact = [_synthetic_log(rng, 400, lambda z, v: 0.3 * z[:, 0] - 2.0 * z[:, 4] + 0.5 * np.hypot(v[:, 0], v[:, 1]))
             for _ in range(3)]
    noise = [_synthetic_log(rng, 400, lambda z, v: rng.normal(size=len(z))) for _ in range(3)]
    fit = disturbance_predictability(exact, feature_sets=sets, mlp_epochs=30)["fits"][0]
    assert fit["linear"]["r2"] > 0.999 and fit["mlp"]["r2"] > 0.9
    fit = disturbance_predictability(noise, feature_sets=sets, mlp_epochs=30)["fits"][0]
    assert fit["linear"]["r2"] < 0.02 and fit["mlp"]["r2"] < 0.05


def test_audit_measures_the_ground_effect_and_a_candidate_on_the_lemniscate():
    effects = [e for e in EFFECTS if e.name.startswith(("ground effect (per rotor)", "translational lift"))]
    out = audit_effects(replace(PaperConfig(), trials=1, workers=1), effects=effects)
    ge, lift = out["effects"]
    # 0.25 m: 1 + 0.215 e^(-0.25/0.195) = 1.0596 of ~hover thrust, i.e. ~+0.58 m/s^2 (pd_eso holds height)
    assert ge["in_world"] and ge["delta_f_z_mps2"]["mean"] == pytest.approx(0.58, abs=0.05)
    # k_h 0.0051 1/m, air speed up to ~3 m/s (gusts included): a few hundredths of a m/s^2, upward
    assert not lift["in_world"] and 0.0 < lift["delta_f_z_mps2"]["mean"] < 0.03
    assert lift["delta_f_z_mps2"]["peak"] < 0.15


def test_applied_reference_removes_the_echo_of_the_command_through_delay_and_lag():
    """A world whose only mismatch with the controller's model is the command delay and the thrust
    lag (noisy mocap makes the command jitter): f_true_z is that jitter's echo; referenced to the
    applied thrust it all but vanishes."""
    from sim.aero_audit import applied_referenced_f_z
    from sim.flights import FlightTask, run_flight
    from sim.scenarios import make_scenario

    cfg = PaperConfig()
    base = make_scenario("lemniscate_near_ground")
    ideal = (("params", replace(base.params, mass_kg=1.0, drag_coeff_per_s=(0.0, 0.0, 0.0), battery_sag_per_min=0.0)),
             ("ground_effect", NoGroundEffect()), ("turbulence", NO_TURBULENCE),
             ("inner_loop", replace(base.inner_loop, rotor_thrust_limits=False)))
    log = run_flight(FlightTask("lemniscate_near_ground", "pd_eso", {}, 1, cfg.lemniscate, cfg.estimator_config(),
                                cfg.control, ideal))
    t_app = applied_thrust_series(log.thrust_prev_n, ThrustLag(base.inner_loop.thrust_time_constant_s,
                                                               base.command_delay_s), cfg.control.dt_s)
    f_applied = applied_referenced_f_z(log, t_app, nominal_mass_kg=1.0)
    k = log.t_s > cfg.lemniscate.cycle_start_s
    assert np.std(log.f_true[k, 2]) > 0.2
    assert np.std(f_applied[k]) < 0.1 * np.std(log.f_true[k, 2])
