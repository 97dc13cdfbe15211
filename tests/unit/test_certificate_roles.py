"""The role certificate (neso/certificate/roles.py) and the verdict for what flies (neso/certificate/flight.py):
every input in its role — the state in the loop gain, the thrust and attitude in the loop through the controller's
output, the rest bounded by what the vehicle can do — with the measured velocity's lag in the loop, an eventual
bound on |e_z| in metres, every verdict re-verified in numpy, and the dissipation inequality it claims checked at
random states against the worst slopes."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from neso.certificate import (POLICY, CertificateInputs, LoopPlant, NetworkSlopes, RoleInputs, certify_lmi,
                              certify_roles, flight_budget, flight_certificate, max_certified_lipschitz_best,
                              max_certified_state_lipschitz, max_certified_state_lipschitz_verified, verify_roles)
from neso.certificate.roles import hinf_norm, loop_matrices, role_matrices
from neso.control import ControlConfig
from neso.netfile import load_network
from neso.types import velocity_lag_s
from tests.busutil import REPO
from tests.helpers import random_network

GAINS = [(10.0, 6.0, 15.0), (4.0, 3.0, 15.0), (20.0, 10.0, 30.0), (20.0, 3.0, 10.0)]
PLANT = LoopPlant.of(ControlConfig())
LAG = velocity_lag_s()


@pytest.mark.parametrize("gains", GAINS)
@pytest.mark.parametrize("lag", [0.0, LAG])
def test_the_frontier_is_one_over_the_hinf_norm_and_above_lemma_1s(gains, lag):
    a, b, c = role_matrices(*gains, lag)
    n = a.shape[0]
    w = np.logspace(-3, 4, 5000)
    sweep = max(np.linalg.norm(c @ np.linalg.solve(1j * x * np.eye(n) - a, b), 2) for x in w)
    norm = hinf_norm(a, b, c)
    assert sweep <= norm * (1 + 1e-9) and sweep >= norm * (1 - 1e-3)
    exact = max_certified_state_lipschitz(*gains, lag)
    verified = max_certified_state_lipschitz_verified(*gains, lag)
    assert exact == pytest.approx(1.0 / norm, rel=1e-12)
    assert exact * (1 - 1e-4) <= verified <= exact
    # the same closed loop under a coarser bound on Δḟ: the role certificate can only certify more
    assert verified > 1.5 * max_certified_lipschitz_best(*gains)


def test_the_velocity_filter_is_in_the_loop():
    """With the source's 15 Hz filter on a 50 Hz difference (20.6 ms) the D term and the network's velocity input
    lag the true velocity: the certified slope drops (7.40 → 6.94 at the flown gains) and the loop has a sixth
    state whose pole is the filter's."""
    assert LAG == pytest.approx(0.5 / 50 + 1 / (2 * math.pi * 15))
    m = loop_matrices(10.0, 6.0, 15.0, LAG)
    assert m.n == 6 and m.b_ref[5, 0] == -1.0 and m.c_state[1, 5] == pytest.approx(-1 / LAG)
    assert max_certified_state_lipschitz(10.0, 6.0, 15.0) == pytest.approx(7.3956, abs=1e-3)
    assert max_certified_state_lipschitz(10.0, 6.0, 15.0, LAG) == pytest.approx(6.94, abs=0.01)
    assert max(np.linalg.eigvals(m.a).real) < 0


def _worst_dissipation(inputs: RoleInputs, res, rng, n: int = 3000) -> float:
    """max over random states of (V̇ + αV − μ w² − μ_r r²) / scale, with φ_s and φ_u at their bounds, signed to
    raise V, and any |w| ≤ C_f, |r| ≤ a (the reference input)."""
    m = inputs.matrices
    ls, lu = inputs.channels
    p = res.P
    worst = -math.inf
    for _ in range(n):
        e = rng.normal(size=m.n) * 10.0 ** rng.uniform(-3, 2, size=m.n)
        pbe = float((p @ m.b)[:, 0] @ e)
        sign = np.sign(pbe) or 1.0
        phi = sign * (ls * np.linalg.norm(m.c_state @ e) + lu * abs(float((m.c_thrust @ e)[0])))
        w = sign * inputs.C_f * rng.uniform(0, 1)
        r = np.sign(float((p @ m.b_ref)[:, 0] @ e) or 1.0) * inputs.ref_input * rng.uniform(0, 1)
        edot = m.a @ e + m.b[:, 0] * (phi + w) + m.b_ref[:, 0] * r
        vdot = 2 * e @ p @ edot
        v = e @ p @ e
        mu_r = res.mu_ref if math.isfinite(res.mu_ref) else 0.0
        slack = vdot + res.alpha * v - res.mu * w ** 2 - mu_r * r ** 2
        worst = max(worst, slack / (abs(vdot) + v + res.mu * w ** 2 + mu_r * r ** 2))
    return worst


@pytest.mark.parametrize("frac,loop_gain", [(0.0, 0.0), (0.3, 0.0), (0.3, 0.1), (0.8, 0.0)])
@pytest.mark.parametrize("lag", [0.0, LAG])
def test_the_dissipation_inequality_holds_at_random_states_for_the_worst_slopes(frac, loop_gain, lag):
    """V̇ + αV − μw² − μ_r z̈*² ≤ 0 for φ = −g_s·(C_s E) − g_u (c_u E) with the worst ‖g_s‖ ≤ ls, |g_u| ≤ lu
    (signed to raise V), any |w| ≤ C_f and |z̈*| ≤ a — and |e_z| ≤ the stated bound on the set V settles in."""
    kp, kd, om = GAINS[0]
    lip = frac * max_certified_state_lipschitz_verified(kp, kd, om, lag, loop_gain)
    inputs = RoleInputs(kp, kd, om, lipschitz_state=lip, loop_gain=loop_gain, exogenous_rate_mps3=1.0,
                        velocity_lag_s=lag)
    res = certify_roles(inputs)
    assert res.holds and verify_roles(inputs, res) and math.isfinite(res.error_bound_m)
    assert _worst_dissipation(inputs, res, np.random.default_rng(4)) <= 1e-9
    # the eventual set {V ≤ (μ C_f² + μ_r a²)/α}: its largest |e| is sqrt(level (P⁻¹)₁₁), never above the bound
    mu_r = res.mu_ref if math.isfinite(res.mu_ref) else 0.0
    level = (res.mu * inputs.C_f ** 2 + mu_r * inputs.ref_input ** 2) / res.alpha
    assert math.sqrt(level * np.linalg.inv(res.P)[0, 0]) <= res.error_bound_m
    assert res.error_bound_m <= res.ultimate_bound  # |e| ≤ ‖E‖


def test_a_verdict_is_withdrawn_when_its_numbers_do_not_verify():
    kp, kd, om = GAINS[0]
    inputs = RoleInputs(kp, kd, om, lipschitz_state=3.0, loop_gain=0.05, exogenous_rate_mps3=1.0)
    res = certify_roles(inputs)
    assert verify_roles(inputs, res)
    assert not verify_roles(inputs, replace(res, P=-res.P))
    assert not verify_roles(inputs, replace(res, error_bound_m=0.5 * res.error_bound_m))
    assert not verify_roles(replace(inputs, loop_gain=0.5), res)  # the same numbers for a larger loop gain
    above = RoleInputs(kp, kd, om, lipschitz_state=1.01 * max_certified_state_lipschitz(kp, kd, om))
    assert not certify_roles(above).holds


def test_a_loop_gain_through_the_thrust_of_one_or_more_is_never_certified():
    """K = m L_T + k_att L_att: the controller makes the thrust from f̂, so a network's thrust slope feeds back at
    once; at K ≥ 1 the loop is ill-posed (the discrete loop T_k = −m κ T_{k−1} diverges), whatever L_s."""
    kp, kd, om = GAINS[0]
    for k in (1.0, 1.18):
        res = certify_roles(RoleInputs(kp, kd, om, lipschitz_state=0.0, loop_gain=k))
        assert not res.holds and "loop gain" in res.notes[0]
    # below 1 it still costs: the state slope certified shrinks as K grows
    fronts = [max_certified_state_lipschitz_verified(kp, kd, om, LAG, k) for k in (0.0, 0.1, 0.3)]
    assert fronts[0] > fronts[1] > fronts[2] > 0


def test_rates_come_from_what_the_vehicle_can_do():
    """One place (neso.certificate.flight.exogenous_rates): the force-rate limit, the tilt limit, the body-rate limit
    and the vertical specific-force floor give the thrust's, attitude's and speed's exogenous rates and the
    attitude's share of the loop."""
    from neso.certificate import exogenous_rates

    c = ControlConfig()
    r = exogenous_rates(PLANT)
    assert PLANT.force_rate_limit_nps == c.force_rate_limit_nps == 40.0 and PLANT.max_tilt_rad == c.max_tilt_rad
    assert r.thrust_nps == pytest.approx(math.sqrt(2) * 40 * math.sin(c.max_tilt_rad))
    assert r.attitude_rps == pytest.approx(min(math.sqrt(2) * 40 / (1.0 * POLICY.min_specific_force_mps2
                                                                     * math.cos(c.max_tilt_rad)),
                                               math.radians(220) / math.cos(c.max_tilt_rad)))
    assert r.attitude_per_uz == pytest.approx(math.tan(c.max_tilt_rad) / POLICY.min_specific_force_mps2)
    heavy = exogenous_rates(replace(PLANT, mass_kg=2.0))
    assert heavy.thrust_nps == r.thrust_nps and heavy.attitude_rps <= r.attitude_rps


def test_the_paper_networks_with_a_thrust_input_are_refused_and_base_l2_by_its_loop_gain():
    """The README's limit-cycling paper network (base-L1, 2.24 Hz without noise) and base-L2 (T_{k−1} slope 1.18
    (m/s²)/N, above 1/m) were "certified" by the state slope alone. In their true roles neither flies."""
    l2 = flight_certificate(NetworkSlopes.of(load_network(f"{REPO}/networks/paper/base-L2.safetensors")), kp=10.0,
                            kd=6.0, omega_o=15.0, plant=PLANT)
    assert not l2.holds and l2.loop_gain > 1.0 and l2.slopes.thrust == pytest.approx(1.18, abs=0.01)
    assert any("loop gain" in r for r in l2.reasons)
    l1 = flight_certificate(NetworkSlopes.of(load_network(f"{REPO}/networks/paper/base-L1.safetensors")), kp=10.0,
                            kd=6.0, omega_o=15.0, plant=PLANT)
    assert not l1.holds and 0.0 < l1.loop_gain < 1.0 and not l1.stable


def test_the_verdict_bounds_the_error_in_centimetres_against_pd_esos():
    """holds ⇔ stable and the eventual |e_z| bound over the envelope at most max_bound_ratio × PD+ESO's; the
    budget the trainer spends is the largest state slope that still holds; the bound grows with the slope."""
    budget = flight_budget(10.0, 6.0, 15.0, plant=PLANT)
    inside = flight_certificate(NetworkSlopes(0.999 * budget), kp=10.0, kd=6.0, omega_o=15.0, plant=PLANT)
    outside = flight_certificate(NetworkSlopes(1.02 * budget), kp=10.0, kd=6.0, omega_o=15.0, plant=PLANT)
    assert inside.holds and inside.bound_ratio <= POLICY.max_bound_ratio
    assert not outside.holds and outside.stable and outside.bound_ratio > POLICY.max_bound_ratio
    assert "cm" in outside.text() and "fly well" in outside.reasons[0]
    none = flight_certificate(NetworkSlopes(0.0), kp=10.0, kd=6.0, omega_o=15.0, plant=PLANT)
    assert none.holds and none.bound_cm == pytest.approx(none.pdeso_bound_cm) and 5.0 < none.bound_cm < 30.0
    assert none.bound_cm < inside.bound_cm < outside.bound_cm
    # hover: the same certificates give a smaller bound (no reference terms)
    from neso.certificate import ReferenceBounds

    hover, pdeso_hover = inside.bound_for_cm(ReferenceBounds())
    assert pdeso_hover <= none.pdeso_bound_cm and hover < inside.bound_cm


def test_a_thrust_input_network_at_another_mass_is_refused():
    slopes = NetworkSlopes(0.3, thrust=0.02, mass_kg=1.0, thrust_inputs=True)
    at_1 = flight_certificate(slopes, kp=10.0, kd=6.0, omega_o=15.0, plant=PLANT)
    at_15 = flight_certificate(slopes, kp=10.0, kd=6.0, omega_o=15.0, plant=replace(PLANT, mass_kg=1.5))
    assert at_1.holds, at_1.text()
    assert not at_15.holds and "1 kg vehicle, flown on 1.5 kg" in " ".join(at_15.reasons)
    unknown = flight_certificate(replace(slopes, mass_kg=math.nan), kp=10.0, kd=6.0, omega_o=15.0, plant=PLANT)
    assert not unknown.holds and "states no mass" in " ".join(unknown.reasons)
    state_only = flight_certificate(NetworkSlopes(0.5, mass_kg=1.0), kp=10.0, kd=6.0, omega_o=15.0,
                                    plant=replace(PLANT, mass_kg=1.5))
    assert state_only.holds  # no input in newtons: nothing in it scales with mass


def test_each_role_is_bounded_by_its_own_columns():
    """A network's slope in each role is bounded by its columns' exact SVD product (finite differences along those
    columns only); the state slope never exceeds the whole network's."""
    net = random_network(5, sizes=(5, 16, 12, 1), bound=4.0)
    net = type(net)(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                    net.lipschitz_bound, {"feature_set": "paper@1", "mass_kg": "1.0"}, "physical")
    slopes = NetworkSlopes.of(net)
    assert net.role_columns()["thrust"] == (2,) and net.role_columns()["attitude"] == (3, 4)
    assert slopes.state <= net.certified_lipschitz_physical() * (1 + 1e-12) and slopes.thrust_inputs
    rng = np.random.default_rng(2)
    z = rng.normal(size=(5000, 5)) * [0.3, 0.2, 1.0, 0.1, 0.1]
    for role, cols in net.role_columns().items():
        if not cols:
            continue
        dz = np.zeros_like(z)
        dz[:, list(cols)] = rng.normal(size=(5000, len(cols))) * rng.choice([1e-3, 1e-1, 1.0], size=(5000, 1))
        ratio = np.abs(net.predict(z + dz) - net.predict(z))[:, 0] / np.linalg.norm(dz, axis=1)
        assert ratio.max() <= getattr(slopes, role) * (1 + 1e-9), role


def test_the_role_certificate_certifies_more_than_lemma_1():
    net = random_network(5, sizes=(4, 16, 12, 1), bound=4.0)
    net = type(net)(net.weights, net.biases, net.input_mean, net.input_std, net.output_mean, net.output_std,
                    net.lipschitz_bound, {"feature_set": "state@1"}, "physical")
    lmi = certify_lmi(CertificateInputs(10.0, 6.0, 15.0, lipschitz=net.certified_lipschitz_physical()))
    roles = certify_roles(RoleInputs(10.0, 6.0, 15.0, lipschitz_state=net.certified_lipschitz_state()))
    assert roles.holds and roles.max_certified > lmi.max_certified_lipschitz
