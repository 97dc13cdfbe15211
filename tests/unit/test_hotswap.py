"""Network hot swap: the swap math, the candidate gate, the shadow error, the estimator's step object."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from neso.estimator import AppliedControl, NeuralESO, NeuralEsoConfig
from flight.hotswap import Canary, CanaryConfig, ShadowError, gate
from neso.netfile import load_network, network_to_bytes, save_network
from neso.network import LipschitzMLP
from runtime.schema import ReferenceMsg, StateMsg
from flight.estimator import EstimatorConfig, EstimatorCore, NetworkChoice, load_flown_network
from neso.certificate import flight_budget, max_certified_state_lipschitz_verified
from neso.types import velocity_lag_s
from tests.helpers import (BASE, REPO, candidate, fixed_clock, measurement, nan_weights, random_network, widened,
                           with_header, with_meta)



# -- the swap ---------------------------------------------------------------------------------
def test_network_swap_between_two_ticks_keeps_the_total_estimate_continuous_to_1e_12():
    a, b = random_network(1, bound=2.0), random_network(2, bound=2.0)
    est = NeuralESO(NeuralEsoConfig(), a)
    est.reset(measurement(), 9.0)
    rng = np.random.default_rng(0)
    for k in range(200):
        meas = measurement(pos=(0, 0, 1 + 0.05 * math.sin(k / 7)), vel=(0, 0, 0.3 * math.cos(k / 7)), t_s=0.02 * k)
        applied = AppliedControl(np.array([0.0, 0.0, rng.normal(0, 0.3)]), 9.0 + rng.normal(0, 0.5))
        if k == 150:
            twin = copy.deepcopy(est)  # the same estimator, never swapped
            est.set_network(b)
            kept = twin.update(meas, applied)
            x3_before_swap = twin.eso.state[2].copy()
            out = est.update(meas, applied)
            assert abs(out.f_n[2] - kept.f_n[2]) > 1e-3, "the two networks really predict differently here"
            assert np.max(np.abs(out.f_hat - kept.f_hat)) <= 1e-12
            assert np.allclose(est.eso.state[2], x3_before_swap + (kept.f_n - out.f_n), atol=1e-12, rtol=0)  # x̂3 took the step
        else:
            est.update(meas, applied)
    assert est.network is b


# -- the gate ---------------------------------------------------------------------------------
def test_a_good_candidate_passes_with_its_findings():
    v = gate(network_to_bytes(candidate()), active=load_network(BASE), vehicle="uav1")
    assert v.passed, v.reason
    base = load_network(BASE)
    assert v.findings["layers"] == "→".join(map(str, base.layer_sizes)) and float(v.findings["val_loss"]) == 0.05
    assert v.findings["feature_set"] == base.feature_set.key


def _other_size_set() -> str:
    """A feature set whose size is not the shipped network's."""
    from neso.features import FEATURE_SETS

    n = load_network(BASE).n_inputs
    return next(key for key, fs in FEATURE_SETS.items() if fs.size != n)


@pytest.mark.parametrize("make, reason", [
    (lambda: network_to_bytes(candidate())[:-100], "truncated"),
    (lambda: nan_weights(network_to_bytes(candidate())), "non-finite"),
    (lambda: network_to_bytes(with_meta(random_network(3, sizes=(5, 16, 16, 1), bound=1.0), vehicle="uav1",
                                        val_loss=0.1)), "wrong layer shapes"),
    (lambda: with_header(network_to_bytes(candidate()), feature_set="telepathy@1"), "unknown feature set"),
    (lambda: with_header(network_to_bytes(candidate()), feature_set=_other_size_set()), "inputs refused"),
    (lambda: network_to_bytes(candidate(vehicle="uav2")), "vehicle 'uav2'"),
    (lambda: network_to_bytes(with_meta(candidate(), val_loss="")), "no validation loss"),
])
def test_bad_candidates_are_refused_with_the_reason(make, reason):
    v = gate(make(), active=load_network(BASE), vehicle="uav1")
    assert not v.passed and reason in v.reason, v.reason


def test_a_certificate_over_its_bound_is_refused():
    net = candidate()
    f = (1.1 * net.lipschitz_bound / net.certified_lipschitz_state()) ** (1 / net.n_layers)  # 10 % over its bound
    over = LipschitzMLP(tuple(w * f for w in net.weights), net.biases, net.input_mean, net.input_std,
                        net.output_mean, net.output_std, 1e9, net.metadata, net.bound_units)
    data = with_header(network_to_bytes(over), lipschitz_bound=repr(net.lipschitz_bound))
    v = gate(data, active=load_network(BASE), vehicle="uav1")
    assert not v.passed and "certificate" in v.reason and "exceeds" in v.reason, v.reason


def test_shadow_error_is_the_rms_over_its_window():
    s = ShadowError(window=3)
    assert s.rms() == -1.0
    for pred, fhat in ((1.0, 0.0), (0.0, 2.0), (3.0, 0.0), (1.0, 1.0)):
        s.add(pred, fhat)
    assert s.samples == 3 and math.isclose(s.rms(), math.sqrt((4 + 9 + 0) / 3))


# -- the estimator's step object --------------------------------------------------------------
def state(seq, z=0.3):
    return StateMsg(seq=seq, stamp_s=1.0, t_s=0.02 * (seq + 1), pos_enu_m=(0.0, 0.0, z + 0.01 * math.sin(seq / 5)),
                    vel_enu_mps=(0.0, 0.0, 0.05 * math.cos(seq / 5)), roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0,
                    source="sim")


@pytest.fixture
def core():
    net, source = load_flown_network(BASE)
    return EstimatorCore(EstimatorConfig(network=BASE, network_dir=""), net, NetworkChoice(net, source, None),
                         clock=fixed_clock)


def test_offer_shadow_promote_rollback(core, tmp_path):
    path = str(tmp_path / "cand.safetensors")
    save_network(path, candidate())
    for k in range(20):
        core.on_state(state(k), 0.0)
    verdict = core.check_offer(path)
    assert verdict.passed, verdict.reason
    core.accept(verdict, path)
    for k in range(20, 60):
        core.on_state(state(k), 0.0)
    msg = core.network_msg()
    assert msg.candidate["id"] == "cand-1" and msg.candidate["state"] == "shadow"
    assert msg.shadow_error_rms_mps2 > 0 and core.shadow.samples == 40
    assert msg.candidate["shadow_samples"] == 40 and msg.candidate["active_error_rms_mps2"] >= 0
    before = core.on_state(state(60), 0.0)[0]
    ok, _ = core.promote()
    assert ok
    after = core.on_state(state(61), 0.0)[0]
    assert after.network_id == "cand-1" and before.network_id != "cand-1"
    msg = core.network_msg()
    assert msg.active["id"] == "cand-1" and msg.candidate == {} and msg.previous["path"] == BASE
    assert core.rollback()[0]
    assert core.on_state(state(62), 0.0)[0].network_id == before.network_id
    assert not core.promote()[0], "nothing left to promote"


def test_refused_offers_leave_the_active_network_and_candidate_untouched(core, tmp_path):
    good = str(tmp_path / "good.safetensors")
    save_network(good, candidate())
    core.accept(core.check_offer(good), good)
    active = core.estimator.network
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(Path(good).read_bytes()[:50])
    for path in (str(bad), str(tmp_path / "missing.safetensors")):
        verdict = core.check_offer(path)
        assert not verdict.passed
    assert core.estimator.network is active and core.candidate[1]["id"] == "cand-1"


def test_an_l_n_change_shows_where_the_network_came_from_and_is_fixed_after_a_promote(tmp_path):
    net, source = load_flown_network(BASE)
    choice = NetworkChoice(net, source, str(REPO / "networks"))
    core = EstimatorCore(EstimatorConfig(network=BASE), net, choice, clock=fixed_clock)
    half = load_network(REPO / "networks" / "base-x0.5.safetensors").lipschitz_bound_physical()
    core.apply({"lipschitz_bound": half})
    assert core.active_info["source"] == "file" and core.active_info["path"].endswith("base-x0.5.safetensors")
    core.apply({"lipschitz_bound": 0.8 * net.lipschitz_bound_physical()})
    assert core.active_info["source"] == "scaled" and core.active_info["path"] == BASE
    core.on_state(state(0), 0.0)  # the change lands at the next sample
    # L_N is the network's physical bound on its state inputs (what the certificate's loop gain counts)
    assert core.estimator.network.certified_lipschitz_state() <= 0.8 * net.lipschitz_bound_physical() * (1 + 1e-9)
    path = str(tmp_path / "cand.safetensors")
    save_network(path, candidate())
    core.accept(core.check_offer(path), path)
    assert core.promote()[0]
    assert "fixed" in core.check({"lipschitz_bound": 0.3, "pathway": "neural_eso"})


@pytest.mark.parametrize("shown", ["{:.4g}", "{:.5g}"])  # just above, just below
def test_an_l_n_typed_as_shown_finds_the_network_trained_for_it_and_never_flies_more_than_asked(shown):
    net, source = load_flown_network(BASE)
    choice = NetworkChoice(net, source, str(REPO / "networks"))
    half = load_network(REPO / "networks" / "base-x0.5.safetensors").lipschitz_bound_physical()
    typed = float(shown.format(half))  # 0.746, 0.74599: as the dashboard and `neso params` print it
    assert typed != half
    flown, what = choice.network_for(typed)
    assert "base-x0.5.safetensors" in what
    assert flown.certified_lipschitz_state() <= typed * (1 + 1e-9)
    assert "scaled" in choice.network_for(half * 0.99)[1]  # 1 % off is another bound: the loaded one scaled


# -- the certificate, checked where the change is applied -------------------------------------
def test_an_l_n_whose_certificate_fails_is_refused_with_the_margin_unless_overridden(tmp_path):
    from runtime.params import ParamSet

    from flight.estimator import estimator_params

    net, source = load_flown_network(BASE)
    # the networks trained here stay well inside their bounds: one trained for an L_N above the stable frontier
    wide = widened(net, 1.4 * max_certified_state_lipschitz_verified(10.0, 6.0, 15.0, velocity_lag_s()))
    steep = widened(net, 1.2 * flight_budget(10.0, 6.0, 15.0))  # stable, but not certified to fly well
    save_network(tmp_path / "base.safetensors", net)
    save_network(tmp_path / "base-wide.safetensors", wide)
    save_network(tmp_path / "base-steep.safetensors", steep)
    core = EstimatorCore(EstimatorConfig(network=BASE), net, NetworkChoice(net, source, str(tmp_path)),
                         clock=fixed_clock)
    assert core.certificate().holds, core.certificate().text()
    double = wide.lipschitz_bound_physical()
    cert = core.certificate_of(core.choice.network_for(double)[0])
    assert not cert.holds and cert.margin < 0
    params = ParamSet(estimator_params(core.config, net.lipschitz_bound_physical()), check=core.check)
    ok, why, _ = params.request({"lipschitz_bound": double})
    assert not ok and "certificate FAILS" in why and f"margin {cert.margin:+.3g}" in why and "override" in why
    # stable, but its |e_z| bound more than twice PD+ESO's: refused too, with that reason
    steep_cert = core.certificate_of(core.choice.network_for(steep.lipschitz_bound_physical())[0])
    assert not steep_cert.holds and steep_cert.margin > 0 and steep_cert.stable
    ok, why, _ = params.request({"lipschitz_bound": steep.lipschitz_bound_physical()})
    assert not ok and "fly well" in why and "cm" in why
    assert params.take_pending() == {} and params.take_overrides() == []
    ok, why, _ = params.request({"lipschitz_bound": double, "override": True})
    assert ok and why == ""
    notes = params.take_overrides()
    assert len(notes) == 1 and "by override" in notes[0] and "certificate FAILS" in notes[0]
    core.apply(params.take_pending())
    core.on_state(state(0), 0.0)
    assert not core.certificate().holds and core.network_msg().certificate["holds"] is False


def test_the_certificate_follows_the_controller_gains():
    net, source = load_flown_network(BASE)
    core = EstimatorCore(EstimatorConfig(network=BASE), net, NetworkChoice(net, source, None), clock=fixed_clock)
    assert core.certificate().holds and core.set_gains(*core.gains_z) is None
    note = core.set_gains(core.gains_z[0], 0.5)  # a soft derivative gain shrinks what is certified
    assert note is not None and "FAILS" in note
    msg = core.network_msg()
    assert msg.certificate["kd"] == 0.5 and msg.certificate["holds"] is False


def test_an_uncertified_startup_network_is_not_flown_unless_allowed():
    from flight.estimator import startup_network

    gains = (10.0, 6.0)
    good, _ = load_flown_network(BASE)
    wide = widened(good, 1.4 * flight_budget(*gains, 15.0))
    net, (level, text) = startup_network(EstimatorConfig(network="wide"), wide, gains)
    assert net is None and level == "error" and "NOT flown" in text and "FAILS" in text
    net, (level, text) = startup_network(EstimatorConfig(network="wide", allow_uncertified=True), wide, gains)
    assert net is wide and level == "warning" and "OUTSIDE" in text
    assert startup_network(EstimatorConfig(), good, gains)[0] is good
    # the paper's L_N = 1 network, the one that limit-cycles at 2.24 Hz without noise (docs/method.md): 2.8 in its
    # state inputs, inside the state-only frontier, so it flew "certified"; its T_{k-1} and attitude inputs close the
    # loop through the controller's output (loop gain 0.80), and in that loop nothing is certified
    paper, _ = load_flown_network(str(REPO / "networks" / "paper" / "base-L1.safetensors"))
    net, (level, text) = startup_network(EstimatorConfig(), paper, gains)
    assert paper.certified_lipschitz_state() < max_certified_state_lipschitz_verified(*gains, 15.0)
    assert net is None and level == "error" and "loop gain" in text


def test_promoting_an_uncertified_or_predicted_worse_candidate_needs_force(core, tmp_path):
    path = str(tmp_path / "wide.safetensors")
    save_network(path, candidate(scale=3.0))
    core.on_state(state(0), 0.0)
    core.accept(core.check_offer(path), path)
    ok, why = core.promote()
    assert not ok and "certificate FAILS" in why and "force" in why
    good = str(tmp_path / "good.safetensors")
    save_network(good, candidate())
    core.accept(core.check_offer(good), good, {"rmse_active_cm": 1.0, "rmse_candidate_cm": 1.2, "change": 0.2})
    ok, why = core.promote()
    assert not ok and "predicted to fly worse" in why and "+20 %" in why
    ok, why = core.promote(force=True)
    assert ok and "by force" in why
    # better than the active network, no better than PD+ESO at the flown gains: not an improvement either
    core.accept(core.check_offer(good), good, {"rmse_active_cm": 1.3, "rmse_candidate_cm": 1.2, "change": -0.077,
                                               "rmse_pdeso_cm": 1.1, "change_vs_pdeso": 0.09})
    ok, why = core.promote()
    assert not ok and "no better than PD+ESO at the flown gains" in why and "PD+ESO at the flown gains 1.10 cm" in why
    ok, why = core.promote(force=True)
    assert ok and "by force" in why


# -- the canary --------------------------------------------------------------------------------
def test_the_canary_rolls_back_a_network_that_tracks_worse_on_the_same_segment():
    canary = Canary(CanaryConfig(window_samples=50, margin=0.1))
    rng = np.random.default_rng(0)
    for k in range(120):
        canary.observe("lemniscate", 1, 0.01 * math.sin(k / 5) + rng.normal(0, 1e-3))
    canary.arm()
    verdict = None
    for k in range(120):  # a new run of the same segment, twice the error at the same places
        verdict = verdict or canary.observe("lemniscate", 3, 0.02 * math.sin(k / 5) + rng.normal(0, 1e-3))
    assert verdict is not None and verdict.rollback and verdict.samples == 50 and verdict.change > 0.5
    assert not canary.armed and "rolled back" in verdict.text()


def test_the_canary_keeps_a_network_that_tracks_better_and_says_so():
    canary = Canary(CanaryConfig(window_samples=50, margin=0.1))
    for k in range(80):
        canary.observe("hover", 1, 0.01 * (-1) ** k)
    canary.arm()
    verdicts = [canary.observe("hover", 1, 0.008 * (-1) ** k) for k in range(60)]  # the same run goes on
    verdict = next(v for v in verdicts if v is not None)
    assert not verdict.rollback and verdict.change < 0 and "kept" in verdict.text()


def test_the_canary_does_not_judge_on_millimetres_of_noise():
    canary = Canary(CanaryConfig(window_samples=30, margin=0.1, min_rms_m=0.002))
    for k in range(40):
        canary.observe("hover", 1, 1e-4 * (-1) ** k)
    canary.arm()
    verdicts = [canary.observe("hover", 1, 1.5e-3 * (-1) ** k) for k in range(40)]  # 15 x worse, still 1.5 mm
    assert not next(v for v in verdicts if v is not None).rollback


def _reference(seq, z_ref, segment):
    return ReferenceMsg(seq=seq, stamp_s=1.0, t_s=0.02 * (seq + 1), pos_enu_m=(0.0, 0.0, z_ref), vel_enu_mps=(0.0, 0.0, 0.0),
                        acc_enu_mps2=(0.0, 0.0, 0.0), yaw_rad=0.0, segment=segment)


def test_the_estimator_rolls_back_by_itself_between_two_samples_and_says_why(tmp_path):
    net, source = load_flown_network(BASE)
    config = EstimatorConfig(network=BASE, canary=CanaryConfig(window_samples=40))
    core = EstimatorCore(config, net, NetworkChoice(net, source, None), clock=fixed_clock)
    path = str(tmp_path / "cand.safetensors")
    save_network(path, candidate())
    for k in range(100):  # 2 s of hover 1 mm off the reference
        core.on_state(state(k, z=0.3), 0.0)
        core.on_reference(_reference(k, 0.3 + 0.001 * math.sin(k / 5) - 0.01 * math.sin(k / 5), "hover"))
    core.accept(core.check_offer(path), path)
    assert core.promote()[0] and core.network_msg().canary["armed"]
    for k in range(100, 160):  # after the promotion the same hover is tracked three times worse
        if core.estimator.network is not None and core.network_id != "cand-1":
            break
        core.on_state(state(k, z=0.3), 0.0)
        core.on_reference(_reference(k, 0.3 + 0.001 * math.sin(k / 5) - 0.03 * math.sin(k / 5), "hover"))
    assert core.network_id == net.metadata["id"], "rolled back to the base network"
    level, text = core.events[-1]
    assert level == "warning" and "rolled back" in text and "hover" in text
    msg = core.network_msg()
    assert not msg.canary["armed"] and "rolled back" in msg.canary["last"] and msg.previous["id"] == "cand-1"
    before = core.on_state(state(k + 1, z=0.3), 0.0)[0]
    assert before.network_id == net.metadata["id"]


def test_the_canary_tripwire_rolls_back_a_growing_error_at_once():
    canary = Canary(CanaryConfig(window_samples=500, trip_samples=50, trip_factor=3.0))
    rng = np.random.default_rng(1)
    for _ in range(300):
        canary.observe("hover", 1, rng.normal(0, 0.005))
    canary.arm()
    verdicts = [canary.observe("hover", 1, 0.005 * 1.15 ** k * math.sin(k / 3)) for k in range(60)]
    first = next(k for k, v in enumerate(verdicts) if v is not None)
    verdict = verdicts[first]
    assert verdict.rollback and verdict.tripwire and first < 60 and "tripwire" in verdict.text()


def test_the_canary_keeps_an_equal_network_whose_window_differs_by_chance():
    """Equal networks, different gust realisations: a ratio above 1 + margin but inside the noise floor."""
    canary = Canary(CanaryConfig(window_samples=500, margin=0.1))
    rng = np.random.default_rng(4)
    from scipy.signal import lfilter

    slow = lfilter([0.05], [1.0, -0.95], rng.normal(0, 1, 2000))  # gust-like, 0.4 s correlation: windows differ
    for k in range(1000):
        canary.observe("hover", 1, 0.004 * slow[k])
    canary.arm()
    verdicts = [canary.observe("hover", 1, 0.0045 * slow[1000 + k]) for k in range(500)]
    decided = [v for v in verdicts if v is not None]
    assert len(decided) == 1 and verdicts[-1] is decided[0], "decided once, at the end of the window"
    verdict = decided[0]
    assert not verdict.tripwire and verdict.threshold > 1.1, verdict.text()
    assert verdict.rollback == (verdict.rms_after_m > verdict.rms_before_m * verdict.threshold)


def test_a_network_with_a_thrust_input_made_for_another_mass_is_not_flown_unless_allowed():
    """Issue 29: the paper's network (its T_{k-1} input in newtons, trained at 1 kg) flown on a 1.5 kg vehicle
    landed 5.81 cm off (~100× PD+ESO) and the estimator said "certificate holds". The file states its mass; the
    estimator refuses it at another mass, with the reason, unless allowed; the controller refuses a mass change
    under which the flown network is not certified (overridably)."""
    from flight.controller import ControllerConfig, ControllerCore
    from flight.estimator import startup_network
    from neso.certificate import LoopPlant, NetworkSlopes
    from neso.control import ControlConfig

    small = random_network(3, sizes=(5, 12, 8, 1), bound=0.01)
    thrust_net = type(small)(small.weights, small.biases, small.input_mean, small.input_std, small.output_mean,
                             small.output_std, small.lipschitz_bound, {"feature_set": "paper@1", "mass_kg": "1.0",
                                                                       "id": "paper-small"}, "physical")
    assert startup_network(EstimatorConfig(), thrust_net, (10.0, 6.0))[0] is thrust_net  # made for this vehicle
    net, (level, text) = startup_network(EstimatorConfig(mass_kg=1.5), thrust_net, (10.0, 6.0))
    assert net is None and level == "error" and "1 kg vehicle, flown on 1.5 kg" in text
    net, (level, _) = startup_network(EstimatorConfig(mass_kg=1.5, allow_uncertified=True), thrust_net, (10.0, 6.0))
    assert net is thrust_net and level == "warning"
    core = EstimatorCore(EstimatorConfig(), thrust_net, NetworkChoice(thrust_net, "x", None), clock=fixed_clock)
    assert core.set_gains(10.0, 6.0, 1.5) is not None and not core.certificate().holds  # the controller's broadcast
    ctl = ControllerCore(ControllerConfig(), clock=fixed_clock)
    ctl.network_certificate = core.certificate_of(thrust_net).to_dict()
    values = {"kp_xy": 6.0, "kd_xy": 4.5, "kp_z": 10.0, "kd_z": 6.0, "mass_kg": 1.5}
    refusal = ctl.check_gains(values)
    assert refusal is not None and refusal.overridable and "flown on 1.5 kg" in str(refusal)
    assert ctl.check_gains(dict(values, mass_kg=1.0)) is None
    assert NetworkSlopes.of(thrust_net).thrust_inputs and LoopPlant.of(ControlConfig()).mass_kg == 1.0
