"""Independent re-verification of the literal and tight certificates (and the LMI's, by :func:`verify_lmi`).
"""
from __future__ import annotations

import math

import numpy as np

from neso.certificate.core import CertificateInputs, CertificateResult, observer_matrices, tracking_matrices
from neso.certificate.lmi import verify_lmi

def _solve_lyapunov_kron(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``Aᵀ P + P A = −Q`` by the vectorised linear system (independent of scipy's Bartels–Stewart)."""
    n = a.shape[0]
    eye = np.eye(n)
    big = np.kron(eye, a.T) + np.kron(a.T, eye)
    p = np.linalg.solve(big, -q.reshape(-1, order="F")).reshape((n, n), order="F")
    return 0.5 * (p + p.T)


def verify_certificate(inputs: CertificateInputs, result: CertificateResult, *, rtol: float = 1e-6) -> bool:
    """Re-check a certificate from its stated parameters only (n-axis matrices, Kronecker Lyapunov solve).

    Recomputes ``P``'s from ``Q``'s and scalings, the coupling terms and the inequalities, and checks that the
    reported margins and bound are no better than the recomputed ones. Returns True iff ``result`` claims
    ``holds`` and that claim is justified (so ``holds=False`` results return False).
    """
    if not result.holds:
        return False
    if result.method == "lmi":
        return verify_lmi(inputs, result, rtol=rtol)
    n = inputs.n_axes
    eye = np.eye(n)
    a_e, b_e = tracking_matrices(inputs.kp, inputs.kd, n)
    a_o, b_o = observer_matrices(inputs.omega_o, n)
    te = np.kron(np.asarray(result.scale_e), np.ones(n))
    to = np.kron(np.asarray(result.scale_obs), np.ones(n))
    if np.any(te <= 0) or np.any(to <= 0):
        return False
    qe, qo = np.kron(result.Q_e, eye), np.kron(result.Q_obs, eye)
    if np.linalg.eigvalsh(qe)[0] <= 0 or np.linalg.eigvalsh(qo)[0] <= 0:
        return False
    abar_e = np.diag(te) @ a_e @ np.diag(1 / te)
    abar_o = np.diag(to) @ a_o @ np.diag(1 / to)
    pb_e, pb_o = _solve_lyapunov_kron(abar_e, qe), _solve_lyapunov_kron(abar_o, qo)
    if np.linalg.eigvalsh(pb_e)[0] <= 0 or np.linalg.eigvalsh(pb_o)[0] <= 0:
        return False
    lam_e, lam_o = np.linalg.eigvalsh(qe)[0], np.linalg.eigvalsh(qo)[0]
    p = np.linalg.norm(pb_e @ np.diag(te) @ b_e, 2)
    c = np.linalg.norm(pb_o @ np.diag(to) @ b_o, 2)
    # |f̃| ≤ ‖ξ‖ / t_o3 for every axis block.
    inv_t3 = 1.0 / np.asarray(result.scale_obs)[2]
    k_e, k_o = 1.0 / te.min(), 1.0 / to.min()
    s = result.weight_s
    g_e, g_o, c_f = inputs.gamma_e, inputs.gamma_etilde, inputs.C_f
    if result.method == "literal":
        if not (np.allclose(te, 1) and np.allclose(to, 1) and s == 1.0):
            return False
        d_e, d_o, d_c = result.delta_e, result.delta_o, result.delta_c
        if d_e is None or d_o is None or d_c is None or min(d_e, d_o, d_c) <= 0:
            return False
        al_e = lam_e - d_e - (c * g_e) ** 2 / d_o
        al_o = lam_o - (2 * c * g_o + d_o + d_c) - p**2 / d_e
        if al_e <= 0 or al_o <= 0:
            return False
        bound = math.sqrt((c * c_f) ** 2 / d_c / min(al_e, al_o))
        return result.ultimate_bound >= bound * (1 - rtol) and min(result.alpha_e, result.alpha_o) <= min(
            al_e, al_o) * (1 + rtol)
    m11 = s * lam_e
    m12 = -(s * p * inv_t3 + c * g_e * k_e)
    m22 = lam_o - 2 * c * g_o * k_o
    mm = np.array([[m11, m12], [m12, m22]])
    try:
        np.linalg.cholesky(mm)
    except np.linalg.LinAlgError:
        return False
    alpha = np.linalg.eigvalsh(mm)[0]
    if alpha <= 0:
        return False
    bound = max(k_e, k_o) * 2 * c * c_f / alpha
    return result.ultimate_bound >= bound * (1 - rtol) and result.alpha <= alpha * (1 + rtol)
