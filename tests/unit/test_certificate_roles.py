"""The role certificate (neso/certificate/roles.py): the state inputs in the loop gain, the others in the
constant. Exact frontier (1/‖G‖_∞), never below Lemma 1's LMI, every verdict re-verified in numpy, and the
dissipation inequality it claims checked at random states against the worst network slope."""
from __future__ import annotations

import math

import numpy as np
import pytest

from neso.certificate import (CertificateInputs, RoleInputs, certify_lmi, certify_roles, flight_budget,
                              flight_certificate, max_certified_lipschitz_best, max_certified_state_lipschitz,
                              max_certified_state_lipschitz_verified, verify_roles)
from neso.certificate.roles import hinf_norm, role_matrices
from tests.helpers import random_network

GAINS = [(10.0, 6.0, 15.0), (4.0, 3.0, 15.0), (20.0, 10.0, 30.0), (20.0, 3.0, 10.0)]


@pytest.mark.parametrize("gains", GAINS)
def test_the_frontier_is_one_over_the_hinf_norm_and_above_lemma_1s(gains):
    a, b, c = role_matrices(*gains)
    w = np.logspace(-3, 4, 5000)
    sweep = max(np.linalg.norm(c @ np.linalg.solve(1j * x * np.eye(5) - a, b), 2) for x in w)
    norm = hinf_norm(a, b, c)
    assert sweep <= norm * (1 + 1e-9) and sweep >= norm * (1 - 1e-3)
    exact = max_certified_state_lipschitz(*gains)
    verified = max_certified_state_lipschitz_verified(*gains)
    assert exact == pytest.approx(1.0 / norm, rel=1e-12)
    assert exact * (1 - 1e-4) <= verified <= exact
    # the same closed loop under a coarser bound on Δḟ: the role certificate can only certify more
    assert verified > 1.5 * max_certified_lipschitz_best(*gains)


def test_flight_budget_is_the_verified_role_frontier_and_the_verdict_is_monotone():
    budget = flight_budget(10.0, 6.0, 15.0)
    assert budget == max_certified_state_lipschitz_verified(10.0, 6.0, 15.0) == pytest.approx(7.3956, abs=1e-3)
    assert flight_certificate(0.999 * budget, kp=10.0, kd=6.0, omega_o=15.0).holds
    refused = flight_certificate(1.001 * budget, kp=10.0, kd=6.0, omega_o=15.0)
    assert not refused.holds and "state inputs" in refused.text() and refused.margin < 0


@pytest.mark.parametrize("frac", [0.0, 0.3, 0.8])
def test_the_dissipation_inequality_holds_at_random_states_for_the_worst_slope(frac):
    """V̇ + αV − μw² ≤ 0 for φ = −g·(CE) with the worst ‖g‖ ≤ L_s (signed to raise V) and any |w| ≤ C_f."""
    kp, kd, om = GAINS[0]
    lip = frac * flight_budget(kp, kd, om)
    inputs = RoleInputs(kp, kd, om, lipschitz_state=lip, lipschitz_exo=lip)
    res = certify_roles(inputs)
    assert res.holds and verify_roles(inputs, res) and math.isfinite(res.ultimate_bound)
    a, b, c = role_matrices(kp, kd, om)
    p = res.P
    rng = np.random.default_rng(4)
    for _ in range(3000):
        e = rng.normal(size=5) * 10.0 ** rng.uniform(-3, 2, size=5)
        y = c @ e
        pbe = float((p @ b)[:, 0] @ e)
        phi = -np.sign(pbe) * lip * np.linalg.norm(y)  # |φ| at its bound, raising V
        w = np.sign(pbe) * inputs.C_f * rng.uniform(0, 1)
        vdot = 2 * e @ p @ (a @ e + b[:, 0] * (phi + w))
        v = e @ p @ e
        assert vdot + res.alpha * v - res.mu * w ** 2 <= 1e-9 * (abs(vdot) + v + res.mu * w ** 2)


def test_a_verdict_is_withdrawn_when_its_numbers_do_not_verify():
    kp, kd, om = GAINS[0]
    inputs = RoleInputs(kp, kd, om, lipschitz_state=3.0, lipschitz_exo=1.0)
    res = certify_roles(inputs)
    assert verify_roles(inputs, res)
    from dataclasses import replace

    assert not verify_roles(inputs, replace(res, P=-res.P))
    assert not verify_roles(inputs, replace(res, ultimate_bound=0.5 * res.ultimate_bound))
    above = RoleInputs(kp, kd, om, lipschitz_state=1.01 * flight_budget(kp, kd, om))
    assert not certify_roles(above).holds


def test_only_the_state_inputs_count_in_the_verdict():
    """A network's slope in the state inputs is bounded by certified_lipschitz_state (finite differences along
    p_z and v_z only); its attitude inputs do not enter the verdict at all, only the constant C_f."""
    net = random_network(5, sizes=(4, 16, 12, 1), bound=4.0)
    net = type(net)(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                    net.lipschitz_bound, {"feature_set": "state@1"}, "physical")
    assert net.state_columns == (0, 1)
    state = net.certified_lipschitz_state()
    assert state <= net.certified_lipschitz_physical() * (1 + 1e-12)
    rng = np.random.default_rng(2)
    z = rng.normal(size=(5000, 4)) * [0.3, 0.2, 0.1, 0.1]
    dz = np.zeros_like(z)
    dz[:, :2] = rng.normal(size=(5000, 2)) * rng.choice([1e-3, 1e-1, 1.0], size=(5000, 1))
    slopes = np.abs(net.predict(z + dz) - net.predict(z))[:, 0] / np.linalg.norm(dz, axis=1)
    assert slopes.max() <= state * (1 + 1e-9)
    inputs = CertificateInputs(10.0, 6.0, 15.0, lipschitz=net.certified_lipschitz_physical())
    lmi = certify_lmi(inputs)
    roles = certify_roles(RoleInputs(10.0, 6.0, 15.0, lipschitz_state=state,
                                     lipschitz_exo=net.certified_lipschitz_columns((2, 3))))
    assert roles.holds and roles.max_certified > lmi.max_certified_lipschitz
