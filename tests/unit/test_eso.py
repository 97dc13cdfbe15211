"""The observer: poles where claimed, zero steady-state error for a constant disturbance."""
import math

import numpy as np
import pytest

from neso.eso import EsoConfig, ExtendedStateObserver, error_dynamics, exact_gains, input_matrix, transition_matrix
from neso.types import LOOP_PERIOD_S, OMEGA_O_RPS


@pytest.mark.parametrize("omega", [5.0, OMEGA_O_RPS, 20.0, 40.0])
def test_exact_discretisation_places_triple_pole_at_exp_minus_omega_dt(omega):
    dt = 0.02
    poles = np.linalg.eigvals(error_dynamics(omega, dt, "exact"))
    # a triple pole is ill-conditioned numerically: compare the characteristic polynomial instead
    expected = np.poly([math.exp(-omega * dt)] * 3)
    assert np.allclose(np.poly(poles).real, expected, atol=1e-12)
    assert np.allclose(np.abs(poles), math.exp(-omega * dt), atol=1e-4)


def test_euler_discretisation_does_not_place_the_pole_exactly():
    poly = np.poly(np.linalg.eigvals(error_dynamics(20.0, 0.02, "euler"))).real
    assert not np.allclose(poly, np.poly([math.exp(-0.4)] * 3), atol=1e-3)


def _simulate_axis(observer, f_true, steps, dt, u=0.0):
    """Exact ZOH simulation of a double integrator with constant disturbance; returns final state."""
    x = np.zeros((2, 3))  # pos, vel per axis
    phi, gam = transition_matrix(dt)[:2, :2], input_matrix(dt)[:2]
    for _ in range(steps):
        x = phi @ x + np.outer(gam, u + f_true)
        observer.update(x[0], np.full(3, u))
    return x


@pytest.mark.parametrize("disc", ["exact", "euler"])
def test_constant_disturbance_is_estimated_with_zero_steady_state_error(disc):
    dt = 0.02
    obs = ExtendedStateObserver(EsoConfig(omega_o_rps=OMEGA_O_RPS, dt_s=dt, discretisation=disc))
    obs.reset(np.zeros(3))
    f_true = np.array([0.3, -1.2, 2.5])
    x = _simulate_axis(obs, f_true, steps=400, dt=dt, u=0.7)
    assert np.allclose(obs.extended, f_true, atol=1e-9)
    if disc == "exact":  # the exact form also matches the plant's sampled position and velocity
        assert np.allclose(obs.state[0], x[0], atol=1e-9)
        assert np.allclose(obs.state[1], x[1], atol=1e-9)


def test_error_decays_at_the_designed_rate():
    dt, omega = LOOP_PERIOD_S, OMEGA_O_RPS
    obs = ExtendedStateObserver(EsoConfig(omega_o_rps=omega, dt_s=dt))
    obs.reset(np.zeros(3))
    f_true = np.ones(3)
    errors = []
    x = np.zeros((2, 3))
    phi, gam = transition_matrix(dt)[:2, :2], input_matrix(dt)[:2]
    for _ in range(150):
        x = phi @ x + np.outer(gam, f_true)
        obs.update(x[0], np.zeros(3))
        errors.append(abs(obs.extended[2] - 1.0))
    # a triple pole at β decays like k² β^k, so errors at k1 < k2 compare as β^(k2−k1)·(k2/k1)²
    beta = math.exp(-omega * dt)
    k1, k2 = 30, 60
    measured = errors[k2] / errors[k1]
    predicted = beta ** (k2 - k1) * (k2 / k1) ** 2
    assert 0.3 * predicted < measured < 3 * predicted


def test_exact_gains_formula():
    g = exact_gains(20.0, 0.02)
    b = math.exp(-0.4)
    assert g[0] == pytest.approx(1 - b**3)
    assert g[2] == pytest.approx((1 - b) ** 3 / 0.0004)


def test_invalid_config_is_refused():
    with pytest.raises(ValueError):
        EsoConfig(omega_o_rps=-1)
    with pytest.raises(ValueError):
        EsoConfig(discretisation="tustin")
