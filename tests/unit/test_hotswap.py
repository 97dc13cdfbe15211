"""Network hot swap: the swap math, the candidate gate, the shadow error, the estimator's step object."""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest

from neso.estimator import AppliedControl, NeuralESO, NeuralEsoConfig
from neso.hotswap import ShadowError, gate
from neso.netfile import load_network, network_to_bytes, save_network
from neso.network import LipschitzMLP
from runtime.schema import StateMsg
from services.estimator import EstimatorConfig, EstimatorCore, NetworkChoice, load_flown_network
from tests.helpers import (BASE, REPO, candidate, measurement, nan_weights, random_network, with_meta,
                           with_stated_bound)



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
    assert v.findings["layers"] == "5→20→25→10→1" and float(v.findings["val_loss"]) == 0.05


@pytest.mark.parametrize("make, reason", [
    (lambda: network_to_bytes(candidate())[:-100], "truncated"),
    (lambda: nan_weights(network_to_bytes(candidate())), "non-finite"),
    (lambda: network_to_bytes(with_meta(random_network(3, sizes=(5, 16, 16, 1), bound=1.0), vehicle="uav1",
                                        val_loss=0.1)), "wrong layer shapes"),
    (lambda: network_to_bytes(candidate(vehicle="uav2")), "vehicle 'uav2'"),
    (lambda: network_to_bytes(with_meta(candidate(), val_loss="")), "no validation loss"),
])
def test_bad_candidates_are_refused_with_the_reason(make, reason):
    v = gate(make(), active=load_network(BASE), vehicle="uav1")
    assert not v.passed and reason in v.reason, v.reason


def test_a_certificate_over_its_bound_is_refused():
    net = candidate()
    over = LipschitzMLP(tuple(w * 1.1 for w in net.weights), net.biases, net.input_mean, net.input_std,
                        net.output_mean, net.output_std, 1e9, net.metadata)
    data = with_stated_bound(network_to_bytes(over), 1.0)
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
    return EstimatorCore(EstimatorConfig(network=BASE, network_dir=""), net, NetworkChoice(net, source, None))


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
    core = EstimatorCore(EstimatorConfig(network=BASE), net, choice)
    core.apply({"lipschitz_bound": 0.5})
    assert core.active_info["source"] == "file" and core.active_info["path"].endswith("base-L0.5.safetensors")
    core.apply({"lipschitz_bound": 0.7})
    assert core.active_info["source"] == "scaled" and core.active_info["path"] == BASE
    path = str(tmp_path / "cand.safetensors")
    save_network(path, candidate())
    core.on_state(state(0), 0.0)
    core.accept(core.check_offer(path), path)
    assert core.promote()[0]
    assert "fixed" in core.check({"lipschitz_bound": 0.3, "pathway": "neural_eso"})
