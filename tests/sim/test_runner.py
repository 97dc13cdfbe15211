"""The in-process runner, the certificate against a simulated flight, and the paper pipeline end to end."""
import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from neso.certificate import CertificateInputs, certify, max_certified_lipschitz
from neso.control import ControlConfig
from neso.eso import EsoConfig
from neso.estimator import NeuralEsoConfig
from neso.methods import METHODS, build_estimator
from neso.trajectories import Landing, Lemniscate
from neso.features import DEFAULT_FEATURE_SET, ThrustLag
from neso.types import OMEGA_O_RPS
from sim.experiments import training_pairs
from sim.flights import FlightTask, run_flight
from sim.runner import fly
from sim.scenarios import make_scenario

EST = NeuralEsoConfig(eso=EsoConfig(omega_o_rps=OMEGA_O_RPS))


def _landing(method, seed, networks=None):
    return run_flight(FlightTask("nominal_landing", method, networks or {}, seed, Landing(), EST, ControlConfig()))


def test_same_seed_same_flight_other_seed_other_flight():
    a, b, c = _landing("pd_eso", 3), _landing("pd_eso", 3), _landing("pd_eso", 4)
    assert np.array_equal(a.pos_true_m, b.pos_true_m)
    assert not np.array_equal(a.pos_true_m, c.pos_true_m)


def test_observer_removes_the_steady_state_error_pd_leaves():
    pd, eso = _landing("pd", 1), _landing("pd_eso", 1)
    late = pd.t_s > Landing().descent_end_s + 2
    assert np.mean(np.abs(pd.z_error_m[late])) > 0.03  # ground effect + 5 % heavier than modelled
    assert np.mean(np.abs(eso.z_error_m[late])) < 0.015


@pytest.fixture(scope="module")
def base_network():
    from neso.training import train_lipschitz_mlp

    logs = [_landing("pd_eso", 500 + i) for i in range(2)]
    z, y = training_pairs(logs, "eso", DEFAULT_FEATURE_SET, ThrustLag())
    return train_lipschitz_mlp(z, y, lipschitz_bound=1.0, epochs=30,
                               metadata={"feature_set": DEFAULT_FEATURE_SET}).network


@pytest.mark.parametrize("method", sorted(METHODS))
def test_every_method_flies_the_nominal_landing(method, base_network):
    log = _landing(method, 2, {"base": base_network, "acceleration": base_network, "tdr": base_network})
    assert not log.diverged
    assert np.max(np.abs(log.z_error_m[log.t_s > 6])) < 0.15


@pytest.mark.parametrize("method", ["tight", "lmi"])
def test_certified_setting_stays_inside_its_ultimate_bound(base_network, method):
    """Gains flown on z (k_p 10, k_d 6, ω_o 15) with a network scaled so its *physical* certificate is
    half the tight (or LMI) certificate's limit: the simulated error state E = [e, ė, x̃1, x̃2, f̃] must stay
    within every stated eventual bound that holds after the initial transient."""
    control = ControlConfig()
    inputs = CertificateInputs(kp=control.kp[2], kd=control.kd[2], omega_o=EST.eso.omega_o_rps, lipschitz=0.0)
    l_max = max_certified_lipschitz(inputs, method)
    l_phys = 0.5 * l_max
    net = base_network.scaled_to_bound(l_phys, "physical", all_inputs=True)  # Lemma 1 counts every input
    assert net.certified_lipschitz_physical() <= l_phys * (1 + 1e-9)
    certs = [c for c in (certify(replace(inputs, lipschitz=l_phys), m) for m in ("tight", "lmi")) if c.holds]
    assert method in [c.method for c in certs]

    estimator = build_estimator("neural_eso", EST, {"base": net})
    observer_states = []
    log = fly(sim_config=make_scenario("nominal_landing"), estimator=estimator, trajectory=Landing(), seed=5,
              control=control, on_tick=lambda k, t, est: observer_states.append(est.eso.state[:, 2].copy()))
    obs = np.array(observer_states[1:])  # state after tick k−1's update, aligned below
    e = log.pos_ref_m[:-1, 2] - log.pos_true_m[:-1, 2]
    x1_err = log.pos_true_m[:-1, 2] - obs[:, 0]
    f_tilde = log.f_true[:-1, 2] - log.f_hat[:-1, 2]
    vel_true = np.gradient(log.pos_true_m[:, 2], log.t_s)[:-1]
    vel_ref = np.gradient(log.pos_ref_m[:, 2], log.t_s)[:-1]
    x2_err = vel_true - obs[:, 1]
    E = np.column_stack((e, vel_ref - vel_true, x1_err, x2_err, f_tilde))
    norms = np.linalg.norm(E, axis=1)
    assert np.all(np.isfinite(norms))
    for cert in certs:
        assert np.max(norms[50:]) <= cert.ultimate_bound_sublevel
        print(f"L_N {l_phys:.3f}: max ‖E‖ after 1 s {np.max(norms[50:]):.3f} vs {cert.method}'s eventual bound "
              f"{cert.ultimate_bound_sublevel:.1f}")


@pytest.mark.parametrize("network", ["none", "default", "budget"])
@pytest.mark.parametrize("scenario,trajectory", [("nominal_landing", Landing()),
                                                 ("lemniscate_near_ground", Lemniscate(cycles=2))])
def test_the_flight_certificates_bound_holds_in_simulated_flights(network, scenario, trajectory, base_network):
    """The verdict the services fly by (neso.certificate.flight_certificate: every input in its role, the source's
    15 Hz velocity filter in the loop) states an eventual |e_z| bound in cm; the simulated flight — with the
    world's motion-capture noise and its filtered finite-difference velocity feeding the controller and the
    network — stays inside it once the start's transient is over (after 2 s): PD+ESO (no network), the shipped
    default network, and one at the whole budget the trainer may spend."""
    from neso.certificate import LoopPlant, NetworkSlopes, flight_budget, flight_certificate
    from neso.netfile import load_network
    from tests.helpers import REPO

    control = ControlConfig()
    plant = LoopPlant.of(control)
    state_only = base_network.within_block_bounds([(2, 3)], [1e-12])  # no attitude slope: the budget is all state
    nets = {"none": None, "default": load_network(f"{REPO}/networks/base.safetensors"),
            "budget": state_only.scaled_to_bound(flight_budget(10.0, 6.0, OMEGA_O_RPS, plant=plant), "physical")}
    net = nets[network]
    slopes = NetworkSlopes.of(net) if net is not None else NetworkSlopes(0.0)
    cert = flight_certificate(slopes, kp=control.kp[2], kd=control.kd[2], omega_o=OMEGA_O_RPS, plant=plant)
    assert cert.holds, cert.text()
    estimator = build_estimator("neural_eso" if net is not None else "pd_eso", EST, {"base": net} if net else {})
    log = fly(sim_config=make_scenario(scenario), estimator=estimator, trajectory=trajectory, seed=5, control=control)
    assert not log.diverged
    late = log.t_s > 2.0
    worst_cm = float(np.max(np.abs(log.z_error_m[late]))) * 100
    print(f"{network} on {scenario}: max |e_z| after 2 s {worst_cm:.2f} cm vs the certified {cert.bound_cm:.1f} cm "
          f"(PD+ESO {cert.pdeso_bound_cm:.1f})")
    assert worst_cm <= cert.bound_cm


@pytest.mark.slow  # ~40 s alone: the whole paper pipeline; in make test, not make test-fast
def test_paper_pipeline_cli_writes_the_documented_json(tmp_path):
    """The pipeline end to end through the CLI, with the tuned baseline at the gains the search states
    (tests/sim/test_tuning.py flies the search itself)."""
    from sim.tuning import TUNED_GAINS

    out = tmp_path / "paper.json"
    tuned = [f"--tuned={k}={g.kp:g},{g.kd:g},{g.omega_o_rps:g}" for k, g in TUNED_GAINS.items()]
    proc = subprocess.run(
        [sys.executable, "-m", "cli.main", "experiment", "paper", "--trials", "1", "--epochs", "3",
         "--workers", "2", "--json", str(out), "--plots", str(tmp_path / "plots"), *tuned],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    data = json.loads(out.read_text())
    assert set(data) == {"experiments", "seconds", "trials", "recipe", "recipes", "tuned_gains",
                         "tuned_gains_fly"} and data["trials"] == 1
    assert data["tuned_gains"] == {k: g.to_dict() for k, g in TUNED_GAINS.items()}
    assert data["recipe"] == "certified" and set(data["recipes"]) == {"certified", "paper"}
    assert data["recipes"]["certified"]["experiments"] == data["experiments"]
    for name, recipe in data["recipes"].items():
        exps = recipe["experiments"]
        assert set(exps) == {"nominal_landing", "ood_slope", "lipschitz_ablation", "lemniscate_near_ground",
                             "noise_free_nominal", "robustness"}
        assert set(exps["noise_free_nominal"]["methods"]) == {"pd_eso", "pd_eso_tuned", "neural_eso", "neural_eso_tuned"}
        assert exps["nominal_landing"]["metric"] == "steady_state_abs_z_error_cm"
        assert exps["lemniscate_near_ground"]["metric"] == "z_rmse_cm"
        flown = set(exps["lemniscate_near_ground"]["methods"])
        assert set(METHODS) | {"pd_eso_tuned", "neural_eso_tuned", "neural_eso_tdr_tuned"} <= flown
        assert flown - set(METHODS) <= {"pd_eso_tuned", "neural_eso_tuned", "neural_eso_tdr_tuned", "pd_eso_tdr_gain",
                                        "pd_eso_tdr_gain_tuned"}
        assert set(exps["nominal_landing"]["methods"]) >= {"pd_eso_tuned", "neural_eso_tuned"}
        landing, lemniscate = exps["robustness"]["kinds"]["landing"], exps["robustness"]["kinds"]["lemniscate"]
        assert set(landing) == {"pd_eso", "pd_eso_tuned", "neural_eso", "neural_eso_tuned"} and landing["pd_eso"]["why"] == []
        assert lemniscate["neural_eso_tdr_tuned"]["lemniscate_total"] == 1 and "why" in lemniscate["neural_eso_tdr_tuned"]
        details = recipe["details"]
        for method, gains in details["tdr_as_gain"].items():  # PD+ESO at the TDR network's slopes added to its gains
            flown_at = TUNED_GAINS["lemniscate"] if method.endswith("_tuned") else None
            net = details["networks"]["tdr_tuned" if flown_at else "tdr"]
            assert gains["kp"] == pytest.approx((flown_at.kp if flown_at else 10.0) + net["gain_change"]["dkp"])
            assert gains["kd"] == pytest.approx((flown_at.kd if flown_at else 6.0) + net["gain_change"]["dkd"])
        assert details["networks"]["tdr_tuned"]["gains"] == TUNED_GAINS["lemniscate"].to_dict()
        assert len(exps["lipschitz_ablation"]["nominal"]) == 4
        for exp in ("nominal_landing", "ood_slope", "lemniscate_near_ground"):
            for result in exps[exp]["methods"].values():
                assert set(result) == {"mean", "std", "trials", "diverged"}
                assert len(result["trials"]) == 1
    # PD+ESO at the tuned gains is the same flight whatever the recipe, and another flight than at the paper's
    a, b = (data["recipes"][r]["experiments"]["lemniscate_near_ground"]["methods"] for r in ("certified", "paper"))
    assert a["pd_eso_tuned"] == b["pd_eso_tuned"] and a["pd_eso_tuned"] != a["pd_eso"]
    assert set(data["recipes"]["paper"]["experiments"]["lipschitz_ablation"]["nominal"]) == {"0.2", "0.5", "1.0", "2.0"}
    assert data["recipes"]["certified"]["details"]["networks"]["base_x1"]["certificate_holds"]
    for recipe in data["recipes"].values():  # the verdict is the services' (neso.certificate.flight_certificate)
        for net in recipe["details"]["networks"].values():
            assert net["certificate_holds"] == net["certificate"]["holds"]
            assert net["certified_lipschitz_state"] <= net["certified_lipschitz_physical"] * (1 + 1e-12)
            assert net["certificate"]["lipschitz_phys"] == net["certified_lipschitz_state"]
    assert not data["recipes"]["paper"]["details"]["networks"]["base_x1"]["certificate_holds"]  # T_{k-1} in the loop
    assert len(list((tmp_path / "plots").glob("*.png"))) == 4
    assert "Experiment 1" in proc.stdout and "comparisons" in proc.stdout and "recipe paper" in proc.stdout
    assert "Tuned PD+ESO: gains given, not searched" in proc.stdout and "Robustness, lemniscate gains" in proc.stdout
    g = TUNED_GAINS["lemniscate"]
    assert f"pd_eso_tuned (k_p {g.kp:.3g}, k_d {g.kd:.3g}, ω_o {g.omega_o_rps:g})" in proc.stdout
