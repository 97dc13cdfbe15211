"""The certificate's inputs, the error systems' matrices, the result type and the numeric checks every method shares
(the package docstring derives them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.linalg

Method = Literal["literal", "tight", "lmi"]
METHODS: tuple[str, ...] = ("literal", "tight", "lmi")

# Relative margin demanded of λ_min(M) so the verdict does not flip on rounding at the boundary.
_REL_TOL = 1e-9


# --------------------------------------------------------------------------------------------- inputs


#: The non-gain constants' defaults (they move the ultimate bound, never the verdict; CertificateInputs says why).
L1_MPS3 = 5.0
LU_PER_S = 20.0
REF_VEL_MAX_MPS = 0.5
REF_ACC_MAX_MPS2 = 1.0
# The z reference every mission of the runtime stays inside (flight.mission.segment_reference_bounds: a 0.4 m
# transit over its 1 s minimum is the steepest), what the flight certificate's envelope takes
MISSION_VEL_MAX_MPS = 0.75
MISSION_ACC_MAX_MPS2 = 2.4
MISSION_JERK_MAX_MPS3 = 24.0


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
    L_1: float = L1_MPS3
    L_u: float = LU_PER_S
    ref_vel_max: float = REF_VEL_MAX_MPS
    ref_acc_max: float = REF_ACC_MAX_MPS2
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
    Their scale depends on ``Q`` and is only meaningful together with ``ultimate_bound``. For ``lmi`` all four
    are the decay rate ``α`` (1/s) of ``V̇ ≤ −αV + μC_f²``; ``lambda_e``, ``lambda_o``, ``c_pb``, ``pe_be_norm``
    do not apply (NaN) and ``coupling_matrix`` is the assembled 8×8 matrix inequality.

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
    # lmi only: per-axis composite P (5×5, unscaled, V = EᵀPE; P_e, P_obs above are its diagonal blocks and
    # Q_e, Q_obs what those blocks' Lyapunov equations give), S-procedure multipliers (τ_e, τ_ẽ), μ of
    # V̇ ≤ −αV + μC_f² (α = alpha, 1/s), the P structure ("block" | "full"), and the solver time spent (s)
    P: np.ndarray | None = None
    multipliers: tuple[float, float] | None = None
    mu: float | None = None
    structure: str | None = None
    solve_time_s: float | None = None

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



def composite_matrices(kp: float, kd: float, omega_o: float, n_axes: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (5n×5n), ``B`` (5n×n) of ``Ė = A E + B Δḟ`` with ``E = [e_state; ẽ_obs]``: ``A = [[A_e, B_e S], [0,
    A_obs]]``, ``S`` picking ``f̃`` out of ``ẽ_obs`` (the paper's two subsystems, cascaded through ``f̃``)."""
    a_e, b_e = tracking_matrices(kp, kd, n_axes)
    a_o, b_o = observer_matrices(omega_o, n_axes)
    n = n_axes
    pick_f = np.kron(np.array([[0.0, 0.0, 1.0]]), np.eye(n))
    a = np.block([[a_e, b_e @ pick_f], [np.zeros((3 * n, 2 * n)), a_o]])
    return a, np.vstack([np.zeros((2 * n, n)), b_o])


def negative_margin(m: np.ndarray, err: np.ndarray | None = None) -> float:
    """How surely ``M ≺ 0``: ``−λ_max(D M D)`` less the rounding slack, with ``D = diag(|M_ii|^{-1/2})`` (so
    ``D M D`` has unit diagonal; a congruence, so the sign pattern of the eigenvalues is that of ``M``). The slack
    is ``‖D err D‖_F`` (assembly error, Weyl) plus ``n·eps·‖D M D‖_F`` (eigensolver). ``−inf`` if a diagonal entry
    is not negative or anything is not finite; ``M ≺ 0`` is proven when the result is > 0."""
    d = -np.diag(m)
    if not np.all(np.isfinite(m)) or np.any(d <= 0):
        return -math.inf
    s = 1.0 / np.sqrt(d)
    ms = m * np.outer(s, s)
    lam = float(np.linalg.eigvalsh(0.5 * (ms + ms.T))[-1])
    slack = m.shape[0] * np.finfo(float).eps * float(np.linalg.norm(ms))
    if err is not None:
        slack += float(np.linalg.norm(err * np.outer(s, s)))
    return -lam - slack


def bisect_verified(ok, lo: float, hi: float, best, rel_tol: float):
    """``(largest value, its certificate)`` of a bisection on ``ok(value)`` (a certificate that verified, or None)
    between ``lo``, where ``best`` verified, and ``hi``, to relative resolution ``rel_tol``. ``ok`` must be
    monotone (a certificate at ``L`` is one at every smaller ``L``): the result is the last value that verified,
    never a bracket end."""
    while hi - lo > rel_tol * hi:
        mid = 0.5 * (lo + hi)
        cert = ok(mid)
        if cert is None:
            hi = mid
        else:
            best, lo = cert, mid
    return lo, best
