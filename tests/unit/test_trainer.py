"""The trainer's job, driven directly (no bus): real `.rrd` in, certified network in the registry, gate passed."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from flight.hotswap import gate
from neso.netfile import load_network
from neso.certificate import flight_budget
from neso.learning import RECIPES, recipe_bound
from neso.types import OMEGA_O_RPS
from services import registry
from services.trainer import Job, TrainerConfig, parse_job, train_job
from tests.helpers import BASE, EXAMPLE, flight_messages, write_recording

ACTIVE = {"id": "base", "path": BASE, "certified_phys": load_network(BASE).certified_lipschitz_physical()}
FLOWN = {"kp": 10.0, "kd": 6.0, "omega_o": OMEGA_O_RPS}  # as NetworkMsg.certificate reports the gains flown


@pytest.fixture
def rrd(tmp_path):
    path = tmp_path / "flight.rrd"
    write_recording(path, flight_messages(300, pathway="neural_eso"))
    return str(path)


def test_a_tdr_job_trains_from_the_active_network_certifies_predicts_stores_and_offers(tmp_path):
    """The example recording (a real 12 s landing flown by this system) retrained as TDR with the recipe of the
    active network: its inputs, the lag-consistent label, z-scores refitted, the certified bound for the gains flown."""
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    offered = []
    job = parse_job(1, {"recordings": [str(EXAMPLE)], "epochs": 3, "force_offer": True}, config)
    result = train_job(job, config, "uav1", ACTIVE, lambda p, pred: offered.append((p, pred)) or (True, "in shadow"),
                       FLOWN)
    assert offered == [(result.path, result.predicted)] and result.offer == (True, "in shadow")
    assert set(result.timings_s) == {"dataset", "train", "certify", "predict", "store", "offer"}
    net, base = load_network(result.path), load_network(BASE)
    recipe = RECIPES[base.metadata["recipe"]]
    assert net.feature_set is base.feature_set and net.layer_sizes == base.layer_sizes
    assert net.metadata["label"] == recipe.tdr_label == "applied" and net.metadata["recipe"] == recipe.name
    assert not np.array_equal(net.input_std, base.input_std), "z-scores refitted on the new data (recipe 'fit')"
    bound = recipe_bound(recipe, 10.0, 6.0, 15.0)  # the trainer's budget: fly well at those gains, 0.9 of it
    assert bound == pytest.approx(recipe.certified_fraction * flight_budget(
        10.0, 6.0, 15.0, exogenous_fraction=recipe.exogenous_fraction, exogenous_roles=("attitude",)))
    assert net.bound_units == "physical" and net.lipschitz_bound == pytest.approx(bound)
    assert net.metadata["mass_kg"] == "1.0"  # the vehicle the recordings flew: the file says what it was made for
    assert net.certified_lipschitz_state() <= net.lipschitz_bound * (1 + 1e-9)
    exo = tuple(i for i in range(net.n_inputs) if i not in net.state_columns)
    assert net.certified_lipschitz_columns(exo) <= recipe.exogenous_fraction * net.lipschitz_bound * (1 + 1e-9)
    assert "val loss" in result.summary() and "slopes ∂f_N/∂input" in result.summary()
    assert net.metadata["parent"] == "base" and net.metadata["vehicle"] == "uav1"
    assert json.loads(net.metadata["recordings"]) == [str(EXAMPLE)]
    assert gate(Path(result.path).read_bytes(), active=base, vehicle="uav1").passed
    (entry,) = registry.entries(config.registry)
    assert entry.id == result.network_id
    cert = entry.info["certificate"]
    assert cert["holds"] is True and cert["margin"] > 0 and cert["bound_ratio"] <= cert["max_bound_ratio"]
    assert cert["bound_cm"] > cert["pdeso_bound_cm"] > 0
    pred = entry.info["predicted"]
    assert pred == result.predicted and pred["seconds"] > 5
    assert pred["rmse_active_cm"] > 0 and pred["rmse_candidate_cm"] > 0
    # the counterfactual's change in mean square, on the recorded flight's own level (sim.counterfactual)
    assert pred["change_counterfactual"] == pytest.approx(pred["rmse_candidate_cm"] / pred["rmse_active_cm"] - 1)
    f, a, c = pred["rmse_recorded_cm"], pred["rmse_active_cm"], pred["rmse_candidate_cm"]
    assert f > 0 and pred["expected_active_cm"] == pytest.approx(f)
    assert pred["expected_candidate_cm"] == pytest.approx((f * f + c * c - a * a) ** 0.5)
    assert pred["change"] == pytest.approx(pred["expected_candidate_cm"] / f - 1)
    assert np.sign(pred["change"]) == np.sign(pred["change_counterfactual"])
    assert entry.row()["predicted_change"] == pred["change"] and entry.info["val_loss"] >= 0
    # what it learned, as gain: its mean slopes on p_z and v_z added to the flown gains, flown as PD+ESO alone
    slopes = net.learned["slopes"]
    assert entry.info["gain_change"] == {"dkp": slopes["pos_z_m"], "dkd": slopes["vel_z_mps"]}
    assert pred["gain_only"] == {"dkp": slopes["pos_z_m"], "dkd": slopes["vel_z_mps"],
                                 "kp": 10.0 + slopes["pos_z_m"], "kd": 6.0 + slopes["vel_z_mps"]}
    assert pred["rmse_pdeso_cm"] > 0 and pred["rmse_gain_only_cm"] > 0
    assert pred["change_vs_pdeso"] == pytest.approx(pred["expected_candidate_cm"] / pred["expected_pdeso_cm"] - 1)
    if pred["change_vs_pdeso"] < 0:  # the split adds up: its gain alone plus what it learned beyond that
        split = pred["split"]
        assert split["gain_cm"] + split["learned_cm"] == pytest.approx(split["total_cm"])
    text = result.summary()
    assert "as gain Δk_p" in text and "k_p 10 → " in text and "PD+ESO at the flown gains" in text
    assert "thrust lag" in text and "identified" in text


def test_a_candidate_predicted_to_fly_worse_is_stored_but_not_offered(tmp_path):
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    offered = []
    # a bound of 1e-4: the candidate is flat, it cannot do what the base network does
    job = parse_job(1, {"recordings": [str(EXAMPLE)], "epochs": 1, "lipschitz_bound": 1e-4}, config)
    result = train_job(job, config, "uav1", ACTIVE, lambda p, pred: offered.append(p) or (True, ""), FLOWN)
    if result.predicted["change"] >= 0:
        assert offered == [] and not result.offer[0] and "predicted to fly worse" in result.offer[1]
    else:
        assert offered == [result.path]
    assert len(registry.entries(config.registry)) == 1


def test_an_eso_job_trains_from_scratch_at_the_bound_asked(tmp_path):
    path = tmp_path / "eso.rrd"
    write_recording(path, flight_messages(300, pathway="eso"))
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    job = parse_job(1, {"recordings": [str(path)], "mode": "base", "epochs": 2, "lipschitz_bound": 0.5,
                        "offer": False}, config)
    result = train_job(job, config, "uav1", None)
    net = load_network(result.path)
    assert result.offer is None and net.lipschitz_bound == 0.5 and net.bound_units == "physical"
    assert net.metadata["parent"] == "" and net.metadata["label"] == "eso" and result.predicted == {}


def test_jobs_that_cannot_be_done_are_refused_with_the_reason(rrd, tmp_path):
    config = TrainerConfig(registry=str(tmp_path / "registry"), recordings_dir=str(tmp_path / "none"))
    for args, reason in (({}, "no recordings given"), ({"recordings": ["/nope.rrd"]}, "no such recording"),
                         ({"recordings": [rrd], "label": "x"}, "label"), ({"recordings": [rrd], "mode": "x"}, "mode"),
                         ({"recordings": [rrd], "epochs": 0}, "epochs"),
                         ({"recordings": [rrd], "lipschitz_bound": -1}, "lipschitz_bound"),
                         ({"recordings": [rrd], "bogus": 1}, "unknown")):
        with pytest.raises(ValueError, match=reason):
            parse_job(1, args, config)
    job = Job(1, (rrd,), "tdr", None, None, 2, True, 0)
    with pytest.raises(ValueError, match="no estimator has reported one"):
        train_job(job, config, "uav1", None)
    with pytest.raises(ValueError, match="vehicle 'uav1'"):
        train_job(job, config, "uav2", ACTIVE)


def test_a_candidate_that_learned_nothing_is_offered_only_by_force_and_a_diverged_one_never():
    from services.trainer import withheld_because

    better = {"change": -0.1, "change_vs_pdeso": -0.05}
    assert withheld_because(0.4, better, False) == ""
    assert "predicted to fly worse" in withheld_because(0.4, {"change": 0.05, "change_vs_pdeso": -0.01}, False)
    assert withheld_because(0.4, {"change": 0.05}, True) == ""
    assert "no better than PD+ESO" in withheld_because(0.4, {"change": -0.1, "change_vs_pdeso": 0.0}, False)
    assert withheld_because(0.4, {"change": -0.1, "change_vs_pdeso": 0.02}, True) == ""
    for vs_mean in (1.0, 1.7):
        why = withheld_because(vs_mean, better, False)
        assert why.startswith("not offered") and "predicting the mean" in why and "force_offer=true" in why
        assert withheld_because(vs_mean, better, True) == ""
    for force in (False, True):
        assert "training diverged" in withheld_because(float("nan"), better, force)


def test_a_candidate_better_than_the_active_network_but_not_than_pd_eso_is_not_offered(tmp_path, monkeypatch):
    """Issue 32: the trainer compared only with the active network, so in a still hover every candidate was offered
    although none beat PD+ESO. Its prediction flies PD+ESO at the flown gains too, and that is the bar."""
    import services.trainer as trainer

    flown = {"rmse_active_cm": 1.20, "rmse_candidate_cm": 1.05, "change": 1.05 / 1.20 - 1, "rmse_pdeso_cm": 1.00,
             "change_vs_pdeso": 0.05}
    monkeypatch.setattr(trainer, "predict_closed_loop", lambda *a, **k: dict(flown))
    config = TrainerConfig(registry=str(tmp_path / "registry"))
    offered = []
    job = parse_job(1, {"recordings": [str(EXAMPLE)], "epochs": 2}, config)
    result = train_job(job, config, "uav1", ACTIVE, lambda p, pred: offered.append(p) or (True, ""), FLOWN)
    assert result.info["val_loss_vs_mean"] < 1.0  # it learned something: only the PD+ESO bar withholds it
    assert offered == [] and not result.offer[0] and "no better than PD+ESO at the flown gains" in result.offer[1]
    forced = train_job(parse_job(2, {"recordings": [str(EXAMPLE)], "epochs": 2, "force_offer": True}, config), config,
                       "uav1", ACTIVE, lambda p, pred: offered.append(p) or (True, "in shadow"), FLOWN)
    assert forced.offer == (True, "in shadow") and offered == [forced.path]
