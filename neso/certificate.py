"""Small-gain stability certificate of Neural-ESO (paper Section IV, Lemma 1 and Theorem 1).

Pure numpy/scipy, no I/O.

Error states (per axis; SI units, so the stacked vectors have mixed units):

* tracking ``e_state = [e, ė]``              (m, m/s),            dynamics ``ė_s = A_e e_s + B_e f̃``
* observer ``ẽ_obs  = [x̃1, x̃2, f̃]``         (m, m/s, m/s²),      dynamics ``ẽ̇ = A_obs ẽ + B_obs Δḟ``
* ``E = [e_state, ẽ_obs]``; ``‖E‖`` is the Euclidean norm of that mixed-unit vector.

Lemma 1: ``‖Δḟ‖ ≤ γ_e ‖e_state‖ + γ_ẽ ‖ẽ_obs‖ + C_f`` with ``γ_e = L_N λ_c``, ``γ_ẽ = L_N``,
``C_f = L_1 + L_N C_z``, ``C_z = L_u + ‖q̇*‖max + ‖q̈*‖max``.

**n axes.** With identical diagonal gains ``k_p I_n, k_d I_n, β_i I_n`` every matrix is a Kronecker product
``A ⊗ I_n``; eigenvalues, Lyapunov solutions' spectra and induced 2-norms are those of the 1-axis matrices, so the
n-axis certificate equals the 1-axis one (``L_N`` being the Lipschitz constant of the whole vector map ``f_N``).
The optimisers work per axis; :func:`verify_certificate` rebuilds the n-axis matrices and checks the claim.

**λ_c and a gap in the paper's Lemma 1.** ``ż`` contains ``ẋ1 = q̇* − ė``, whose ``‖ė‖`` the printed proof drops:
``‖ż‖ ≤ C_z + ‖ė‖ + ‖k_p e‖ + ‖k_d ė‖ + ‖f̃‖``. ``lambda_c_rule="corrected"`` (default) uses
``λ_c = sqrt(k_p² + (k_d+1)²)`` which covers that term (Cauchy–Schwarz); ``"paper"`` uses the printed
``λ_c = sqrt(k_p² + k_d²)`` to reproduce the paper literally.

**Units of L_N.** Physical Lipschitz constant of ``f_N`` in (m/s²) per unit of the mixed-SI input ``z``.
A network's normalised bound converts as ``L_phys = L_norm · σ_y / min_i σ_{z,i}``.

Two methods:

* ``literal`` — the paper's proof as written: ``Q_e = I``, ``Q_obs = I``, unit weights, separate Young splits with
  free ``δ_e, δ_o, δ_c``. Optimising ``δ_e, δ_o`` with ``δ_c → 0`` the supremum margin is exactly
  ``λ_min(M)`` of the 2×2 matrix ``M = [[λ_e, −(‖P_eB_e‖ + c_pb γ_e)], [·, λ_o − 2 c_pb γ_ẽ]]`` (the balanced split
  ``δ_e = (λ_e−m)p/(a+p)``, ``δ_o = (μ−m)a/(a+p)`` attains it), so the verdict is
  ``λ_e (λ_o − 2 c_pb L_N) > (‖P_eB_e‖ + c_pb λ_c L_N)²`` — closed form and monotone in ``L_N``
  (left side decreasing, right side increasing). ``δ_c`` only trades margin against the bound; the reported
  ``δ_e, δ_o, δ_c`` minimise the ultimate bound ``sqrt(C_o/α)`` among all valid certificates
  (``δ_c`` in closed form, ``δ_e, δ_o`` by Nelder–Mead in log space from the max-margin point).
* ``tight`` — same Lemma-1 bound, more freedom: diagonal scalings ``η = T_e e_state``, ``ξ = T_o ẽ_obs`` (bandwidth
  scaling), diagonal ``Q̄_e, Q̄_o`` in the scaled coordinates, weight ``V = s·ηᵀP̄_eη + ξᵀP̄_oξ``, and the 2×2
  positive-definiteness condition in ``(‖η‖, ‖ξ‖)`` instead of Young splits. Lemma 1 stays in unscaled norms and is
  converted with ``‖e_state‖ ≤ κ_e‖η‖``, ``‖ẽ_obs‖ ≤ κ_o‖ξ‖`` (``κ = 1/min diag T``) and ``|f̃| ≤ ‖ξ‖/t_o3``. The
  certified ``L_N`` of one parameter set is the root of a quadratic; it is maximised by multi-start Nelder–Mead.
  Every reported certificate is re-verified from its parameters by :func:`verify_certificate`.

Bounds reported (both in the mixed units of ``E``):

* ``ultimate_bound`` — the paper's radius: ``V̇ < 0`` whenever ``‖E‖`` exceeds it.
* ``ultimate_bound_sublevel`` — what trajectories eventually satisfy: the smallest sublevel set of ``V`` that
  contains that ball, ``‖E‖ ≤ r·sqrt(λ_max(P̄)/λ_min(P))`` (``P̄`` scaled, ``P`` unscaled Lyapunov matrix).
  Compare simulated ``‖E(t)‖`` against this one.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.optimize

Method = Literal["literal", "tight"]
METHODS: tuple[str, ...] = ("literal", "tight")

# Relative margin demanded of λ_min(M) so the verdict does not flip on rounding at the boundary.
_REL_TOL = 1e-9


# --------------------------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class CertificateInputs:
    """Everything the certificate depends on.

    Gains (per axis, identical on every axis):
        kp: proportional gain, 1/s². kd: derivative gain, 1/s.
        omega_o: observer bandwidth, rad/s; ``β = (3ω, 3ω², ω³)`` (triple pole at ``−ω``).
        lipschitz: ``L_N``, physical Lipschitz constant of ``f_N``, (m/s²) per unit of mixed-SI ``z``.
        n_axes: number of identical axes; does not change the result (see module docstring).

    Non-gain constants (they only move the ultimate bound, never the verdict):
        L_1: bound on ``‖ḟ‖`` of the true disturbance, m/s³. Default 5: the ground-effect fit
            ``ΔT/mg = 0.215 e^{−h/0.195}`` descending at 0.3 m/s through h = 0.1 m gives
            ``g·0.215/0.195·e^{−0.51}·0.3 ≈ 1.9 m/s³``; rounded up for turbulence and slope.
        L_u: bound on ``‖u̇‖`` of the control components of ``z`` (the increment saturation of paper Remark 2),
            in z-units per second ("m/s³ equivalent"). Default 20.
        ref_vel_max: bound on ``‖q̇*‖``, m/s. Default 0.5.
        ref_acc_max: bound on ``‖q̈*‖``, m/s². Default 1.0.
        lambda_c_rule: ``"corrected"`` (default, ``sqrt(kp²+(kd+1)²)``) or ``"paper"`` (``sqrt(kp²+kd²)``).
    """

    kp: float
    kd: float
    omega_o: float
    lipschitz: float
    n_axes: int = 1
    L_1: float = 5.0
    L_u: float = 20.0
    ref_vel_max: float = 0.5
    ref_acc_max: float = 1.0
    lambda_c_rule: Literal["corrected", "paper"] = "corrected"

    def __post_init__(self) -> None:
        for name in ("kp", "kd", "omega_o"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0 (Hurwitz gains), got {v!r}")
        for name in ("lipschitz", "L_1", "L_u", "ref_vel_max", "ref_acc_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        if int(self.n_axes) != self.n_axes or self.n_axes < 1:
            raise ValueError(f"n_axes must be a positive integer, got {self.n_axes!r}")
        if self.lambda_c_rule not in ("corrected", "paper"):
            raise ValueError(f"lambda_c_rule must be 'corrected' or 'paper', got {self.lambda_c_rule!r}")

    @property
    def lambda_c(self) -> float:
        """``λ_c`` with ``(‖ė‖ +) ‖k_p e‖ + ‖k_d ė‖ ≤ λ_c ‖e_state‖``, 1/s² (mixed)."""
        kd_eff = self.kd + 1.0 if self.lambda_c_rule == "corrected" else self.kd
        return math.hypot(self.kp, kd_eff)

    @property
    def gamma_e(self) -> float:
        return self.lipschitz * self.lambda_c

    @property
    def gamma_etilde(self) -> float:
        return self.lipschitz

    @property
    def C_z(self) -> float:
        return self.L_u + self.ref_vel_max + self.ref_acc_max

    @property
    def C_f(self) -> float:
        """``C_f = L_1 + L_N C_z``, m/s³."""
        return self.L_1 + self.lipschitz * self.C_z


# --------------------------------------------------------------------------------------------- matrices


def observer_gains(omega_o: float) -> tuple[float, float, float]:
    """``(β1, β2, β3) = (3ω, 3ω², ω³)``: all three observer poles at ``−ω_o``."""
    return 3.0 * omega_o, 3.0 * omega_o**2, omega_o**3


def tracking_matrices(kp: float, kd: float, n_axes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``A_e`` (2n×2n), ``B_e`` (2n×n) of ``ė_s = A_e e_s + B_e f̃`` with block order ``[e; ė]``."""
    a1 = np.array([[0.0, 1.0], [-kp, -kd]])
    b1 = np.array([[0.0], [-1.0]])
    eye = np.eye(n_axes)
    return np.kron(a1, eye), np.kron(b1, eye)


def observer_matrices(omega_o: float, n_axes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``A_obs`` (3n×3n), ``B_obs`` (3n×n) with block order ``[x̃1; x̃2; f̃]``."""
    b1, b2, b3 = observer_gains(omega_o)
    a1 = np.array([[-b1, 1.0, 0.0], [-b2, 0.0, 1.0], [-b3, 0.0, 0.0]])
    bb = np.array([[0.0], [0.0], [1.0]])
    eye = np.eye(n_axes)
    return np.kron(a1, eye), np.kron(bb, eye)


def solve_lyapunov(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``P`` with ``Aᵀ P + P A = −Q`` (scipy solves ``A X + X Aᴴ = Q``, hence the transpose), symmetrised."""
    p = scipy.linalg.solve_continuous_lyapunov(a.T, -q)
    return 0.5 * (p + p.T)


def lyapunov_residual(a: np.ndarray, p: np.ndarray, q: np.ndarray) -> float:
    """``‖Aᵀ P + P A + Q‖_F / ‖Q‖_F`` (dimensionless)."""
    return float(np.linalg.norm(a.T @ p + p @ a + q) / np.linalg.norm(q))


def _spec(m: np.ndarray) -> float:
    return float(np.linalg.norm(m, 2))


def _lambda_min_2x2(m11: float, m12: float, m22: float) -> float:
    return 0.5 * (m11 + m22) - math.sqrt(0.25 * (m11 - m22) ** 2 + m12**2)


def _max_root(a: float, p: float, c: float, lam_o: float, lam_c: float, kap_e: float, kap_o: float) -> float:
    """Largest ``L`` with ``a(λ_o − 2cκ_o L) ≥ (p + cλ_cκ_e L)²`` (0 if none): the certified ``L_N`` of one
    parameter set. The left side decreases and the right side increases in ``L`` (monotone verdict)."""
    qa = (c * lam_c * kap_e) ** 2
    qb = 2.0 * p * c * lam_c * kap_e + 2.0 * a * c * kap_o
    qc = p * p - a * lam_o
    if qc >= 0.0:
        return 0.0
    # Stable form of the positive root of qa L² + qb L + qc = 0.
    return (-2.0 * qc) / (qb + math.sqrt(qb * qb - 4.0 * qa * qc))


# --------------------------------------------------------------------------------------------- result


@dataclass(frozen=True, eq=False)
class CertificateResult:
    """One certificate: verdict, margins, bound and everything needed to re-check it.

    Margins ``alpha*`` multiply ``‖·‖²`` in ``V̇ ≤ −α_e‖e_s‖² − α_o‖ẽ‖² + C_o`` (literal) or in the scaled
    coordinates ``‖η‖², ‖ξ‖²`` (tight; there ``α_e = α_o = α = λ_min(M)``, the balanced split of the 2×2 form).
    Their scale depends on ``Q`` and is only meaningful together with ``ultimate_bound``.

    Matrices (per axis; the n-axis ones are ``X ⊗ I_n``): ``P_e`` (2×2) and ``P_obs`` (3×3) in UNSCALED
    coordinates so that ``V(E) = weight_s·e_sᵀP_e e_s + ẽᵀP_obs ẽ``; ``Q_e``, ``Q_obs`` are the Q's of the scaled
    Lyapunov equations; ``scale_e`` (2,), ``scale_obs`` (3,) the diagonal of ``T_e``, ``T_o`` (ones for literal).
    """

    method: str
    holds: bool
    lipschitz: float
    alpha_e: float
    alpha_o: float
    alpha: float
    alpha_sup: float  # supremum margin over the free constants (δ_c → 0); > 0 iff holds
    ultimate_bound: float  # V̇ < 0 outside this ‖E‖ ball, mixed SI (m, m/s, m/s²); inf if not holds
    ultimate_bound_sublevel: float  # eventual bound on ‖E‖ (sublevel set), mixed SI; inf if not holds
    max_certified_lipschitz: float  # physical units, (m/s²)/unit z
    lambda_e: float
    lambda_o: float
    c_pb: float  # ‖P̄_o T_o B_obs‖
    pe_be_norm: float  # ‖P̄_e T_e B_e‖ (without weight s)
    lambda_c: float
    gamma_e: float
    gamma_etilde: float
    C_z: float
    C_f: float
    C_o: float | None  # literal only: (c_pb C_f)²/δ_c
    delta_e: float | None  # literal only
    delta_o: float | None
    delta_c: float | None
    weight_s: float
    kappa_e: float
    kappa_o: float
    coupling_matrix: np.ndarray  # M (2×2), quadratic form in (‖η‖, ‖ξ‖)
    P_e: np.ndarray
    P_obs: np.ndarray
    Q_e: np.ndarray
    Q_obs: np.ndarray
    scale_e: np.ndarray
    scale_obs: np.ndarray
    n_axes: int = 1
    notes: tuple[str, ...] = field(default_factory=tuple)

    def to_json_dict(self) -> dict:
        """JSON-safe dict: arrays as nested lists, non-finite floats as ``None``."""

        def conv(v):
            if isinstance(v, np.ndarray):
                return [conv(x) for x in v.tolist()] if v.ndim else conv(v.item())
            if isinstance(v, list | tuple):
                return [conv(x) for x in v]
            if isinstance(v, bool | np.bool_):
                return bool(v)
            if isinstance(v, float | np.floating):
                return float(v) if math.isfinite(v) else None
            return v

        out = {k: conv(getattr(self, k)) for k in self.__dataclass_fields__}
        out["units"] = {
            "lipschitz": "(m/s^2) per unit of mixed-SI z",
            "ultimate_bound": "Euclidean norm of E=[e,de,x1~,x2~,f~] in mixed SI (m, m/s, m, m/s, m/s^2)",
            "C_f": "m/s^3",
        }
        return out


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


# --------------------------------------------------------------------------------------------- tight


@dataclass(frozen=True)
class TightParams:
    """Free parameters of the tight certificate (per axis; all > 0).

    scale_e (2,), scale_obs (3,): diagonals of ``T_e``, ``T_o`` (``η = T_e e_s``, ``ξ = T_o ẽ``);
    q_e (2,), q_obs (3,): diagonals of ``Q̄_e``, ``Q̄_o`` in scaled coordinates; weight_s: ``V = s V_e + V_o``.
    """

    scale_e: tuple[float, float]
    scale_obs: tuple[float, float, float]
    q_e: tuple[float, float]
    q_obs: tuple[float, float, float]
    weight_s: float

    @staticmethod
    def from_log(x: np.ndarray) -> "TightParams":
        """7 log-parameters; ``t_e1 = t_o3 = q_e1 = q_o3 = 1`` fix redundant overall scales."""
        e = np.exp(np.clip(x, -60.0, 60.0))
        return TightParams((1.0, e[0]), (e[1], e[2], 1.0), (1.0, e[3]), (e[4], e[5], 1.0), float(e[6]))


def _tight_terms(kp: float, kd: float, omega_o: float, prm: TightParams) -> dict:
    """Gain-only terms of the tight certificate for one parameter set (1 axis)."""
    a_e, b_e = tracking_matrices(kp, kd)
    a_o, b_o = observer_matrices(omega_o)
    te, to = np.asarray(prm.scale_e), np.asarray(prm.scale_obs)
    qe, qo = np.diag(prm.q_e), np.diag(prm.q_obs)
    pb_e = solve_lyapunov(te[:, None] * a_e / te[None, :], qe)
    pb_o = solve_lyapunov(to[:, None] * a_o / to[None, :], qo)
    return dict(
        Pbar_e=pb_e, Pbar_o=pb_o, Q_e=qe, Q_obs=qo, te=te, to=to,
        lambda_e=float(min(prm.q_e)), lambda_o=float(min(prm.q_obs)),
        pe_be=_spec(pb_e @ (te[:, None] * b_e)), c_pb=_spec(pb_o @ (to[:, None] * b_o)),
        kappa_e=float(1.0 / te.min()), kappa_o=float(1.0 / to.min()),
    )


def _tight_lmax(terms: dict, prm: TightParams, lam_c: float) -> float:
    a = prm.weight_s * terms["lambda_e"]
    p = prm.weight_s * terms["pe_be"] / terms["to"][2]
    return _max_root(a, p, terms["c_pb"], terms["lambda_o"], lam_c, terms["kappa_e"], terms["kappa_o"])


def _tight_quadratic(terms: dict, prm: TightParams, inputs: CertificateInputs) -> tuple[np.ndarray, float, float]:
    """``M`` (2×2), ``α = λ_min(M)`` and the decrease-ball radius ``κ · 2 c_pb C_f / α`` for ``inputs``."""
    s, c = prm.weight_s, terms["c_pb"]
    m11 = s * terms["lambda_e"]
    m12 = -(s * terms["pe_be"] / terms["to"][2] + c * inputs.gamma_e * terms["kappa_e"])
    m22 = terms["lambda_o"] - 2.0 * c * inputs.gamma_etilde * terms["kappa_o"]
    alpha = _lambda_min_2x2(m11, m12, m22)
    kappa = max(terms["kappa_e"], terms["kappa_o"])
    radius = kappa * 2.0 * c * inputs.C_f / alpha if alpha > 0 else math.inf
    return np.array([[m11, m12], [m12, m22]]), alpha, radius


def _start_points(kp: float, omega_o: float) -> list[np.ndarray]:
    lw = math.log(omega_o)
    bw = np.array([-0.5 * math.log(kp), 2 * lw, lw, 0.0, 0.0, 0.0, 0.0])  # bandwidth scaling
    pts = [np.zeros(7), bw]
    for ds in (-2.0, 2.0, 4.0):
        x = bw.copy()
        x[6] += ds
        pts.append(x)
    return pts


class _FastTight:
    """Cheap per-axis evaluation of the certified ``L_N`` for the optimiser.

    Uses ``P̄ = T⁻¹ P(T Q̄ T) T⁻¹`` (similarity scaling) and the linearity of ``Q ↦ P(Q)``: the unscaled solutions
    for ``Q = e_i e_iᵀ`` are computed once, so one evaluation is a few 3×3 products. Only the optimiser uses it;
    reported certificates are rebuilt with :func:`_tight_terms` and re-verified.
    """

    def __init__(self, kp: float, kd: float, omega_o: float, lam_c: float) -> None:
        a_e, b_e = tracking_matrices(kp, kd)
        a_o, b_o = observer_matrices(omega_o)
        self.basis_e = [solve_lyapunov(a_e, np.diag(np.eye(2)[i])) for i in range(2)]
        self.basis_o = [solve_lyapunov(a_o, np.diag(np.eye(3)[i])) for i in range(3)]
        self.b_e, self.b_o = b_e[:, 0], b_o[:, 0]
        self.lam_c = lam_c

    def lmax(self, x: np.ndarray) -> float:
        prm = TightParams.from_log(x)
        te, to = np.asarray(prm.scale_e), np.asarray(prm.scale_obs)
        w_e = te**2 * np.asarray(prm.q_e)
        w_o = to**2 * np.asarray(prm.q_obs)
        p_e = w_e[0] * self.basis_e[0] + w_e[1] * self.basis_e[1]
        p_o = w_o[0] * self.basis_o[0] + w_o[1] * self.basis_o[1] + w_o[2] * self.basis_o[2]
        pe_be = float(np.linalg.norm((p_e @ self.b_e) / te))  # ‖P̄_e T_e B_e‖ = ‖T_e⁻¹ P_e B_e‖
        c_pb = float(np.linalg.norm((p_o @ self.b_o) / to))
        a = prm.weight_s * min(prm.q_e)
        p = prm.weight_s * pe_be / to[2]
        return _max_root(a, p, c_pb, min(prm.q_obs), self.lam_c, 1.0 / te.min(), 1.0 / to.min())


@functools.lru_cache(maxsize=256)
def _optimise_tight(kp: float, kd: float, omega_o: float, lam_c: float) -> tuple[tuple[float, ...], float]:
    """Log-parameters maximising the certified ``L_N`` for these gains (independent of ``L_N`` and ``C_f``),
    and that maximum. Multi-start Nelder–Mead with restarts; never worse than the literal point (x = 0)."""
    fast = _FastTight(kp, kd, omega_o, lam_c)

    def obj(x: np.ndarray) -> float:
        lm = fast.lmax(x)
        return -math.log(lm) if lm > 0 else 1e3

    opts = dict(xatol=1e-7, fatol=1e-11, maxfev=3000, adaptive=True)
    runs = [scipy.optimize.minimize(obj, x0, method="Nelder-Mead", options=opts) for x0 in _start_points(kp, omega_o)]
    best = min(runs, key=lambda r: r.fun)
    for _ in range(4):  # restarts re-open the simplex; Nelder–Mead stalls otherwise
        r = scipy.optimize.minimize(obj, best.x, method="Nelder-Mead", options=opts)
        if r.fun >= best.fun - 1e-10:
            break
        best = r
    x = best.x if best.fun <= obj(np.zeros(7)) else np.zeros(7)
    # Recompute with the slow path so the reported maximum matches the certificate's own algebra.
    prm = TightParams.from_log(x)
    lmax = _tight_lmax(_tight_terms(kp, kd, omega_o, prm), prm, lam_c)
    return tuple(float(v) for v in x), float(lmax)


def certify_tight(inputs: CertificateInputs, *, optimise_bound: bool = True) -> CertificateResult:
    """Tighter certificate under the same Lemma-1 bound (see module docstring).

    The verdict uses the parameters maximising the certified ``L_N`` for these gains (so it is monotone in
    ``L_N``: ``holds ⇔ L_N < max_certified_lipschitz``). When it holds and ``optimise_bound`` is true the
    parameters are then refined to minimise ``ultimate_bound`` at this ``L_N``; a refinement is kept only if it
    still certifies. The returned certificate is re-verified by :func:`verify_certificate`.
    """
    lam_c = inputs.lambda_c
    x_star, lmax = _optimise_tight(float(inputs.kp), float(inputs.kd), float(inputs.omega_o), lam_c)
    x = np.array(x_star)

    def build(xv: np.ndarray):
        prm = TightParams.from_log(xv)
        terms = _tight_terms(inputs.kp, inputs.kd, inputs.omega_o, prm)
        m, alpha, radius = _tight_quadratic(terms, prm, inputs)
        return prm, terms, m, alpha, radius

    prm, terms, m, alpha, radius = build(x)
    holds = alpha > _REL_TOL * max(m[0, 0], abs(m[1, 1]))
    if holds and optimise_bound and inputs.C_f > 0:

        def obj(xv: np.ndarray) -> float:
            try:
                _, _, mm, al, rad = build(xv)
            except (np.linalg.LinAlgError, ValueError):
                return 1e6
            ok = al > _REL_TOL * max(mm[0, 0], abs(mm[1, 1]))
            return math.log(rad) if ok else 1e6

        res = scipy.optimize.minimize(obj, x, method="Nelder-Mead",
                                      options=dict(xatol=1e-6, fatol=1e-9, maxfev=600, adaptive=True))
        if res.fun < obj(x):
            x = res.x
            prm, terms, m, alpha, radius = build(x)

    result = _tight_result(inputs, prm, terms, m, alpha, radius, holds, lmax)
    if holds and not verify_certificate(inputs, result):
        # Never report an unverified 'holds' (an optimiser or algebra bug must not produce a false verdict).
        result = _tight_result(inputs, prm, terms, m, alpha, math.inf, False, lmax,
                               extra_note="independent re-verification failed; verdict withdrawn")
    return result


def _tight_result(inputs, prm, terms, m, alpha, radius, holds, lmax, extra_note=None) -> CertificateResult:
    te, to = terms["te"], terms["to"]
    s = prm.weight_s
    # Unscaled Lyapunov matrices: V = s e_sᵀ(T_e P̄_e T_e)e_s + ẽᵀ(T_o P̄_o T_o)ẽ.
    p_e = te[:, None] * terms["Pbar_e"] * te[None, :]
    p_o = to[:, None] * terms["Pbar_o"] * to[None, :]
    sub = math.inf
    if holds:
        pbar = scipy.linalg.block_diag(s * terms["Pbar_e"], terms["Pbar_o"])
        p_full = scipy.linalg.block_diag(s * p_e, p_o)
        r_scaled = radius / max(terms["kappa_e"], terms["kappa_o"])
        sub = r_scaled * math.sqrt(np.linalg.eigvalsh(pbar)[-1] / np.linalg.eigvalsh(p_full)[0])
    notes = [f"lambda_c_rule={inputs.lambda_c_rule}",
             "alpha_e = alpha_o = lambda_min(M) (balanced split); bound radius = kappa*2*c_pb*C_f/alpha"]
    if extra_note:
        notes.append(extra_note)
    return CertificateResult(
        method="tight", holds=bool(holds), lipschitz=inputs.lipschitz,
        alpha_e=float(alpha), alpha_o=float(alpha), alpha=float(alpha), alpha_sup=float(alpha),
        ultimate_bound=float(radius if holds else math.inf), ultimate_bound_sublevel=float(sub),
        max_certified_lipschitz=float(lmax), lambda_e=terms["lambda_e"], lambda_o=terms["lambda_o"],
        c_pb=terms["c_pb"], pe_be_norm=terms["pe_be"], lambda_c=inputs.lambda_c, gamma_e=inputs.gamma_e,
        gamma_etilde=inputs.gamma_etilde, C_z=inputs.C_z, C_f=inputs.C_f, C_o=None,
        delta_e=None, delta_o=None, delta_c=None, weight_s=s,
        kappa_e=terms["kappa_e"], kappa_o=terms["kappa_o"], coupling_matrix=m, P_e=p_e, P_obs=p_o,
        Q_e=terms["Q_e"], Q_obs=terms["Q_obs"], scale_e=te.copy(), scale_obs=to.copy(),
        n_axes=inputs.n_axes, notes=tuple(notes),
    )


# --------------------------------------------------------------------------------------------- public API


def certify(inputs: CertificateInputs, method: Method = "tight") -> CertificateResult:
    """Dispatch to :func:`certify_literal` or :func:`certify_tight`."""
    if method == "literal":
        return certify_literal(inputs)
    if method == "tight":
        return certify_tight(inputs)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def max_certified_lipschitz(inputs: CertificateInputs, method: Method = "tight", *, rel_tol: float = 1e-10) -> float:
    """Largest ``L_N`` (physical units) for which ``certify(...).holds`` is true, by bisection on the verdict.

    The verdict is monotone in ``L_N`` (module docstring), so bisection is exact up to ``rel_tol``; the result
    agrees with the closed-form ``CertificateResult.max_certified_lipschitz``. Returns 0.0 if even ``L_N = 0``
    fails (impossible for positive gains).
    """
    from dataclasses import replace

    def ok(lip: float) -> bool:
        inp = replace(inputs, lipschitz=lip)
        if method == "tight":
            return certify_tight(inp, optimise_bound=False).holds
        return certify(inp, method).holds

    if not ok(0.0):
        return 0.0
    lo, hi = 0.0, 1.0
    while ok(hi):
        lo, hi = hi, 2.0 * hi
        if hi > 1e12:
            return math.inf
    while hi - lo > rel_tol * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


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


def largest_certified_lipschitz(kp: float, kd: float, omega_o: float) -> float:
    """The largest physical ``L_N`` ((m/s²) per unit z) the certificate allows for these gains
    (1/s², 1/s, rad/s): the verdict holds for every smaller bound. Cached per gains."""
    return certify_tight(CertificateInputs(kp=kp, kd=kd, omega_o=omega_o, lipschitz=0.0),
                         optimise_bound=False).max_certified_lipschitz


@dataclass(frozen=True)
class FlightCertificate:
    """The verdict for what flies: a network's certified physical Lipschitz constant against the
    largest the certificate allows for the z gains and observer bandwidth.

    ``lipschitz_phys``, ``max_certified``: (m/s²) per unit z. ``kp`` 1/s², ``kd`` 1/s, ``omega_o`` rad/s.
    ``margin``: ``max_certified − lipschitz_phys`` (> 0 iff it holds).
    """

    holds: bool
    lipschitz_phys: float
    max_certified: float
    kp: float
    kd: float
    omega_o: float

    @property
    def margin(self) -> float:
        return self.max_certified - self.lipschitz_phys

    def text(self) -> str:
        verdict = "holds" if self.holds else "FAILS"
        rel = self.margin / self.max_certified * 100 if self.max_certified > 0 else float("-inf")
        return (f"certificate {verdict}: L_N {self.lipschitz_phys:.4g} (m/s²)/unit z physical vs {self.max_certified:.4g} "
                f"certified for kp {self.kp:g}, kd {self.kd:g}, ω_o {self.omega_o:g} (margin {self.margin:+.4g}, {rel:+.0f} %)")

    def to_dict(self) -> dict:
        return {"holds": self.holds, "lipschitz_phys": self.lipschitz_phys, "max_certified": self.max_certified,
                "margin": self.margin, "kp": self.kp, "kd": self.kd, "omega_o": self.omega_o, "text": self.text()}


def flight_certificate(lipschitz_phys: float, *, kp: float, kd: float, omega_o: float) -> FlightCertificate:
    """The certificate for a network of physical Lipschitz constant ``lipschitz_phys`` flown with these
    z gains (the planar axes carry no network: ``L_N = 0`` there, which every positive gain certifies)."""
    lmax = largest_certified_lipschitz(float(kp), float(kd), float(omega_o))
    return FlightCertificate(bool(lipschitz_phys < lmax), float(lipschitz_phys), float(lmax), float(kp), float(kd),
                             float(omega_o))
