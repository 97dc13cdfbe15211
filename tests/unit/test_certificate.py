"""The small-gain certificate (paper Section IV): Lyapunov algebra, verdicts, monotonicity, bounds, CLI."""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

import neso.certificate as certificate
from neso.certificate import (
    CertificateInputs,
    best_certificate,
    certify,
    certify_lmi,
    certify_literal,
    certify_tight,
    lmi_matrix,
    lyapunov_residual,
    max_certified_lipschitz,
    max_certified_lipschitz_best,
    negative_margin,
    observer_matrices,
    tracking_matrices,
    verify_certificate,
)

from tests.helpers import lemma1_bound, paper_error_system, worst_case_run

REPO = Path(__file__).resolve().parents[2]
GAIN_SETS = [(10.0, 6.0, 20.0), (10.0, 6.0, 10.0), (4.0, 4.0, 10.0), (25.0, 10.0, 30.0)]


def inputs(kp=10.0, kd=6.0, w=20.0, lip=0.01, **kw) -> CertificateInputs:
    return CertificateInputs(kp=kp, kd=kd, omega_o=w, lipschitz=lip, **kw)


def fast(method):
    """The certificate function with the cheap verdict path (the one the bisection uses)."""
    return {"literal": certify_literal, "tight": lambda i: certify_tight(i, optimise_bound=False),
            "lmi": lambda i: certify_lmi(i, optimise_bound=False)}[method]


# ------------------------------------------------------------------------------------- Lyapunov algebra


@pytest.mark.parametrize("method", ["literal", "tight"])
def test_lyapunov_equations_are_solved(method):
    inp = inputs(lip=0.01)
    res = certify_literal(inp) if method == "literal" else certify_tight(inp)
    a_e, _ = tracking_matrices(inp.kp, inp.kd)
    a_o, _ = observer_matrices(inp.omega_o)
    # Unscaled P's solve Aᵀ P + P A = −T Q̄ T (T = I for the literal certificate).
    q_e = np.diag(res.scale_e) @ res.Q_e @ np.diag(res.scale_e)
    q_o = np.diag(res.scale_obs) @ res.Q_obs @ np.diag(res.scale_obs)
    assert lyapunov_residual(a_e, res.P_e, q_e) < 1e-10
    assert lyapunov_residual(a_o, res.P_obs, q_o) < 1e-10
    assert np.linalg.eigvalsh(res.P_e)[0] > 0 and np.linalg.eigvalsh(res.P_obs)[0] > 0
    if method == "literal":
        assert np.allclose(res.Q_e, np.eye(2)) and np.allclose(res.Q_obs, np.eye(3))


# ------------------------------------------------------------------------------------- literal figures


def literal_closed_form(kp: float, kd: float, w: float, lambda_c: float) -> float:
    """The literal certificate's largest L_N, from scratch: with Q_e = Q_obs = I (λ_e = λ_o = 1) the
    positive root of 1·(1 − 2 c_pb L) = (‖P_eB_e‖ + c_pb λ_c L)², P from AᵀP + PA = −I."""
    a_e, b_e = np.array([[0.0, 1.0], [-kp, -kd]]), np.array([[0.0], [-1.0]])
    a_o, b_o = np.array([[-3 * w, 1.0, 0.0], [-3 * w**2, 0.0, 1.0], [-(w**3), 0.0, 0.0]]), np.array([[0.0], [0.0], [1.0]])
    p = np.linalg.norm(scipy.linalg.solve_continuous_lyapunov(a_e.T, -np.eye(2)) @ b_e, 2)
    c = np.linalg.norm(scipy.linalg.solve_continuous_lyapunov(a_o.T, -np.eye(3)) @ b_o, 2)
    return float(max(np.roots([(c * lambda_c) ** 2, 2 * p * c * lambda_c + 2 * c, p * p - 1.0]).real))


def test_literal_max_lipschitz_for_paper_gains_is_about_0p018_and_the_closed_form():
    corrected = certify_literal(inputs(lip=0.0)).max_certified_lipschitz
    printed = certify_literal(inputs(lip=0.0, lambda_c_rule="paper")).max_certified_lipschitz
    assert 0.015 < corrected < 0.020
    assert 0.015 < printed < 0.020
    assert corrected < printed  # the corrected λ_c is larger
    assert corrected == pytest.approx(literal_closed_form(10.0, 6.0, 20.0, math.hypot(10.0, 7.0)), rel=1e-9)
    assert printed == pytest.approx(literal_closed_form(10.0, 6.0, 20.0, math.hypot(10.0, 6.0)), rel=1e-9)


@pytest.mark.parametrize("method", ["literal", "tight", "lmi"])
def test_bisection_matches_closed_form_max_lipschitz(method):
    inp = inputs(lip=0.0)
    res = fast(method)(inp)
    assert max_certified_lipschitz(inp, method) == pytest.approx(res.max_certified_lipschitz, rel=1e-7)


# ------------------------------------------------------------------------------------- verdict properties


@pytest.mark.parametrize("method", ["literal", "tight", "lmi"])
def test_verdict_is_monotone_in_lipschitz(method):
    base = inputs(lip=0.0)
    lmax = fast(method)(base).max_certified_lipschitz
    sweep = np.linspace(0.0, 2.0 * lmax, 50)
    verdicts = []
    for lip in sweep:
        inp = replace(base, lipschitz=float(lip))
        res = fast(method)(inp)
        verdicts.append(res.holds)
        # α_e, α_o > 0 iff holds
        assert res.holds == (res.alpha_e > 0 and res.alpha_o > 0)
        if res.holds:
            assert verify_certificate(inp, res)
            assert math.isfinite(res.ultimate_bound)
        else:
            assert res.ultimate_bound == math.inf
    first_fail = verdicts.index(False)
    assert all(verdicts[:first_fail]) and not any(verdicts[first_fail:])
    assert 0 < first_fail < 50
    assert sweep[first_fail - 1] < lmax <= sweep[first_fail]


def test_bound_refinement_does_not_change_the_tight_verdict():
    for lip in (0.0, 0.3, 0.9, 1.1):
        inp = inputs(lip=lip)
        a, b = certify_tight(inp), certify_tight(inp, optimise_bound=False)
        assert a.holds == b.holds
        if a.holds:
            assert a.ultimate_bound <= b.ultimate_bound * (1 + 1e-12)
            assert verify_certificate(inp, a)


@pytest.mark.parametrize("gains", GAIN_SETS)
def test_tight_certifies_at_least_the_literal_lipschitz(gains):
    inp = inputs(*gains, lip=0.0)
    lit, tight = certify_literal(inp), certify_tight(inp)
    assert tight.max_certified_lipschitz >= lit.max_certified_lipschitz
    # and the gain is substantial (bandwidth scaling removes the ‖P_obs B_obs‖ ~ ω conditioning)
    assert tight.max_certified_lipschitz > 5 * lit.max_certified_lipschitz


@pytest.mark.parametrize("gains", GAIN_SETS)
@pytest.mark.parametrize("method", ["literal", "tight", "lmi"])
def test_zero_lipschitz_holds_for_hurwitz_gains(gains, method):
    inp = inputs(*gains, lip=0.0)
    res = certify(inp, method)
    assert res.holds and res.alpha > 0 and verify_certificate(inp, res)


def test_literal_bound_at_zero_lipschitz_is_the_eso_only_value():
    """With L_N = 0 the bound is min over δ_e, δ_c of sqrt((c_pb L_1)² / (δ_c · min(λ_e−δ_e, λ_o−δ_c−p²/δ_e)))."""
    inp = inputs(lip=0.0)
    res = certify_literal(inp)
    c, p = res.c_pb, res.pe_be_norm
    d_e = np.linspace(1e-3, 1 - 1e-3, 1200)[:, None]
    d_c = np.linspace(1e-3, 1 - 1e-3, 1200)[None, :]
    alpha = np.minimum(1 - d_e, 1 - d_c - p * p / d_e)
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(alpha > 0, np.sqrt((c * inp.L_1) ** 2 / (d_c * alpha)), np.inf)
    grid = float(bound.min())
    assert res.ultimate_bound == pytest.approx(grid, rel=2e-3)
    assert res.ultimate_bound <= grid * (1 + 1e-9)
    # continuity: the bound tends to the ESO-only value as L_N → 0, for both methods
    for method_fn in (certify_literal, certify_tight):
        b0 = method_fn(inp).ultimate_bound
        b_small = method_fn(replace(inp, lipschitz=1e-9)).ultimate_bound
        assert b_small == pytest.approx(b0, rel=1e-3)


def test_n_axes_does_not_change_the_certificate():
    one, three = inputs(lip=0.3), inputs(lip=0.3, n_axes=3)
    for fn in (certify_literal, certify_tight, certify_lmi):
        a, b = fn(one), fn(three)
        assert a.holds == b.holds
        assert a.max_certified_lipschitz == pytest.approx(b.max_certified_lipschitz, rel=1e-12)
        assert a.ultimate_bound == pytest.approx(b.ultimate_bound, rel=1e-12)
        if b.holds:
            assert verify_certificate(three, b)  # rebuilt with the 3-axis Kronecker matrices


def test_verifier_rejects_a_tampered_certificate():
    inp = inputs(lip=0.9)
    res = certify_tight(inp)
    assert res.holds and verify_certificate(inp, res)
    assert not verify_certificate(inp, replace(res, scale_obs=np.ones(3)))  # literal coordinates fail at 0.9
    assert not verify_certificate(inp, replace(res, ultimate_bound=0.5 * res.ultimate_bound))
    assert not verify_certificate(replace(inp, lipschitz=1.2), res)
    lit = certify_literal(inputs(lip=0.01))
    assert verify_certificate(inputs(lip=0.01), lit)
    assert not verify_certificate(inputs(lip=0.01), replace(lit, delta_c=2.0))


# ------------------------------------------------------------------------------------- the bound itself


def _worst_vdot(res, inp, e_s: np.ndarray, e_o: np.ndarray) -> np.ndarray:
    """V̇ along the true error dynamics with the worst Δḟ allowed by Lemma 1; rows are samples.

    Built here from the paper's matrices, independently of the certificate's own algebra.
    """
    kp, kd, w = inp.kp, inp.kd, inp.omega_o
    a_e = np.array([[0.0, 1.0], [-kp, -kd]])
    a_o = np.array([[-3 * w, 1.0, 0.0], [-3 * w * w, 0.0, 1.0], [-(w**3), 0.0, 0.0]])
    lam_c = math.hypot(kp, kd + 1.0)
    f_tilde = e_o[:, 2]
    de_s = e_s @ a_e.T + np.outer(f_tilde, [0.0, -1.0])
    w_max = inp.lipschitz * (lam_c * np.linalg.norm(e_s, axis=1) + np.linalg.norm(e_o, axis=1)) + inp.C_f
    g = 2.0 * (e_o @ res.P_obs)[:, 2]  # ∂V̇/∂(Δḟ)
    vdot_e = 2.0 * res.weight_s * np.einsum("ij,jk,ik->i", e_s, res.P_e, de_s)
    vdot_o = 2.0 * np.einsum("ij,jk,ik->i", e_o, res.P_obs, e_o @ a_o.T) + np.abs(g) * w_max
    return vdot_e + vdot_o


@pytest.mark.parametrize("method", ["literal", "tight"])
@pytest.mark.parametrize("lip_frac", [0.0, 0.5, 0.95])
def test_vdot_is_negative_outside_the_ultimate_bound(method, lip_frac):
    fn = certify_literal if method == "literal" else certify_tight
    lmax = fn(inputs(lip=0.0)).max_certified_lipschitz
    inp = inputs(lip=lip_frac * lmax)
    res = fn(inp)
    assert res.holds
    rng = np.random.default_rng(1)
    n = 20000
    # directions with wildly different component scales, to reach the observer's stiff directions
    d = rng.normal(size=(n, 5)) * np.exp(rng.uniform(-8, 8, size=(n, 5)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = res.ultimate_bound * (1.0 + 1e-6) * np.exp(rng.uniform(0.0, 3.0, size=(n, 1)))
    pts = d * r
    vdot = _worst_vdot(res, inp, pts[:, :2], pts[:, 2:])
    assert np.all(vdot < 0)
    # and the sublevel bound is no smaller than the decrease-ball radius
    assert res.ultimate_bound_sublevel >= res.ultimate_bound * (1 - 1e-12)


def test_literal_vdot_inequality_of_theorem_1():
    """V̇ ≤ −α_e‖e_s‖² − α_o‖ẽ‖² + C_o at the reported δ's (random points, worst Δḟ)."""
    inp = inputs(lip=0.01)
    res = certify_literal(inp)
    assert res.holds
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(20000, 5)) * np.exp(rng.uniform(-6, 4, size=(20000, 5)))
    vdot = _worst_vdot(res, inp, pts[:, :2], pts[:, 2:])
    rhs = -res.alpha_e * np.sum(pts[:, :2] ** 2, 1) - res.alpha_o * np.sum(pts[:, 2:] ** 2, 1) + res.C_o
    assert np.all(vdot <= rhs + 1e-9 * np.abs(rhs))


# ------------------------------------------------------------------------------------- LMI certificate


@pytest.mark.parametrize("gains", GAIN_SETS)
def test_lmi_contains_tight_and_full_contains_block(gains):
    """Tight's V with the multipliers of the module docstring satisfies the block LMI at 0.99 of tight's maximum,
    so the LMI certifies at least as much; full at least as much as block."""
    lt = certify_tight(inputs(*gains, lip=0.0)).max_certified_lipschitz
    inp = inputs(*gains, lip=0.99 * lt)
    r = certify_tight(inp, optimise_bound=False)
    assert r.holds
    a, p = r.weight_s * r.lambda_e, r.weight_s * r.pe_be_norm / r.scale_obs[2]
    q = r.c_pb * inp.gamma_e * r.kappa_e
    tau_e, tau_o = a * r.c_pb / ((p + q) * inp.gamma_e * r.kappa_e), r.c_pb / (inp.gamma_etilde * r.kappa_o)
    p_tight = np.zeros((5, 5))
    p_tight[:2, :2], p_tight[2:, 2:] = r.weight_s * r.P_e, r.P_obs
    assert negative_margin(*lmi_matrix(inp, p_tight, tau_e, tau_o)) > 0
    block = certify_lmi(inputs(*gains, lip=0.0), structure="block").max_certified_lipschitz
    full = certify_lmi(inputs(*gains, lip=0.0), structure="full").max_certified_lipschitz
    assert block >= lt
    assert full >= block * (1 - 1e-5)
    assert certify_lmi(inp, structure="block").holds


def test_lmi_verifier_rejects_perturbed_certificates():
    base = inputs(lip=0.0)
    lmax = certify_lmi(base).max_certified_lipschitz
    inp = replace(base, lipschitz=0.9 * lmax)
    res = certify_lmi(inp)
    assert res.holds and verify_certificate(inp, res)
    # just above the maximum: neither this certificate nor a new one
    above = replace(base, lipschitz=lmax * (1 + 1e-3))
    assert not verify_certificate(above, certify_lmi(replace(base, lipschitz=lmax)))
    assert not certify_lmi(above).holds and not verify_certificate(above, res)
    # a perturbed P, a P that is not positive definite, the literal certificate's P, negative multipliers
    rng = np.random.default_rng(3)
    noise = rng.normal(size=(5, 5))
    bumped = res.P * (1 + 0.05 * (noise + noise.T))
    assert not verify_certificate(inp, replace(res, P=bumped))
    assert not verify_certificate(inp, replace(res, P=-res.P))
    lit = certify_literal(inp)
    assert not verify_certificate(inp, replace(res, P=scipy_block(lit.P_e, lit.P_obs)))
    assert not verify_certificate(inp, replace(res, multipliers=(-res.multipliers[0], res.multipliers[1])))
    # a smaller claimed bound, a faster claimed decay, a block certificate whose P is not block-diagonal
    assert not verify_certificate(inp, replace(res, ultimate_bound=0.5 * res.ultimate_bound))
    assert not verify_certificate(inp, replace(res, alpha=2.0 * res.alpha))
    assert not verify_certificate(inp, replace(res, structure="block"))
    assert not verify_certificate(inp, replace(res, holds=False))


def scipy_block(p_e, p_o):
    p = np.zeros((5, 5))
    p[:2, :2], p[2:, 2:] = p_e, p_o
    return p


def test_lmi_verdict_is_withdrawn_when_the_solver_lies(monkeypatch):
    """The solver's answer is replaced by a P that is no certificate: nothing verifies, so nothing holds."""
    gains = (7.0, 5.0, 12.0)  # not used elsewhere, so nothing cached hides the lie
    for prog in (certificate._lmi_programs("full"),):
        monkeypatch.setattr(type(prog), "solution", lambda self, t: (-np.eye(5), 1.0, 1.0))
    certificate._lmi_frontier.cache_clear()
    try:
        res = certify_lmi(inputs(*gains, lip=0.0))
        assert not res.holds and res.max_certified_lipschitz == 0.0
        assert any("withdrawn" in n for n in res.notes)
    finally:
        monkeypatch.undo()
        certificate._lmi_frontier.cache_clear()
    assert certify_lmi(inputs(*gains, lip=0.0)).holds


@pytest.mark.parametrize("lip_frac", [0.0, 0.5, 0.95])
def test_lmi_dissipation_inequality_at_random_states(lip_frac):
    """V̇ ≤ −αV + μC_f² for the worst Δḟ Lemma 1 allows (|Δḟ| at its bound, signed to raise V), at states of
    wildly different component scales; and V̇ < 0 outside the ultimate bound."""
    lmax = certify_lmi(inputs(lip=0.0)).max_certified_lipschitz
    inp = inputs(lip=lip_frac * lmax)
    res = certify_lmi(inp)
    assert res.holds
    a, b = paper_error_system(inp.kp, inp.kd, inp.omega_o)
    rng = np.random.default_rng(4)
    d = rng.normal(size=(20000, 5)) * np.exp(rng.uniform(-8, 8, size=(20000, 5)))
    e = d / np.linalg.norm(d, axis=1, keepdims=True) * np.exp(rng.uniform(-6, 6, size=(20000, 1)))
    pe = e @ res.P
    v = np.einsum("ij,ij->i", pe, e)
    vdot = 2 * np.einsum("ij,ij->i", pe, e @ a.T) + 2 * np.abs(pe @ b) * lemma1_bound(inp, e)
    rhs = -res.alpha * v + res.mu * inp.C_f**2
    assert np.all(vdot <= rhs + 1e-9 * (np.abs(rhs) + np.abs(vdot)))
    outside = np.linalg.norm(e, axis=1) > res.ultimate_bound
    assert outside.sum() > 1000 and np.all(vdot[outside] < 0)


@pytest.mark.parametrize("lip_frac", [0.0, 0.5, 0.9])
def test_lmi_bound_holds_on_simulated_worst_case_trajectories(lip_frac):
    """The linear error system driven by the Δḟ that raises V fastest within Lemma 1, from rest and from large
    errors: V(t) ≤ V₀e^{−αt} + (μC_f²/α)(1 − e^{−αt}), so ‖E‖ ends below the eventual bound (and, from rest,
    never leaves it)."""
    lmax = certify_lmi(inputs(lip=0.0)).max_certified_lipschitz
    inp = inputs(lip=lip_frac * lmax)
    res = certify_lmi(inp)
    rng = np.random.default_rng(5)
    e0 = np.zeros((6, 5))
    e0[1:] = rng.normal(size=(5, 5)) * [0.3, 1.0, 0.03, 0.5, 5.0] * 20
    t_s, e = worst_case_run(inp, res.P, e0)
    v0 = np.einsum("ij,jk,ik->i", e0, res.P, e0)
    v = np.einsum("tij,jk,tik->ti", e, res.P, e)
    decay = np.exp(-res.alpha * t_s)[:, None]
    cap = res.mu * inp.C_f**2 / res.alpha
    assert np.all(v <= (v0 * decay + cap * (1 - decay)) * (1 + 1e-3))
    norms = np.linalg.norm(e, axis=2)
    assert norms[:, 0].max() <= res.ultimate_bound  # from rest: inside the sublevel set throughout
    assert norms[-1].max() <= res.ultimate_bound
    # the bound is met, not vacuous: from rest the worst case climbs to a sizeable share of it
    assert norms[:, 0].max() > 0.1 * res.ultimate_bound


def test_best_certificate_is_the_tightest_verified_one():
    kp, kd, w = 10.0, 6.0, 15.0
    best = max_certified_lipschitz_best(kp, kd, w)
    base = inputs(kp, kd, w, lip=0.0)
    others = {m: fast(m)(base).max_certified_lipschitz for m in ("literal", "tight", "lmi")}
    assert best == max(others.values()) == others["lmi"]
    assert best >= certify_lmi(base, structure="block").max_certified_lipschitz
    inside, outside = replace(base, lipschitz=0.99 * best), replace(base, lipschitz=1.01 * best)
    r = best_certificate(inside)
    assert r.method == "lmi" and r.holds and verify_certificate(inside, r)
    assert not best_certificate(outside).holds
    assert best_certificate(inside) is r  # cached per inputs
    # the flown gains: the LMI certifies what tight does not
    between = replace(base, lipschitz=0.5 * (others["tight"] + best))
    assert not certify_tight(between).holds and best_certificate(between).holds


# ------------------------------------------------------------------------------------- JSON and CLI

REQUIRED = {"holds", "alpha_e", "alpha_o", "ultimate_bound", "max_certified_lipschitz"}


def test_json_dict_has_required_keys_and_is_strict_json():
    for res in (certify_literal(inputs(lip=0.01)), certify_literal(inputs(lip=0.5)), certify_tight(inputs(lip=0.5)),
                certify_lmi(inputs(lip=0.5)), certify_lmi(inputs(lip=50.0))):
        d = res.to_json_dict()
        assert REQUIRED <= d.keys()
        assert isinstance(d["holds"], bool)
        text = json.dumps(d, allow_nan=False)
        assert json.loads(text)["method"] == res.method


def _parse(argv):
    from cli import certify

    p = argparse.ArgumentParser()
    s = p.add_subparsers(dest="cmd")
    certify.add_parser(s)
    return certify, p.parse_args(["certify", *argv])


@pytest.mark.parametrize(
    "lip,method,expected",
    [(0.01, "literal", 0), (0.05, "literal", 1), (0.05, "tight", 0), (0.05, "both", 0), (5.0, "both", 1),
     (1.5, "both", 1), (1.5, "lmi", 0), (1.5, "all", 0), (5.0, "lmi", 1), (2.0, "roles", 0), (2.0, "all", 0),
     (5.0, "roles", 1), (5.0, "all", 1), (10.0, "roles", 1), (10.0, "all", 1)],
)
def test_cli_exit_code_matches_holds(lip, method, expected, capsys):
    certify, args = _parse(["--kp", "10", "--kd", "6", "--omega-o", "20", "--lipschitz", str(lip),
                            "--method", method, "--json"])
    rc = certify.run(args)
    out = json.loads(capsys.readouterr().out)
    assert rc == expected
    assert {"holds", "method", "max_certified_lipschitz", "margin", "ultimate_bound", "methods", "inputs"} <= out.keys()
    assert out["holds"] == (rc == 0) and REQUIRED <= out["methods"][out["method"]].keys()
    if method in ("both", "all"):
        methods = out["methods"]
        assert set(methods) == ({"literal", "tight"} if method == "both" else {"literal", "tight", "lmi", "roles"})
        assert out["holds"] == methods["tight" if method == "both" else "roles"]["holds"]
    if method == "all":  # the verdict is the role certificate's, the one the services fly by
        assert out["method"] == "roles" and "P" not in out["methods"]["lmi"]  # compact: no matrices
        assert out["max_certified_lipschitz"] == out["methods"]["roles"]["max_certified_lipschitz"]
        # one margin, the one the services act on (the state slope's headroom), and each part beside it
        assert out["margin"] == pytest.approx(out["max_certified_lipschitz"] - lip)
        assert out["parts"]["state"] == lip and out["parts"]["loop_gain"] == 0.0
        if lip == 5.0:  # stable (5 < 8.35 certified) but its |e_z| bound is ×3.5 PD+ESO's: not said to fly well
            assert out["margin"] > 0 and out["bound_ratio"] > out["max_bound_ratio"] and "fly well" in out["reasons"][0]


def test_cli_json_is_compact_and_verbose_adds_the_matrices(capsys):
    certify, args = _parse(["--lipschitz", "1.0", "--json"])
    assert certify.run(args) == 0
    text = capsys.readouterr().out
    compact = json.loads(text)
    assert compact["margin"] == pytest.approx(compact["max_certified_lipschitz"] - 1.0)

    def keys(d):
        return set(d) | set().union(*(keys(v) for v in d.values() if isinstance(v, dict))) if isinstance(d, dict) else set()

    assert not keys(compact) & {"P", "P_e", "P_obs", "coupling_matrix", "role"}  # compact: no matrices
    certify, args = _parse(["--lipschitz", "1.0", "--json", "--verbose"])
    certify.run(args)
    verbose = json.loads(capsys.readouterr().out)
    assert verbose["methods"]["lmi"]["structure"] == "full" and len(verbose["methods"]["lmi"]["P"]) == 5
    assert {k: v for k, v in verbose.items() if k != "methods"} == {k: v for k, v in compact.items() if k != "methods"}


def test_cli_help_says_what_the_exit_status_means(capsys):
    with pytest.raises(SystemExit):
        _parse(["--help"])
    assert "exit status: 0 the certificate holds, 1 it fails" in " ".join(capsys.readouterr().out.split())


def test_cli_text_report(capsys):
    certify, args = _parse(["--kp", "10", "--kd", "6", "--omega-o", "20", "--lipschitz", "0.05"])
    assert certify.run(args) == 0
    out = capsys.readouterr().out
    assert "[literal] FAILS" in out and "[tight] HOLDS" in out and "max certified L_N" in out
    assert "[lmi] HOLDS" in out and "[roles] HOLDS" in out and "verdict (roles): HOLDS" in out
    assert "re-verified in numpy" in out and "state 0.05 (max certified" in out and "eventual |e_z| <=" in out


def test_cli_as_subprocess():
    code = ("import argparse; from cli import certify; p=argparse.ArgumentParser(); s=p.add_subparsers(dest='cmd'); "
            "certify.add_parser(s); a=p.parse_args(['certify','--kp','10','--kd','6','--omega-o','20',"
            "'--lipschitz','0.05','--method','literal','--json']); raise SystemExit(certify.run(a))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 1, proc.stderr
    out = json.loads(proc.stdout)
    assert out["holds"] is False and out["ultimate_bound"] is None
    assert out["max_certified_lipschitz"] == pytest.approx(certify_literal(inputs(lip=0.05)).max_certified_lipschitz,
                                                           rel=1e-9)
