"""``literal``: the paper's Theorem 1 taken as printed (the package docstring derives it).
"""
from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.optimize

from neso.certificate.core import (_REL_TOL, CertificateInputs, CertificateResult, _lambda_min_2x2, _max_root, _spec,
                                   observer_matrices, solve_lyapunov, tracking_matrices)

# --------------------------------------------------------------------------------------------- literal


def _literal_terms(inputs: CertificateInputs) -> dict:
    a_e, b_e = tracking_matrices(inputs.kp, inputs.kd)
    a_o, b_o = observer_matrices(inputs.omega_o)
    q_e, q_o = np.eye(2), np.eye(3)
    p_e, p_o = solve_lyapunov(a_e, q_e), solve_lyapunov(a_o, q_o)
    return dict(
        P_e=p_e, P_obs=p_o, Q_e=q_e, Q_obs=q_o,
        lambda_e=float(np.linalg.eigvalsh(q_e)[0]), lambda_o=float(np.linalg.eigvalsh(q_o)[0]),
        p=_spec(p_e @ b_e), c_pb=_spec(p_o @ b_o),
    )


def _best_delta_c(alpha_e: float, a_o: float) -> tuple[float, float]:
    """Maximise ``δ_c · min(α_e, A_o − δ_c)`` (i.e. minimise ``C_o/α``); returns ``(δ_c, value)``."""
    if alpha_e >= 0.5 * a_o:
        return 0.5 * a_o, 0.25 * a_o * a_o
    return a_o - alpha_e, alpha_e * (a_o - alpha_e)


def _literal_margins(lam_e, mu, a, p, d_e, d_o):
    """``α_e`` and ``A_o = α_o + δ_c`` of the paper for given ``δ_e, δ_o`` (``a = c_pb γ_e``, ``μ = λ_o − 2c_pbγ_ẽ``)."""
    c_o = 0.0 if a == 0.0 else a * a / d_o
    return lam_e - d_e - c_o, mu - d_o - p * p / d_e


def certify_literal(inputs: CertificateInputs) -> CertificateResult:
    """The paper's Theorem 1 taken literally (``Q_e = I``, ``Q_obs = I``, Young splits); see module docstring."""
    t = _literal_terms(inputs)
    lam_e, lam_o, p, c = t["lambda_e"], t["lambda_o"], t["p"], t["c_pb"]
    a = c * inputs.gamma_e
    mu = lam_o - 2.0 * c * inputs.gamma_etilde
    m11, m12, m22 = lam_e, -(p + a), mu
    alpha_sup = _lambda_min_2x2(m11, m12, m22)
    lmax = _max_root(lam_e, p, c, lam_o, inputs.lambda_c, 1.0, 1.0)
    holds = alpha_sup > _REL_TOL * max(lam_e, lam_o)
    coupling = np.array([[m11, m12], [m12, m22]])

    d_e = d_o = d_c = None
    alpha_e = alpha_o = alpha_sup
    c_o = None
    bound = sub = math.inf
    c_f = inputs.C_f
    if holds:
        m = alpha_sup
        # Max-margin split (attains α_e = A_o = m); δ_o → 0 is optimal when there is no e→obs coupling.
        d_e0 = (lam_e - m) * p / (a + p)
        d_o0 = (mu - m) * a / (a + p) if a > 0 else 1e-12 * max(mu, 1.0)

        def neg_log_phi(x: np.ndarray) -> float:
            al_e, a_o = _literal_margins(lam_e, mu, a, p, math.exp(x[0]), math.exp(x[1]))
            if al_e <= 0 or a_o <= 0:
                return 1e6
            return -math.log(_best_delta_c(al_e, a_o)[1])

        x0 = np.log([d_e0, d_o0])
        best = x0
        if a > 0:  # with a == 0 the bound does not depend on δ_o (take it tiny); optimise δ_e only
            res = scipy.optimize.minimize(neg_log_phi, x0, method="Nelder-Mead",
                                          options=dict(xatol=1e-8, fatol=1e-12, maxiter=2000))
            best = res.x if res.fun < neg_log_phi(x0) else x0
        else:
            res = scipy.optimize.minimize_scalar(lambda y: neg_log_phi(np.array([y, x0[1]])),
                                                 bracket=(x0[0] - 1.0, x0[0]), tol=1e-12)
            if res.fun < neg_log_phi(x0):
                best = np.array([res.x, x0[1]])
        d_e, d_o = float(math.exp(best[0])), float(math.exp(best[1]))
        alpha_e, a_o = _literal_margins(lam_e, mu, a, p, d_e, d_o)
        d_c, phi = _best_delta_c(alpha_e, a_o)
        alpha_o = a_o - d_c
        c_o = (c * c_f) ** 2 / d_c
        bound = math.sqrt(c_o / min(alpha_e, alpha_o))
        p_full = scipy.linalg.block_diag(t["P_e"], t["P_obs"])
        ev = np.linalg.eigvalsh(p_full)
        sub = bound * math.sqrt(ev[-1] / ev[0])
    return CertificateResult(
        method="literal", holds=bool(holds), lipschitz=inputs.lipschitz,
        alpha_e=float(alpha_e), alpha_o=float(alpha_o), alpha=float(min(alpha_e, alpha_o)),
        alpha_sup=float(alpha_sup), ultimate_bound=float(bound), ultimate_bound_sublevel=float(sub),
        max_certified_lipschitz=float(lmax), lambda_e=lam_e, lambda_o=lam_o, c_pb=c, pe_be_norm=p,
        lambda_c=inputs.lambda_c, gamma_e=inputs.gamma_e, gamma_etilde=inputs.gamma_etilde,
        C_z=inputs.C_z, C_f=c_f, C_o=c_o, delta_e=d_e, delta_o=d_o, delta_c=d_c, weight_s=1.0,
        kappa_e=1.0, kappa_o=1.0, coupling_matrix=coupling, P_e=t["P_e"], P_obs=t["P_obs"],
        Q_e=t["Q_e"], Q_obs=t["Q_obs"], scale_e=np.ones(2), scale_obs=np.ones(3), n_axes=inputs.n_axes,
        notes=(f"lambda_c_rule={inputs.lambda_c_rule}",
               "delta_e, delta_o, delta_c minimise sqrt(C_o/alpha) among valid certificates"),
    )
