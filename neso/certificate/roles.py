"""``roles``: the small-gain certificate with each network input in its role (sharper than Lemma 1).

Same closed loop as the paper's Theorem 1 (z axis; ``E = [e, ė, x̃1, x̃2, f̃]``, ``Ė = A E + B Δḟ``,
:func:`neso.certificate.core.composite_matrices`), same conclusion (``E`` uniformly ultimately bounded),
but ``Δḟ = ḟ − ḟ_N`` is not bounded through ``‖ż‖`` as a whole. The network's inputs play two roles:

* the **tracked state** of its axis, ``p_z`` and ``v_z`` (:attr:`neso.features.FeatureSet.state_columns`):
  their rates are the loop's own, ``ṗ_z = ż* − ė`` and ``v̇_z = z̈* + k_p e + k_d ė + f̃`` (the error
  dynamics ``ë = −k_p e − k_d ė − f̃``), exactly — no triangle inequality, no ``x̃1, x̃2``;
* **exogenous** inputs (attitude, thrust, horizontal speed): their rates are bounded by a constant
  (``exo_rate_max``: the force-increment limit of paper Remark 2 through the inner loop, as for the
  thrust in Assumption 2); they enter only the constant, never the loop gain.

With ``g = (∂f_N/∂p_z, ∂f_N/∂v_z)`` along the trajectory (a Clarke gradient: ``‖g‖ ≤ L_s``, the
network's Lipschitz constant in the state inputs alone, :meth:`LipschitzMLP.certified_lipschitz_state`)::

    Δḟ = φ + w,   φ = −g · (C E),   C = [[0, −1, 0, 0, 0], [k_p, k_d, 0, 0, 1]]   (rows: −ė, v̇_z − z̈*)
    |φ| ≤ L_s ‖C E‖,   |w| ≤ C_f = L_1 + L_s ‖(ż*, z̈*)‖max + L_x · exo_rate_max

(``w = ḟ − g_p ż* − g_v z̈* − g_x ẋ_exo``; ``L_x`` the Lipschitz constant in the exogenous inputs). This
is one norm-bounded uncertainty on the LTI system ``(A, B, C)``: a quadratic ``V = EᵀPE`` with
``V̇ ≤ 0`` for ``w = 0`` exists iff ``L_s ‖C(sI − A)⁻¹B‖_∞ < 1`` (bounded-real lemma), so the largest
certified ``L_s`` is ``1/‖G‖_∞`` exactly, found by Hamiltonian bisection. The certificates themselves
come from SDPs (cvxpy + Clarabel, as the ``lmi`` method; imported lazily) and are never trusted: the LMI

    [[AᵀP + PA + αP + τL_s²CᵀC, PB, PB], [BᵀP, −τ, 0], [BᵀP, 0, −μ]] ⪯ 0,   P ≻ 0

(S-procedure multiplier ``τ``) is rebuilt and checked in numpy with rounding slack
(:func:`neso.certificate.core.negative_margin`), giving ``V̇ ≤ −αV + μ w²`` and the eventual bound
``‖E‖ ≤ C_f sqrt(μ/(α λ_min P))``. The largest ``L_s`` the services use is the largest whose SDP
certificate verified (bisection below ``1/‖G‖_∞``; within 2e-5 of it on the gain grid of ``neso certify --frontier``). At k_p 10, k_d 6, ω_o 15 it certifies ``L_s`` up to 7.40 against the
LMI's 1.66 under Lemma 1 (docs/certificate.md).
"""
from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from neso.certificate.core import (L1_MPS3, LU_PER_S, REF_ACC_MAX_MPS2, REF_VEL_MAX_MPS, bisect_verified,
                                   composite_matrices, negative_margin)

_EPS = np.finfo(float).eps
_MARGIN = 1e-9  # demanded Jacobi-scaled margin of the matrix inequalities, after rounding slack


def role_matrices(kp: float, kd: float, omega_o: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A`` (5×5), ``B`` (5×1) of the composite error system and ``C`` (2×5): the state inputs' rates that
    depend on ``E`` (``−ė`` and ``k_p e + k_d ė + f̃``)."""
    a, b = composite_matrices(kp, kd, omega_o)
    c = np.array([[0.0, -1.0, 0.0, 0.0, 0.0], [kp, kd, 0.0, 0.0, 1.0]])
    return a, b, c


def _imaginary_eigenvalue(h: np.ndarray, tol: float = 1e-9) -> bool:
    ev = np.linalg.eigvals(h)
    return bool(np.any(np.abs(ev.real) <= tol * max(1.0, float(np.max(np.abs(ev))))))


def hinf_norm(a: np.ndarray, b: np.ndarray, c: np.ndarray, *, rtol: float = 1e-10) -> float:
    """``‖C(sI − A)⁻¹B‖_∞`` of a stable ``A``: bisection on ``γ`` with the Hamiltonian test (``γ`` is above
    the norm iff ``[[A, BBᵀ/γ²], [−CᵀC, −Aᵀ]]`` has no eigenvalue on the imaginary axis), bracketed by a
    frequency sweep (a lower bound)."""
    if np.max(np.linalg.eigvals(a).real) >= 0:
        raise ValueError("A is not Hurwitz")
    n = a.shape[0]
    w = np.concatenate([[0.0], np.logspace(-4, 5, 400)])
    lo = max(float(np.linalg.norm(c @ np.linalg.solve(1j * x * np.eye(n) - a, b), 2)) for x in w)
    hi = max(2.0 * lo, 1e-12)

    def above(gamma: float) -> bool:
        h = np.block([[a, b @ b.T / gamma ** 2], [-c.T @ c, -a.T]])
        return not _imaginary_eigenvalue(h)

    while not above(hi):
        lo, hi = hi, 2.0 * hi
    while hi - lo > rtol * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if above(mid) else (mid, hi)
    return hi


@functools.lru_cache(maxsize=256)
def max_certified_state_lipschitz(kp: float, kd: float, omega_o: float) -> float:
    """The largest Lipschitz constant in the state inputs, ((m/s²) per unit z), the role certificate allows
    for gains ``kp`` (1/s²), ``kd`` (1/s), ``omega_o`` (rad/s): ``1/‖G‖_∞`` (module docstring). A value
    below it certifies (bounded-real lemma); the services use the largest that verified,
    :func:`max_certified_state_lipschitz_verified`."""
    a, b, c = role_matrices(float(kp), float(kd), float(omega_o))
    return 1.0 / hinf_norm(a, b, c)


@dataclass(frozen=True)
class RoleInputs:
    """``lipschitz_state`` ``L_s`` and ``lipschitz_exo`` ``L_x``: the network's physical Lipschitz constants
    in its state and its exogenous inputs, (m/s²) per unit z. ``exo_rate_max``: bound on the exogenous
    inputs' rate (z units per second; default 20 as Lemma 1's ``L_u``). ``L_1`` (m/s³), ``ref_vel_max``
    (m/s), ``ref_acc_max`` (m/s²): as :class:`neso.certificate.CertificateInputs`."""

    kp: float
    kd: float
    omega_o: float
    lipschitz_state: float
    lipschitz_exo: float = 0.0
    L_1: float = L1_MPS3
    exo_rate_max: float = LU_PER_S
    ref_vel_max: float = REF_VEL_MAX_MPS
    ref_acc_max: float = REF_ACC_MAX_MPS2

    def __post_init__(self) -> None:
        for name in ("kp", "kd", "omega_o"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("lipschitz_state", "lipschitz_exo", "L_1", "exo_rate_max", "ref_vel_max", "ref_acc_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")

    @property
    def C_f(self) -> float:
        """``|w|`` bound, m/s³ (module docstring)."""
        return (self.L_1 + self.lipschitz_state * math.hypot(self.ref_vel_max, self.ref_acc_max)
                + self.lipschitz_exo * self.exo_rate_max)


@dataclass(frozen=True, eq=False)
class RoleCertificate:
    """The verdict and the certificate's data: ``P`` (5×5), the S-procedure multiplier ``tau``, decay rate
    ``alpha`` (1/s) and input gain ``mu`` of ``V̇ ≤ −αV + μw²``, the eventual bound on ‖E‖ (mixed SI; inf if it
    does not hold or was not computed), the margin the numpy check found. ``max_certified``: the largest
    verified ``L_s`` for these gains."""

    holds: bool
    lipschitz_state: float
    lipschitz_exo: float
    max_certified: float
    C_f: float
    ultimate_bound: float
    P: np.ndarray | None = None
    tau: float = math.nan
    alpha: float = math.nan
    mu: float = math.nan
    margin: float = -math.inf
    notes: tuple[str, ...] = field(default_factory=tuple)

    method = "roles"

    def to_json_dict(self) -> dict:
        def conv(v):
            if isinstance(v, np.ndarray):
                return [conv(x) for x in v.tolist()]
            if isinstance(v, list | tuple):
                return [conv(x) for x in v]
            if isinstance(v, float):
                return v if math.isfinite(v) else None
            return v

        out = {k: conv(getattr(self, k)) for k in self.__dataclass_fields__}
        out.update(method="roles", max_certified_lipschitz=conv(self.max_certified), alpha_e=conv(self.alpha),
                   alpha_o=conv(self.alpha))
        out["units"] = {"lipschitz": "(m/s^2) per unit of the inputs' mixed SI units", "C_f": "m/s^3",
                        "ultimate_bound": "Euclidean norm of E=[e,de,x1~,x2~,f~] in mixed SI"}
        return out


def role_lmi(inputs: RoleInputs, p: np.ndarray, tau: float, alpha: float = 0.0,
             mu: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The S-procedure matrix (module docstring) for a 5×5 ``P`` and multiplier ``τ``: 6×6 without the ``w``
    input (``mu is None``, the verdict) or 7×7 with it, and an elementwise bound on its assembly error."""
    a, b, c = role_matrices(inputs.kp, inputs.kd, inputs.omega_o)
    cc = inputs.lipschitz_state ** 2 * (c.T @ c)
    top = a.T @ p + p @ a + alpha * p + tau * cc
    pb = p @ b
    size = 6 if mu is None else 7
    m = np.zeros((size, size))
    m[:5, :5] = 0.5 * (top + top.T)
    m[:5, 5:6], m[5:6, :5], m[5, 5] = pb, pb.T, -tau
    if mu is not None:
        m[:5, 6:7], m[6:7, :5], m[6, 6] = pb, pb.T, -mu
    ap, ab = np.abs(a), np.abs(p)
    err = np.zeros_like(m)
    err[:5, :5] = ap.T @ ab + ab @ ap + abs(alpha) * ab + tau * np.abs(cc)
    for j in range(5, size):
        err[:5, j:j + 1] = ab @ np.abs(b)
        err[j:j + 1, :5] = err[:5, j:j + 1].T
    return m, (size + 4) * _EPS * err


def _check(inputs: RoleInputs, p: np.ndarray, tau: float, alpha: float = 0.0, mu: float | None = None) -> float:
    """min(margin of the matrix inequality, margin of P ≻ 0), with rounding slack; > _MARGIN: verified."""
    if not (tau >= 0 and alpha >= 0 and (mu is None or mu >= 0) and np.all(np.isfinite(p))
            and np.allclose(p, p.T, rtol=1e-12, atol=0)):
        return -math.inf
    m, err = role_lmi(inputs, p, tau, alpha, mu)
    return min(negative_margin(m, err), negative_margin(-p, 4 * _EPS * np.abs(p)))


class _Programs:
    """The two SDPs in bandwidth-scaled coordinates (:func:`neso.certificate.lmi._lmi_scaling`), compiled once:
    ``feasibility`` (max ``t``: ``M ⪯ −tI``, ``P ⪰ tI``, ``tr P + τ = 1``) and ``bound`` (min ``μ`` at a decay rate
    ``α`` with unscaled ``P ⪰ I``). Not thread-safe: callers hold ``_LOCK``."""

    def __init__(self) -> None:
        import cvxpy as cp

        self.abar, self.bbar = cp.Parameter((5, 5)), cp.Parameter((5, 1))
        self.cc = cp.Parameter((5, 5), PSD=True)
        self.alpha = cp.Parameter(nonneg=True)
        self.p_floor = cp.Parameter(5, nonneg=True)
        self.p = cp.Variable((5, 5), symmetric=True)
        self.tau, self.t, self.mu = cp.Variable(nonneg=True), cp.Variable(), cp.Variable(nonneg=True)
        pb = self.p @ self.bbar
        core = self.abar.T @ self.p + self.p @ self.abar + self.tau * self.cc
        z = np.zeros((1, 1))

        def col(v):
            return cp.reshape(v, (1, 1), order="C")

        m2 = cp.bmat([[core, pb], [pb.T, -col(self.tau)]])
        m3 = cp.bmat([[core + self.alpha * self.p, pb, pb], [pb.T, -col(self.tau), z], [pb.T, z, -col(self.mu)]])
        self.feasibility = cp.Problem(cp.Maximize(self.t), [0.5 * (m2 + m2.T) << -self.t * np.eye(6),
                                                          self.p >> self.t * np.eye(5),
                                                          cp.trace(self.p) + self.tau == 1])
        self.bound = cp.Problem(cp.Minimize(self.mu), [0.5 * (m3 + m3.T) << 0, self.p >> cp.diag(self.p_floor)])

    def load(self, inputs: RoleInputs) -> np.ndarray:
        from neso.certificate.lmi import _lmi_scaling

        a, b, c = role_matrices(inputs.kp, inputs.kd, inputs.omega_o)
        t = _lmi_scaling(inputs.kp, inputs.omega_o)
        self.abar.value = t[:, None] * a / t[None, :]
        self.bbar.value = t[:, None] * b
        cbar = c / t[None, :]
        cc = inputs.lipschitz_state ** 2 * (cbar.T @ cbar)
        self.cc.value = 0.5 * (cc + cc.T)
        self.p_floor.value = 1.0 / t ** 2
        return t

    def solution(self, t: np.ndarray) -> tuple[np.ndarray, float] | None:
        if self.p.value is None or self.tau.value is None:
            return None
        p = 0.5 * (self.p.value + self.p.value.T)
        return t[:, None] * p * t[None, :], float(self.tau.value)


_LOCK = threading.Lock()


@functools.lru_cache(maxsize=1)
def _programs() -> _Programs:
    return _Programs()


@dataclass(frozen=True)
class _Frontier:
    lmax: float  # the largest L_s whose certificate verified
    exact: float  # 1/‖G‖_∞
    p: np.ndarray | None
    tau: float


_ADOPTED: dict[tuple[float, float, float], _Frontier] = {}  # frontiers found before, verified here (adopt_frontier)


def adopt_frontier(kp: float, kd: float, omega_o: float, lmax: float, p, tau: float) -> bool:
    """Take a frontier found before — the largest ``L_s`` ``lmax`` and its certificate ``(P (5×5), τ)`` — for
    these gains without solving an SDP, iff it verifies here in numpy exactly as the bisection's own do (and
    ``lmax`` is below the exact ``1/‖G‖_∞``). False, and nothing adopted, otherwise. Call before the gains'
    first :func:`max_certified_state_lipschitz_verified`; the certificate is only ever as good as this check."""
    key = (float(kp), float(kd), float(omega_o))
    try:
        p = np.array(p, dtype=float)
        lmax, tau = float(lmax), float(tau)
        inputs = RoleInputs(*key, lipschitz_state=lmax)
    except (TypeError, ValueError):
        return False
    if p.shape != (5, 5) or not (0.0 < lmax <= max_certified_state_lipschitz(*key)) \
            or not _check(inputs, p, tau) > _MARGIN:
        return False
    _ADOPTED[key] = _Frontier(lmax, max_certified_state_lipschitz(*key), p, tau)
    return True


def frontier_certificate(kp: float, kd: float, omega_o: float) -> tuple[float, np.ndarray | None, float]:
    """``(lmax, P, τ)`` of the gains' verified frontier (solved, or adopted), for :func:`adopt_frontier` later."""
    f = _frontier(float(kp), float(kd), float(omega_o))
    return f.lmax, f.p, f.tau


@functools.lru_cache(maxsize=256)
def _frontier(kp: float, kd: float, omega_o: float) -> _Frontier:
    """An adopted frontier (:func:`adopt_frontier`), else bisection on "the SDP at L_s is strictly feasible and
    its (P, τ) verifies in numpy" below 1/‖G‖_∞ (monotone: a certificate at L is one at every smaller L), to a
    relative 1e-6."""
    from neso.certificate.lmi import _lmi_solve

    if (kp, kd, omega_o) in _ADOPTED:
        return _ADOPTED[(kp, kd, omega_o)]
    exact = max_certified_state_lipschitz(kp, kd, omega_o)
    with _LOCK:
        prog = _programs()

        def ok(lip: float):
            inputs = RoleInputs(kp, kd, omega_o, lipschitz_state=lip)
            t = prog.load(inputs)
            if not _lmi_solve(prog.feasibility) or not (prog.t.value is not None and prog.t.value > 0):
                return None
            sol = prog.solution(t)
            return sol if sol is not None and _check(inputs, *sol) > _MARGIN else None

        best = ok(0.0)
        if best is None:
            return _Frontier(0.0, exact, None, math.nan)
        lo, best = bisect_verified(ok, 0.0, exact, best, 1e-6)
    return _Frontier(lo, exact, best[0], best[1])


def max_certified_state_lipschitz_verified(kp: float, kd: float, omega_o: float) -> float:
    """The largest ``L_s`` ((m/s²) per unit z) whose role certificate verified in numpy for gains ``kp``
    (1/s²), ``kd`` (1/s), ``omega_o`` (rad/s); just below :func:`max_certified_state_lipschitz` (the SDP near the boundary).
    Cached per gains: what the services and the trainer use."""
    return _frontier(float(kp), float(kd), float(omega_o)).lmax


def _bound_candidates(inputs: RoleInputs) -> list[tuple[np.ndarray, float, float, float]]:
    """(P, τ, α, μ) of the bound SDP over a log grid of decay rates, best (smallest μ/α) first."""
    from neso.certificate.lmi import _lmi_solve

    a, _, _ = role_matrices(inputs.kp, inputs.kd, inputs.omega_o)
    alpha_hi = 2.0 * float(-np.linalg.eigvals(a).real.max())
    out = []
    with _LOCK:
        prog = _programs()
        t = prog.load(inputs)
        for x in np.linspace(math.log(1e-3), math.log(0.999), 10):
            prog.alpha.value = alpha_hi * math.exp(x)
            if not _lmi_solve(prog.bound) or prog.mu.value is None:
                continue
            sol = prog.solution(t)
            if sol is not None:
                out.append((sol[0], sol[1], float(prog.alpha.value), float(prog.mu.value) + 1e-300))
    return sorted(out, key=lambda c: c[3] / c[2])


def certify_roles(inputs: RoleInputs, *, optimise_bound: bool = True) -> RoleCertificate:
    """The role certificate for ``inputs`` (module docstring): holds iff ``L_s`` is at most the largest verified
    one and a certificate at ``L_s`` verifies in numpy; with ``optimise_bound`` the eventual bound from the bound
    SDP (the first candidate that verifies)."""
    front = _frontier(float(inputs.kp), float(inputs.kd), float(inputs.omega_o))
    base = dict(lipschitz_state=inputs.lipschitz_state, lipschitz_exo=inputs.lipschitz_exo, max_certified=front.lmax,
                C_f=inputs.C_f)
    if front.p is None or inputs.lipschitz_state > front.lmax or _check(inputs, front.p, front.tau) <= _MARGIN:
        return RoleCertificate(False, ultimate_bound=math.inf,
                               notes=(f"L_s above the largest verified {front.lmax:.6g} (1/||G||_inf = "
                                      f"{front.exact:.6g})",), **base)
    if optimise_bound and inputs.lipschitz_state < front.lmax:
        tries = [(p, tau, alpha * shrink, mu * (1 + slack)) for p, tau, alpha, mu in _bound_candidates(inputs)
                 for shrink, slack in ((1.0, 1e-4), (0.5, 1e-2), (0.1, 1.0))]  # the solver's optimum sits on the edge
        for p, tau, alpha, mu in tries:
            margin = _check(inputs, p, tau, alpha, mu)
            if margin > _MARGIN:
                lam_min = float(np.linalg.eigvalsh(p)[0]) - 5 * _EPS * float(np.linalg.norm(p))
                return RoleCertificate(True, ultimate_bound=inputs.C_f * math.sqrt(mu / (alpha * lam_min)), P=p,
                                       tau=tau, alpha=alpha, mu=mu, margin=margin,
                                       notes=("V' <= -alpha V + mu w^2; bound = C_f sqrt(mu/(alpha lambda_min(P)))",),
                                       **base)
    return RoleCertificate(True, ultimate_bound=math.inf, P=front.p, tau=front.tau,
                           margin=_check(inputs, front.p, front.tau),
                           notes=("verdict from the frontier's certificate; no bound computed",), **base)


def verify_roles(inputs: RoleInputs, result: RoleCertificate, *, rtol: float = 1e-6) -> bool:
    """Re-check a role certificate from its ``P``, ``τ`` (and ``α``, ``μ`` when it states a bound) only."""
    if not result.holds or result.P is None:
        return False
    p = np.asarray(result.P, dtype=float)
    if p.shape != (5, 5) or _check(inputs, p, result.tau) <= _MARGIN:
        return False
    if not math.isfinite(result.ultimate_bound):
        return True
    if _check(inputs, p, result.tau, result.alpha, result.mu) <= _MARGIN:
        return False
    lam_min = float(np.linalg.eigvalsh(p)[0]) - 5 * _EPS * float(np.linalg.norm(p))
    return lam_min > 0 and result.ultimate_bound >= inputs.C_f * math.sqrt(result.mu / (result.alpha * lam_min)) * (1 - rtol)
