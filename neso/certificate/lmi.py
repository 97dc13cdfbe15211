"""``lmi``: a quadratic V = EᵀPE under Lemma 1 by the S-procedure, solved by cvxpy + Clarabel and re-verified in
numpy (the package docstring derives it).
"""
from __future__ import annotations

import functools
import math
import threading
import time
import warnings
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import scipy.linalg
import scipy.optimize

from neso.certificate.core import (CertificateInputs, CertificateResult, bisect_verified, composite_matrices,
                                   negative_margin)

# --------------------------------------------------------------------------------------------- LMI

LmiStructure = Literal["block", "full"]
LMI_STRUCTURES: tuple[str, ...] = ("block", "full")
LMI_STRUCTURE: LmiStructure = "full"  # the one `method="lmi"` uses (module docstring: why)

# Required margin of the Jacobi-scaled matrix inequality (unit diagonal): λ_max(D M D) ≤ −_LMI_MARGIN, after the
# floating-point error of assembling M has been added. An LMI closer to singular than this is not believed.
_LMI_MARGIN = 1e-9
_LMI_MU_SLACK = 1e-4  # μ is set this much (relative) above the exact Schur-complement value, so M ≺ 0 strictly
_LMI_REL_TOL = 1e-6  # resolution of the bisection on L_N


def lmi_matrix(inputs: CertificateInputs, p: np.ndarray, tau_e: float, tau_o: float, *, alpha: float = 0.0,
               mu: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The S-procedure matrix of the LMI certificate (module docstring) for ``inputs`` (``n_axes`` axes) and a
    per-axis ``P`` (5×5, unscaled): ``M`` of size 7n (``mu is None``) or 8n, and an elementwise bound on the
    floating-point error made assembling it. ``M ≺ 0`` with ``P ≻ 0`` is the certificate."""
    n = inputs.n_axes
    a, b = composite_matrices(inputs.kp, inputs.kd, inputs.omega_o, n)
    eye = np.eye(n)
    pn = np.kron(np.asarray(p, dtype=float), eye)
    pi_e = np.diag(np.r_[np.ones(2 * n), np.zeros(3 * n)])
    pi_o = np.eye(5 * n) - pi_e
    s_e, s_o = tau_e * inputs.gamma_e**2, tau_o * inputs.gamma_etilde**2
    top = a.T @ pn + pn @ a + alpha * pn + s_e * pi_e + s_o * pi_o
    pb = pn @ b
    ins = [tau_e, tau_o] + ([] if mu is None else [mu])
    k = len(ins)
    m = np.zeros((5 * n + k * n, 5 * n + k * n))
    m[: 5 * n, : 5 * n] = 0.5 * (top + top.T)
    for i, t in enumerate(ins):
        sl = slice(5 * n + i * n, 5 * n + (i + 1) * n)
        m[: 5 * n, sl], m[sl, : 5 * n], m[sl, sl] = pb, pb.T, -t * eye
    ap, ab = np.abs(a), np.abs(pn)
    err = np.zeros_like(m)
    err[: 5 * n, : 5 * n] = ap.T @ ab + ab @ ap + abs(alpha) * ab + abs(s_e) * pi_e + abs(s_o) * pi_o
    for i in range(k):
        sl = slice(5 * n + i * n, 5 * n + (i + 1) * n)
        err[: 5 * n, sl] = ab @ np.abs(b)
        err[sl, : 5 * n] = err[: 5 * n, sl].T
    return m, (5 * n + 4) * np.finfo(float).eps * err


def _lmi_scaling(kp: float, omega_o: float) -> np.ndarray:
    """Diagonal of ``T`` with ``Ē = T E`` = ``(e, ė/√k_p, ω²x̃1, ωx̃2, f̃)``: bandwidth scaling, only so the solver
    sees entries of similar size (the certificate is the same in any coordinates)."""
    return np.array([1.0, kp**-0.5, omega_o**2, omega_o, 1.0])


class _LmiPrograms:
    """The two SDPs of one ``P`` structure, compiled once by cvxpy (parameters are the scaled data), solved by
    Clarabel. ``feasibility``: max ``t`` s.t. ``M̄(P̄, τ) ⪯ −tI``, ``P̄ ⪰ tI``, ``tr P̄ + τ_e + τ_o = 1`` (a
    homogeneous LMI, so ``t > 0`` iff strictly feasible). ``bound``: for a decay rate ``α``, min ``μ`` s.t. the
    4-block matrix with ``αP̄`` and the ``C_f`` input is ``⪯ 0`` and ``P ⪰ I`` (unscaled), which minimises
    ``μ/(α λ_min P)``. Not thread-safe: every caller holds ``_LMI_LOCK`` while it loads and solves."""

    def __init__(self, structure: str) -> None:
        import cvxpy as cp

        self.abar = cp.Parameter((5, 5))
        self.bbar = cp.Parameter((5, 1))
        self.r_e = cp.Parameter(5, nonneg=True)
        self.r_o = cp.Parameter(5, nonneg=True)
        self.alpha = cp.Parameter(nonneg=True)
        self.p_floor = cp.Parameter(5, nonneg=True)
        if structure == "full":
            self.p = cp.Variable((5, 5), symmetric=True)
        else:
            self.p_e, self.p_o = cp.Variable((2, 2), symmetric=True), cp.Variable((3, 3), symmetric=True)
            self.p = cp.bmat([[self.p_e, np.zeros((2, 3))], [np.zeros((3, 2)), self.p_o]])
        self.tau_e, self.tau_o = cp.Variable(nonneg=True), cp.Variable(nonneg=True)
        self.t, self.mu = cp.Variable(), cp.Variable(nonneg=True)
        pb = self.p @ self.bbar
        core = (self.abar.T @ self.p + self.p @ self.abar
                + self.tau_e * cp.diag(self.r_e) + self.tau_o * cp.diag(self.r_o))
        z = np.zeros((1, 1))

        def col(v):
            return cp.reshape(v, (1, 1), order="C")

        m3 = cp.bmat([[core, pb, pb], [pb.T, -col(self.tau_e), z], [pb.T, z, -col(self.tau_o)]])
        m4 = cp.bmat([[core + self.alpha * self.p, pb, pb, pb], [pb.T, -col(self.tau_e), z, z],
                      [pb.T, z, -col(self.tau_o), z], [pb.T, z, z, -col(self.mu)]])
        self.feasibility = cp.Problem(cp.Maximize(self.t), [
            0.5 * (m3 + m3.T) << -self.t * np.eye(7), self.p >> self.t * np.eye(5),
            cp.trace(self.p) + self.tau_e + self.tau_o == 1])
        self.bound = cp.Problem(cp.Minimize(self.mu), [
            0.5 * (m4 + m4.T) << 0, self.p >> cp.diag(self.p_floor)])

    def load(self, kp: float, kd: float, omega_o: float, gamma_e: float, gamma_o: float) -> np.ndarray:
        """Set the scaled data for these gains and ``γ``'s; returns the scaling ``T`` (diagonal)."""
        a, b = composite_matrices(kp, kd, omega_o)
        t = _lmi_scaling(kp, omega_o)
        self.abar.value = t[:, None] * a / t[None, :]
        self.bbar.value = t[:, None] * b
        inv2 = 1.0 / t**2
        self.r_e.value = gamma_e**2 * np.r_[inv2[:2], np.zeros(3)]
        self.r_o.value = gamma_o**2 * np.r_[np.zeros(2), inv2[2:]]
        self.p_floor.value = inv2
        return t

    def solution(self, t: np.ndarray) -> tuple[np.ndarray, float, float] | None:
        """``(P unscaled, τ_e, τ_o)`` of the last solve, or None."""
        pv = self.p.value
        if pv is None or self.tau_e.value is None or self.tau_o.value is None:
            return None
        pv = 0.5 * (pv + pv.T)
        return t[:, None] * pv * t[None, :], float(self.tau_e.value), float(self.tau_o.value)


_LMI_LOCK = threading.Lock()


@functools.lru_cache(maxsize=len(LMI_STRUCTURES))
def _lmi_programs(structure: str) -> _LmiPrograms:
    return _LmiPrograms(structure)


def _lmi_solve(problem) -> bool:
    """Solve with Clarabel; True if the solver reports a solution (soundness comes from the numpy check)."""
    import cvxpy as cp

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "solution may be inaccurate": the numpy verification decides
        try:
            problem.solve(solver=cp.CLARABEL)
        except cp.error.SolverError:
            return False
    return problem.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)


def _lmi_rates_and_gains(inputs: CertificateInputs, p: np.ndarray, tau_e: float, tau_o: float,
                         ) -> list[tuple[float, float]]:
    """For fixed ``P, τ``: decay rates ``α`` and input gains ``μ`` to try, best eventual bound first.

    The first minimises ``C_f·sqrt(μ/(α λ_min P))`` over ``α`` (1-D), with ``μ`` the Schur-complement value
    ``bᵀ(−N_α)⁻¹b`` raised by ``_LMI_MU_SLACK``; the others trade bound for margin (smaller ``α``, larger ``μ``:
    as ``α → 0, μ → ∞`` the 4-block margin tends to the 3-block one), so a certificate close to the largest
    ``L_N`` still verifies, with a large bound. Empty if the 3-block matrix is not negative definite. Per axis.
    """
    one = replace(inputs, n_axes=1)
    m3, _ = lmi_matrix(one, p, tau_e, tau_o)
    d = -np.diag(m3)
    if np.any(d <= 0) or not np.all(np.isfinite(m3)):
        return []
    s = 1.0 / np.sqrt(d)
    neg = -(m3 * np.outer(s, s))
    pblk = scipy.linalg.block_diag(p, np.zeros((2, 2))) * np.outer(s, s)
    try:
        lam = scipy.linalg.eigh(pblk, neg, eigvals_only=True)[-1]
    except np.linalg.LinAlgError:
        return []
    if not lam > 0:
        return []
    alpha_max = 1.0 / lam
    b = np.r_[p @ composite_matrices(inputs.kp, inputs.kd, inputs.omega_o)[1][:, 0], 0.0, 0.0] * s

    def mu_of(alpha: float) -> float:
        return float(b @ np.linalg.solve(neg - alpha * pblk, b))

    def log_ratio(x: float) -> float:
        alpha = alpha_max * math.exp(x)
        try:
            mu = mu_of(alpha)
        except np.linalg.LinAlgError:
            return math.inf
        return math.log(mu / alpha) if mu > 0 and math.isfinite(mu) else math.inf

    res = scipy.optimize.minimize_scalar(log_ratio, bounds=(math.log(1e-9), math.log(1 - 1e-4)), method="bounded",
                                         options=dict(xatol=1e-6))
    alpha_opt = alpha_max * math.exp(float(res.x))
    out = []
    for a_frac, slack in ((1.0, _LMI_MU_SLACK), (1.0, 1e-1), (1e-1, 1e1), (1e-3, 1e3), (1e-5, 1e5)):
        alpha = alpha_opt * a_frac
        try:
            mu = mu_of(alpha)
        except np.linalg.LinAlgError:
            continue
        if math.isfinite(mu) and mu >= 0:
            out.append((alpha, mu * (1.0 + slack) + 1e-300))
    return out


@dataclass(frozen=True, eq=False)
class _LmiCert:
    """One verified LMI certificate at ``lipschitz``: per-axis ``P`` (5×5, unscaled), multipliers, ``α`` (1/s),
    ``μ`` (units of V per (m/s³)²), and the margins the numpy check found."""

    lipschitz: float
    p: np.ndarray
    tau_e: float
    tau_o: float
    alpha: float
    mu: float
    margin: float
    p_margin: float


def _lmi_check(inputs: CertificateInputs, p: np.ndarray, tau_e: float, tau_o: float, alpha: float, mu: float,
               ) -> tuple[float, float]:
    """(margin of ``M ≺ 0``, margin of ``P ≻ 0``), both Jacobi-scaled with rounding slack; verified iff both >
    ``_LMI_MARGIN`` and ``α > 0``. Rebuilds everything from ``inputs`` with ``n_axes`` axes."""
    if not (alpha > 0 and tau_e >= 0 and tau_o >= 0 and mu >= 0) or not np.allclose(p, p.T, rtol=1e-12, atol=0):
        return -math.inf, -math.inf
    m, err = lmi_matrix(inputs, p, tau_e, tau_o, alpha=alpha, mu=mu)
    pn = np.kron(0.5 * (p + p.T), np.eye(inputs.n_axes))
    p_err = 4 * np.finfo(float).eps * np.abs(pn)
    return negative_margin(m, err), negative_margin(-pn, p_err)


def _lmi_certificate_at(inputs: CertificateInputs, p: np.ndarray, tau_e: float, tau_o: float) -> _LmiCert | None:
    """The first ``α, μ`` for this ``P, τ`` at ``inputs`` (best bound first) that verifies in numpy; None if none
    does."""
    for alpha, mu in _lmi_rates_and_gains(inputs, p, tau_e, tau_o):
        margin, p_margin = _lmi_check(inputs, p, tau_e, tau_o, alpha, mu)
        if margin > _LMI_MARGIN and p_margin > _LMI_MARGIN:
            return _LmiCert(inputs.lipschitz, p, tau_e, tau_o, alpha, mu, margin, p_margin)
    return None


def _lmi_feasible(prog: _LmiPrograms, inputs: CertificateInputs) -> _LmiCert | None:
    """Max-margin feasibility SDP at ``inputs.lipschitz``, then the numpy verification."""
    t = prog.load(inputs.kp, inputs.kd, inputs.omega_o, inputs.gamma_e, inputs.gamma_etilde)
    if not _lmi_solve(prog.feasibility) or not (prog.t.value is not None and prog.t.value > 0):
        return None
    sol = prog.solution(t)
    return None if sol is None else _lmi_certificate_at(inputs, *sol)


@dataclass(frozen=True)
class _LmiFrontier:
    """The largest verified ``L_N`` for one set of gains and its certificate; solver effort spent."""

    lmax: float
    cert: _LmiCert | None
    solves: int
    solve_time_s: float


@functools.lru_cache(maxsize=256)
def _lmi_frontier(kp: float, kd: float, omega_o: float, lambda_c_rule: str, structure: str) -> _LmiFrontier:
    """Bisection on ``L_N`` of "the SDP is strictly feasible and its ``P`` verifies" (monotone: a certificate at
    ``L`` is one at every smaller ``L``, module docstring), to relative resolution ``_LMI_REL_TOL``. The returned
    maximum is the largest ``L`` whose certificate verified, never a bracket end the solver merely claimed."""
    base = CertificateInputs(kp=kp, kd=kd, omega_o=omega_o, lipschitz=0.0, lambda_c_rule=lambda_c_rule)
    t0 = time.perf_counter()
    solves = 0
    with _LMI_LOCK:
        prog = _lmi_programs(structure)

        def ok(lip: float) -> _LmiCert | None:
            nonlocal solves
            solves += 1
            return _lmi_feasible(prog, replace(base, lipschitz=lip))

        best = ok(0.0)
        if best is None:
            return _LmiFrontier(0.0, None, solves, time.perf_counter() - t0)
        lo, hi = 0.0, 0.25
        while (c := ok(hi)) is not None:
            best, lo, hi = c, hi, 2.0 * hi
            if hi > 1e9:
                break
        lo, best = bisect_verified(ok, lo, hi, best, _LMI_REL_TOL)
    return _LmiFrontier(lo, best, solves, time.perf_counter() - t0)


def _lmi_bound_candidates(prog: _LmiPrograms, inputs: CertificateInputs) -> list[tuple[np.ndarray, float, float]]:
    """``(P, τ_e, τ_o)`` minimising ``μ/α`` of the bound SDP over a log grid of decay rates ``α`` (below twice the
    slowest mode's rate, the most any ``V`` can certify), refined by a bounded 1-D search around the best."""
    t = prog.load(inputs.kp, inputs.kd, inputs.omega_o, inputs.gamma_e, inputs.gamma_etilde)
    a, _ = composite_matrices(inputs.kp, inputs.kd, inputs.omega_o)
    alpha_hi = 2.0 * float(-np.linalg.eigvals(a).real.max())
    found: dict[float, tuple[float, tuple]] = {}

    def value(x: float) -> float:
        prog.alpha.value = alpha_hi * math.exp(x)
        if not _lmi_solve(prog.bound) or prog.mu.value is None:
            return math.inf
        sol = prog.solution(t)
        if sol is None:
            return math.inf
        v = math.log(max(float(prog.mu.value), 1e-300) / prog.alpha.value)
        found[x] = (v, sol)
        return v

    grid = np.linspace(math.log(1e-3), math.log(0.999), 8)
    vals = [value(float(x)) for x in grid]
    i = int(np.argmin(vals))
    if math.isfinite(vals[i]):
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
        scipy.optimize.minimize_scalar(value, bounds=(float(lo), float(hi)), method="bounded",
                                       options=dict(xatol=1e-3, maxiter=12))
    return [sol for _, sol in sorted(found.values(), key=lambda vs: vs[0])[:2]]


def _lmi_bound_value(c_f: float, p: np.ndarray, alpha: float, mu: float) -> float:
    """Eventual bound on ‖E‖: ``C_f · sqrt(μ / (α λ_min(P)))`` (mixed SI), ``λ_min`` lowered by its rounding
    error bound so the bound is never optimistic; inf if ``P`` is not surely positive definite."""
    lam_min = float(np.linalg.eigvalsh(p)[0]) - 5 * np.finfo(float).eps * float(np.linalg.norm(p))
    return c_f * math.sqrt(mu / (alpha * lam_min)) if lam_min > 0 else math.inf


def _lmi_bound(inputs: CertificateInputs, cert: _LmiCert) -> float:
    return _lmi_bound_value(inputs.C_f, cert.p, cert.alpha, cert.mu)


def certify_lmi(inputs: CertificateInputs, *, structure: LmiStructure = LMI_STRUCTURE,
                optimise_bound: bool = True) -> CertificateResult:
    """LMI certificate (module docstring): quadratic ``V = EᵀPE`` with ``P`` block-diagonal (``structure="block"``,
    the paper's ``V_e + V_obs``) or full, Lemma 1 by the two-multiplier S-procedure, solved by cvxpy + Clarabel
    (imported here, lazily), every verdict re-verified in numpy.

    ``max_certified_lipschitz`` is the largest ``L_N`` whose SDP solution verified (bisection, cached per gains);
    the verdict holds iff ``L_N`` is at most that and a verified certificate at ``L_N`` exists. With
    ``optimise_bound`` the bound SDP picks ``P`` for the smallest eventual bound at this ``L_N``; otherwise the
    frontier's certificate (verified at the maximum, hence at every smaller ``L_N``) is re-verified here.
    """
    if structure not in LMI_STRUCTURES:
        raise ValueError(f"structure must be one of {LMI_STRUCTURES}, got {structure!r}")
    front = _lmi_frontier(float(inputs.kp), float(inputs.kd), float(inputs.omega_o), inputs.lambda_c_rule, structure)
    t0 = time.perf_counter()
    certs: list[_LmiCert] = []
    notes = [f"lambda_c_rule={inputs.lambda_c_rule}", f"P structure={structure}",
             "V' <= -alpha V + mu C_f^2 (S-procedure, two multipliers); bound = C_f sqrt(mu/(alpha lambda_min(P)))",
             f"frontier: {front.solves} SDP solves, {front.solve_time_s:.3f} s"]
    if front.cert is None:
        notes.append("no solver proposal passed the numpy verification, even at L_N = 0; verdict withdrawn")
    elif inputs.lipschitz > front.lmax:
        notes.append("L_N above the largest verified L_N")
    else:
        candidates = [(front.cert.p, front.cert.tau_e, front.cert.tau_o)]
        if optimise_bound and inputs.lipschitz < front.lmax:
            with _LMI_LOCK:
                candidates += _lmi_bound_candidates(_lmi_programs(structure), replace(inputs, n_axes=1))
        for p, te, to in candidates:
            c = _lmi_certificate_at(inputs, p, te, to)
            if c is not None:
                certs.append(c)
        if not certs:
            # the frontier's own (α, μ) are valid at every smaller L_N; the re-optimised ones did not verify
            margin, p_margin = _lmi_check(inputs, front.cert.p, front.cert.tau_e, front.cert.tau_o,
                                          front.cert.alpha, front.cert.mu)
            if margin > _LMI_MARGIN and p_margin > _LMI_MARGIN:
                certs.append(replace(front.cert, lipschitz=inputs.lipschitz, margin=margin, p_margin=p_margin))
        if not certs:
            notes.append("no certificate at this L_N passed the numpy verification; verdict withdrawn")
    best = min(certs, key=lambda c: _lmi_bound(inputs, c)) if certs else None
    return _lmi_result(inputs, structure, front, best, notes, time.perf_counter() - t0 + front.solve_time_s)


def _lmi_result(inputs, structure, front: _LmiFrontier, cert: _LmiCert | None, notes: list[str],
                solve_time_s: float) -> CertificateResult:
    shown = cert if cert is not None else front.cert
    p = shown.p if shown is not None else np.full((5, 5), np.nan)
    a, _ = composite_matrices(inputs.kp, inputs.kd, inputs.omega_o)
    holds = cert is not None
    alpha = cert.alpha if holds else -math.inf
    bound = _lmi_bound(inputs, cert) if holds else math.inf
    m = lmi_matrix(replace(inputs, n_axes=1), p, shown.tau_e, shown.tau_o, alpha=shown.alpha, mu=shown.mu)[0] \
        if shown is not None else np.full((8, 8), np.nan)
    p_e, p_o = p[:2, :2], p[2:, 2:]
    nan = math.nan
    return CertificateResult(
        method="lmi", holds=holds, lipschitz=inputs.lipschitz, alpha_e=alpha, alpha_o=alpha, alpha=alpha,
        alpha_sup=alpha, ultimate_bound=bound, ultimate_bound_sublevel=bound, max_certified_lipschitz=front.lmax,
        lambda_e=nan, lambda_o=nan, c_pb=nan, pe_be_norm=nan, lambda_c=inputs.lambda_c, gamma_e=inputs.gamma_e,
        gamma_etilde=inputs.gamma_etilde, C_z=inputs.C_z, C_f=inputs.C_f, C_o=None, delta_e=None, delta_o=None,
        delta_c=None, weight_s=1.0, kappa_e=1.0, kappa_o=1.0, coupling_matrix=m, P_e=p_e, P_obs=p_o,
        Q_e=-(a[:2, :2].T @ p_e + p_e @ a[:2, :2]), Q_obs=-(a[2:, 2:].T @ p_o + p_o @ a[2:, 2:]),
        scale_e=np.ones(2), scale_obs=np.ones(3), n_axes=inputs.n_axes, notes=tuple(notes),
        P=p, multipliers=(shown.tau_e, shown.tau_o) if shown is not None else None,
        mu=shown.mu if shown is not None else None, structure=structure, solve_time_s=solve_time_s,
    )


def verify_lmi(inputs: CertificateInputs, result: CertificateResult, *, rtol: float = 1e-6) -> bool:
    """Re-check an LMI certificate in numpy from its ``P``, multipliers, ``α`` and ``μ`` only (n-axis matrices
    from ``inputs``; nothing from the solver): ``P ≻ 0`` and ``M ≺ 0`` with margin (:func:`negative_margin`),
    and the reported bound no smaller than ``C_f·sqrt(μ/(α λ_min P))``."""
    if not result.holds or result.method != "lmi" or result.P is None or result.multipliers is None:
        return False
    p = np.asarray(result.P, dtype=float)
    if p.shape != (5, 5) or not np.all(np.isfinite(p)) or result.mu is None:
        return False
    if result.structure == "block" and (np.any(p[:2, 2:] != 0) or np.any(p[2:, :2] != 0)):
        return False
    tau_e, tau_o = result.multipliers
    margin, p_margin = _lmi_check(inputs, p, tau_e, tau_o, result.alpha, result.mu)
    if margin <= _LMI_MARGIN or p_margin <= _LMI_MARGIN:
        return False
    bound = _lmi_bound_value(inputs.C_f, p, result.alpha, result.mu)
    return result.ultimate_bound >= bound * (1 - rtol) and result.ultimate_bound_sublevel >= bound * (1 - rtol)
