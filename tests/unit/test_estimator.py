"""Neural-ESO pathways: what each computes, bumpless switching, network swap continuity."""
import itertools

import numpy as np
import pytest

from neso.eso import EsoConfig
from neso.estimator import PATHWAYS, AppliedControl, NeuralESO, NeuralEsoConfig, NeuralObserver
from neso.eso import input_matrix, transition_matrix
from neso.types import OMEGA_O_RPS
from tests.helpers import measurement, random_network

DT = 0.02


class Plant:
    """Double integrator per axis with a height-dependent disturbance (a stand-in ground effect)."""

    def __init__(self):
        self.x = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
        self.phi, self.gam = transition_matrix(DT)[:2, :2], input_matrix(DT)[:2]

    def disturbance(self):
        return np.array([0.2, -0.1, 1.5 * np.exp(-self.x[0, 2] / 0.2) + 0.3])

    def step(self, acc):
        self.x = self.phi @ self.x + np.outer(self.gam, acc + self.disturbance())
        return measurement(pos=self.x[0], vel=self.x[1])


def run(estimator, steps, on_step=None, hold_z=0.5):
    plant = Plant()
    meas = measurement(pos=plant.x[0])
    estimator.reset(meas, 9.81)
    applied = AppliedControl(np.zeros(3), 9.81)
    out = []
    for k in range(steps):
        if on_step:
            on_step(k, estimator)
        est = estimator.update(meas, applied)
        # PD on the plant, cancelling the estimate
        acc = 4.0 * (np.array([0, 0, hold_z]) - plant.x[0]) - 3.0 * plant.x[1] - est.f_hat
        applied = AppliedControl(acc, 9.81 + acc[2])
        meas = plant.step(acc)
        out.append((est, plant.disturbance()))
    return out


def test_eso_pathway_converges_to_the_true_disturbance():
    out = run(NeuralESO(NeuralEsoConfig(pathway="eso")), 300)
    est, f = out[-1]
    assert np.allclose(est.f_hat, f, atol=1e-3)
    assert np.all(est.f_n == 0)


def test_neural_eso_estimates_only_the_residual_and_total_is_right():
    net = random_network(1, bound=0.5)
    out = run(NeuralESO(NeuralEsoConfig(pathway="neural_eso"), net), 300)
    est, f = out[-1]
    assert np.allclose(est.f_hat, f, atol=1e-3)
    assert est.f_n[2] == pytest.approx(float(net.predict(est.z)[0]))
    assert est.delta_f_hat[2] == pytest.approx(f[2] - est.f_n[2], abs=1e-3)
    assert est.f_n[0] == 0 and est.f_n[1] == 0  # the prior acts on z only


def test_nn_and_none_pathways():
    net = random_network(2, bound=0.5)
    est, _ = run(NeuralESO(NeuralEsoConfig(pathway="nn"), net), 50)[-1]
    assert est.f_hat[2] == pytest.approx(float(net.predict(est.z)[0]))
    est, _ = run(NeuralESO(NeuralEsoConfig(pathway="none"), net), 50)[-1]
    assert est.f_hat[2] == 0.0
    assert est.f_hat[0] != 0.0  # planar axes keep their ESO


@pytest.mark.parametrize("before,after", list(itertools.permutations(PATHWAYS, 2)))
def test_pathway_switch_is_bumpless(before, after):
    net = random_network(3, bound=1.0)
    switch_at = 150

    def on_step(k, est):
        if k == switch_at:
            est.set_pathway(after)

    out = run(NeuralESO(NeuralEsoConfig(pathway=before), net), 200, on_step)
    f_z = np.array([o[0].f_hat[2] for o in out])
    steps = np.abs(np.diff(f_z))
    typical = np.max(steps[switch_at - 20:switch_at - 1]) + 1e-9
    # the switch sample moves f̂ no more than the estimate moved by itself just before
    assert steps[switch_at - 1] <= 2 * typical + 1e-6, (steps[switch_at - 3:switch_at + 2], typical)
    assert out[switch_at][0].pathway == after
    assert out[switch_at - 1][0].pathway == before


def test_network_swap_keeps_total_estimate_continuous():
    old, new = random_network(4, bound=1.0), random_network(5, bound=1.0)
    swap_at = 150

    def on_step(k, est):
        if k == swap_at:
            est.set_network(new)

    out = run(NeuralESO(NeuralEsoConfig(pathway="neural_eso"), old), 200, on_step)
    f_n = np.array([o[0].f_n[2] for o in out])
    f_hat = np.array([o[0].f_hat[2] for o in out])
    assert abs(f_n[swap_at] - f_n[swap_at - 1]) > 0.05  # the prior itself jumps …
    assert abs(f_hat[swap_at] - f_hat[swap_at - 1]) < 0.01  # … the total does not: Δf̂ absorbs it
    assert out[-1][0].f_hat[2] == pytest.approx(out[-1][1][2], abs=1e-2)


def test_wrong_network_shape_and_pathway_are_refused():
    est = NeuralESO(NeuralEsoConfig())
    with pytest.raises(ValueError, match="outputs"):
        est.set_network(random_network(6, sizes=(5, 8, 2)))
    with pytest.raises(ValueError, match="pathway"):
        est.set_pathway("magic")


def test_neural_observer_has_no_online_correction():
    """With a network that is simply wrong, the ESO-based estimators converge, the neural observer does not."""
    net = random_network(7, bound=0.3)
    cfg = NeuralEsoConfig(eso=EsoConfig(omega_o_rps=OMEGA_O_RPS, dt_s=DT))
    est_nobs, f = run(NeuralObserver(cfg, net), 300)[-1]
    est_neso, f_neso = run(NeuralESO(cfg, net), 300)[-1]
    assert abs(est_neso.f_hat[2] - f_neso[2]) < 1e-3
    assert abs(est_nobs.f_hat[2] - f[2]) > 0.05
    assert est_nobs.f_hat[2] == pytest.approx(est_nobs.f_n[2])


def test_the_shipped_network_is_found_from_any_folder_and_a_users_own_path_is_kept(tmp_path, monkeypatch):
    from flight.estimator import DEFAULT_NETWORK, PROJECT_ROOT, shipped

    monkeypatch.chdir(tmp_path)
    assert shipped(DEFAULT_NETWORK) == str(PROJECT_ROOT / DEFAULT_NETWORK)
    assert shipped("networks/nope.safetensors") == "networks/nope.safetensors"  # the open says it is missing
    (tmp_path / "networks").mkdir()
    (tmp_path / DEFAULT_NETWORK).write_bytes(b"mine")
    assert shipped(DEFAULT_NETWORK) == DEFAULT_NETWORK  # a file where neso runs wins over the shipped one
