"""``roles``: the small-gain certificate with every network input in its role (sharper than Lemma 1, and sound for
inputs the controller's own output drives).

Same closed loop as the paper's Theorem 1 (z axis; ``E = [e, ė, x̃1, x̃2, f̃]``, ``Ė = A E + B Δḟ``,
:func:`neso.certificate.core.composite_matrices`; ``e = z* − z``), same conclusion (``E`` uniformly ultimately
bounded), but ``Δḟ = ḟ − ḟ_N`` is not bounded through ``‖ż‖`` as a whole. The network's inputs play three roles:

* the **tracked state** of its axis, ``p_z`` and ``v_z`` (:attr:`neso.features.FeatureSet.state_columns`): their
  rates are the loop's own, ``ṗ_z = ż* − ė`` and ``v̇_z = z̈* + k_p e + k_d ė + f̃``, exactly;
* **loop-driven** inputs: the thrust (``T_{k−1}``, ``T_applied``) and, through the tilt of the force, the attitude.
  The controller makes them from ``f̂ = f_N + Δf̂``, so they are the network's own output fed back. With the
  vertical specific force ``u_z`` (``T_z/m = g + u_z``) the plant gives ``u_z = v̇_z − f``, hence
  ``u̇_z = z⃛* + c₁ A E − ḟ_N`` (``c₁ = [k_p, k_d, 0, 0, 1]`` the ``v̇_z`` row, ``c₁B = 1``). A network whose rate
  through these inputs is ``κ u̇_z`` (``|κ| ≤ K = m L_T + k_att L_att``, :mod:`neso.certificate.flight`) closes
  an algebraic loop ``ḟ_N(1 + κ) = …``: it needs ``K < 1`` (the discrete loop ``T_k = −m κ T_{k−1} + …`` needs
  the same), and then enters as a second channel with output ``c_u = c₁A`` and gain ``K/(1 − K)``;
* **exogenous** inputs and parts of rates (the horizontal force's share of the thrust and attitude rates, the
  horizontal speed): bounded by what the vehicle can do (the controller's force-rate limit, the tilt and body-rate
  limits; :func:`neso.certificate.flight.exogenous_rates`), entering only the constant.

With the gradients along the trajectory (Clarke gradients: ``‖g_s‖ ≤ L_s``, the network's Lipschitz constant in its
state inputs, :meth:`LipschitzMLP.certified_lipschitz_state`)::

    Δḟ = φ_s + φ_u + w,   |φ_s| ≤ ls ‖C_s E‖,   |φ_u| ≤ lu |c_u E|,   ls = L_s/(1 − K),   lu = K/(1 − K)
    |w| ≤ C_f = L_1 + ls ‖R_s r‖ + lu |R_u r| + X/(1 − K)

(``r`` the reference's derivatives ``(ż*, z̈*, z⃛*)``, ``X`` the exogenous share, ``L_1`` the bound on ``|ḟ|``).

**The measured velocity.** The source differentiates the motion-capture position and low-passes it (15 Hz); the
controller's D term and the network both see that ``v̂``, not ``v_z``. With ``velocity_lag_s = τ > 0`` the loop
carries the filter as a first-order lag (the half-sample of the difference added to the filter's time constant,
:func:`neso.types.velocity_lag_s`): ``E`` gets ``ε = v̂ − v``, ``ε̇ = −ε/τ − v̇_z``, the D term acts on
``ė − ε``, the network's velocity input moves at ``−ε/τ``, and ``z̈*`` enters through ``ε`` (input ``B_r``).

Each verdict is a quadratic ``V = EᵀPE`` from an SDP (cvxpy + Clarabel, imported lazily) with one S-procedure
multiplier per channel, and is never trusted: the matrix inequality

    [[AᵀP + PA + αP + τ_s ls² C_sᵀC_s + τ_u lu² c_uᵀc_u, PB, PB, PB, PB_r], [BᵀP, −τ_s, …], [BᵀP, ·, −τ_u, …],
     [BᵀP, ·, ·, −μ_w, ·], [B_rᵀP, ·, ·, ·, −μ_r]] ⪯ 0,   P ≻ 0

is rebuilt and checked in numpy with rounding slack (:func:`neso.certificate.core.negative_margin`). The verdict
(``α = 0``, no ``w``, ``r``) says ``V`` decreases without disturbance; the bound program gives
``V̇ ≤ −αV + μ_w w² + μ_r z̈*²`` and, with ``P ⪰ e₁e₁ᵀ``, the eventual bound on the **tracking error itself**:
``|e_z| ≤ sqrt((μ_w C_f² + μ_r z̈*²_max)/α · (P⁻¹)₁₁)`` in metres. Without the thrust channel (``K = 0``) the
largest certified ``L_s`` is ``1/‖C_s(sI − A)⁻¹B‖_∞`` exactly (bounded-real lemma, Hamiltonian bisection); the
services use the largest whose SDP certificate verified (at ``K``: bisection). At k_p 10, k_d 6, ω_o 15 without the
velocity lag that is 7.40 (m/s²) per unit against the LMI's 1.66 under Lemma 1 (docs/certificate.md).
"""
from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from neso.certificate.core import (L1_MPS3, MISSION_ACC_MAX_MPS2, MISSION_JERK_MAX_MPS3, MISSION_VEL_MAX_MPS,
                                   bisect_verified, composite_matrices, negative_margin)

_EPS = np.finfo(float).eps
_MARGIN = 1e-9  # demanded Jacobi-scaled margin of the matrix inequalities, after rounding slack


# --------------------------------------------------------------------------------------------- the loop
@dataclass(frozen=True, eq=False)
class LoopMatrices:
    """The z loop the certificate models (module docstring), ``n`` = 5 (exact velocity) or 6 (with ``ε``).

    ``a`` (n×n), ``b`` (n×1): ``Ė = aE + b Δḟ + b_ref z̈*``; ``b_ref`` (n×1, zero without the lag). ``c_state``
    (2×n): the state inputs' rates driven by ``E`` (rows p_z, v_z); ``ref_state`` (2×2): their reference parts in
    ``(ż*, z̈*)``. ``c_thrust`` (1×n): ``u̇_z`` driven by ``E``; ``ref_thrust`` (2,): its reference part in
    ``(z̈*, z⃛*)``. ``scale`` (n,): the diagonal the solver's coordinates use (conditioning only)."""

    a: np.ndarray
    b: np.ndarray
    b_ref: np.ndarray
    c_state: np.ndarray
    ref_state: np.ndarray
    c_thrust: np.ndarray
    ref_thrust: np.ndarray
    scale: np.ndarray

    @property
    def n(self) -> int:
        return self.a.shape[0]


@functools.lru_cache(maxsize=64)
def loop_matrices(kp: float, kd: float, omega_o: float, velocity_lag_s: float = 0.0) -> LoopMatrices:
    """The loop for z gains ``kp`` (1/s²), ``kd`` (1/s), observer bandwidth ``omega_o`` (rad/s) and the measured
    velocity's lag ``velocity_lag_s`` (s; 0: the exact velocity)."""
    a5, b5 = composite_matrices(kp, kd, omega_o)
    scale = [1.0, kp ** -0.5, omega_o ** 2, omega_o, 1.0]
    if velocity_lag_s <= 0.0:
        c1 = np.array([[kp, kd, 0.0, 0.0, 1.0]])
        return _frozen(LoopMatrices(a5, b5, np.zeros((5, 1)), np.vstack([[0.0, -1.0, 0.0, 0.0, 0.0], c1]),
                                    np.eye(2), c1 @ a5, np.array([0.0, 1.0]), np.array(scale)))
    a = np.zeros((6, 6))
    a[:5, :5] = a5
    a[1, 5] = kd  # ë = −k_p e − k_d (ė − ε) − f̃
    c1 = np.array([[kp, kd, 0.0, 0.0, 1.0, -kd]])  # v̇_z − z̈*
    a[5, :] = -c1[0]
    a[5, 5] -= 1.0 / velocity_lag_s  # ε̇ = −ε/τ − v̇_z
    b = np.zeros((6, 1))
    b[:5] = b5
    b_ref = np.zeros((6, 1))
    b_ref[5, 0] = -1.0
    c_state = np.array([[0.0, -1.0, 0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, -1.0 / velocity_lag_s]])
    return _frozen(LoopMatrices(a, b, b_ref, c_state, np.array([[1.0, 0.0], [0.0, 0.0]]), c1 @ a,
                                np.array([float((c1 @ b_ref)[0, 0]), 1.0]), np.array(scale + [kp ** -0.5])))


def _frozen(m: LoopMatrices) -> LoopMatrices:
    for name in ("a", "b", "b_ref", "c_state", "ref_state", "c_thrust", "ref_thrust", "scale"):
        getattr(m, name).setflags(write=False)
    return m


def role_matrices(kp: float, kd: float, omega_o: float, velocity_lag_s: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A``, ``B`` and the state inputs' ``C`` (2×n) of :func:`loop_matrices`."""
    m = loop_matrices(float(kp), float(kd), float(omega_o), float(velocity_lag_s))
    return m.a, m.b, m.c_state


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
def max_certified_state_lipschitz(kp: float, kd: float, omega_o: float, velocity_lag_s: float = 0.0) -> float:
    """``1/‖C_s(sI − A)⁻¹B‖_∞``, (m/s²) per unit z: the largest Lipschitz constant in the state inputs any
    quadratic certificate allows without loop-driven inputs (``K = 0``); with them it is lower. The services use
    the largest that verified, :func:`max_certified_state_lipschitz_verified`."""
    m = loop_matrices(float(kp), float(kd), float(omega_o), float(velocity_lag_s))
    return 1.0 / hinf_norm(m.a, m.b, m.c_state)


# --------------------------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class RoleInputs:
    """What a role certificate is asked about.

    Gains: ``kp`` (1/s²), ``kd`` (1/s), ``omega_o`` (rad/s); ``velocity_lag_s``: the measured velocity's lag (s).
    The network: ``lipschitz_state`` ``L_s`` ((m/s²) per unit of (p_z m, v_z m/s), jointly); ``loop_gain`` ``K``
    (dimensionless, < 1: the network's slope along ``u_z`` through its thrust and attitude inputs);
    ``exogenous_rate_mps3`` ``X`` (m/s³: the most its exogenous inputs' rates move ``f_N``).
    The envelope: ``L_1`` (bound on ``|ḟ|``, m/s³), ``ref_vel_max`` (m/s), ``ref_acc_max`` (m/s²), ``ref_jerk_max``
    (m/s³) of the z reference.
    """

    kp: float
    kd: float
    omega_o: float
    lipschitz_state: float
    loop_gain: float = 0.0
    exogenous_rate_mps3: float = 0.0
    velocity_lag_s: float = 0.0
    L_1: float = L1_MPS3
    ref_vel_max: float = MISSION_VEL_MAX_MPS
    ref_acc_max: float = MISSION_ACC_MAX_MPS2
    ref_jerk_max: float = MISSION_JERK_MAX_MPS3

    def __post_init__(self) -> None:
        for name in ("kp", "kd", "omega_o"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v!r}")
        for name in ("lipschitz_state", "loop_gain", "exogenous_rate_mps3", "velocity_lag_s", "L_1", "ref_vel_max",
                     "ref_acc_max", "ref_jerk_max"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")

    @property
    def loop_closed(self) -> bool:
        """The algebraic loop through the thrust is well posed: ``K < 1``."""
        return self.loop_gain < 1.0

    @property
    def channels(self) -> tuple[float, float]:
        """``(ls, lu)``: the state and thrust channels' gains after the algebraic loop (inf if ``K ≥ 1``)."""
        if not self.loop_closed:
            return math.inf, math.inf
        return self.lipschitz_state / (1.0 - self.loop_gain), self.loop_gain / (1.0 - self.loop_gain)

    @property
    def matrices(self) -> LoopMatrices:
        return loop_matrices(float(self.kp), float(self.kd), float(self.omega_o), float(self.velocity_lag_s))

    @property
    def C_f(self) -> float:
        """``|w|`` bound, m/s³ (module docstring); inf if ``K ≥ 1``."""
        if not self.loop_closed:
            return math.inf
        ls, lu = self.channels
        m = self.matrices
        v, a, j = self.ref_vel_max, self.ref_acc_max, self.ref_jerk_max
        state_ref = float(np.linalg.norm(np.abs(m.ref_state) @ [v, a]))
        thrust_ref = float(abs(m.ref_thrust[0]) * a + abs(m.ref_thrust[1]) * j)
        return self.L_1 + ls * state_ref + lu * thrust_ref + self.exogenous_rate_mps3 / (1.0 - self.loop_gain)

    @property
    def ref_input(self) -> float:
        """The bound on the input through ``B_r`` (``z̈*``, m/s²; 0 without the velocity lag: then the certificate
        has no such input)."""
        return self.ref_acc_max if self.matrices.b_ref.any() else 0.0


# --------------------------------------------------------------------------------------------- results
@dataclass(frozen=True, eq=False)
class RoleCertificate:
    """The verdict and the certificate's data.

    ``holds``: ``K < 1`` and a certificate verified. ``max_certified``: the largest verified ``L_s`` at this ``K``
    ((m/s²)/unit; ``margin_state`` = it − ``L_s``). ``error_bound_m``: the eventual bound on ``|e_z|`` (m; inf if
    not computed), ``ultimate_bound``: on ``‖E‖`` (mixed SI) from the same ``V``. ``P`` (n×n), multipliers
    ``tau_state``, ``tau_thrust`` (NaN when the channel is absent), decay rate ``alpha`` (1/s), input gains
    ``mu`` (of ``w``), ``mu_ref`` (of ``z̈*``), and the margin the numpy check found."""

    holds: bool
    lipschitz_state: float
    loop_gain: float
    max_certified: float
    C_f: float
    error_bound_m: float
    ultimate_bound: float
    P: np.ndarray | None = None
    tau_state: float = math.nan
    tau_thrust: float = math.nan
    alpha: float = math.nan
    mu: float = math.nan
    mu_ref: float = math.nan
    margin: float = -math.inf
    notes: tuple[str, ...] = field(default_factory=tuple)

    method = "roles"

    @property
    def margin_state(self) -> float:
        return self.max_certified - self.lipschitz_state

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
        out.update(method="roles", max_certified_lipschitz=conv(self.max_certified), margin_state=conv(self.margin_state),
                   error_bound_cm=conv(self.error_bound_m * 100.0), alpha_e=conv(self.alpha), alpha_o=conv(self.alpha))
        out["units"] = {"lipschitz": "(m/s^2) per unit of the state inputs (m, m/s)", "C_f": "m/s^3",
                        "error_bound_m": "eventual |e_z|, m", "error_bound_cm": "eventual |e_z|, cm",
                        "ultimate_bound": "Euclidean norm of E=[e,de,x1~,x2~,f~(,eps)] in mixed SI"}
        return out


# --------------------------------------------------------------------------------------------- checks
@dataclass(frozen=True)
class _Cert:
    """A proposed certificate: ``P`` and the multipliers (NaN for an absent channel), and for a bound ``alpha``,
    ``mu`` (of w), ``mu_ref`` (of z̈*, NaN without the velocity lag)."""

    p: np.ndarray
    tau_s: float = math.nan
    tau_u: float = math.nan
    alpha: float = 0.0
    mu: float | None = None
    mu_ref: float = math.nan


def role_lmi(m: LoopMatrices, ls: float, lu: float, cert: _Cert) -> tuple[np.ndarray, np.ndarray]:
    """The S-procedure matrix (module docstring) and an elementwise bound on its assembly error. Blocks: the state,
    then one input per present channel (``φ_s`` if ``ls > 0``, ``φ_u`` if ``lu > 0``: a channel whose gain is 0
    carries nothing and is left out, since its multiplier would only cost), then ``w`` and ``z̈*`` when a bound is
    asked (``cert.mu`` set)."""
    n, p = m.n, cert.p
    top = m.a.T @ p + p @ m.a + cert.alpha * p
    err_top = np.abs(m.a).T @ np.abs(p) + np.abs(p) @ np.abs(m.a) + abs(cert.alpha) * np.abs(p)
    cols: list[tuple[np.ndarray, float]] = []
    errs = []
    if ls > 0.0:
        cc = ls ** 2 * (m.c_state.T @ m.c_state)
        top = top + cert.tau_s * cc
        err_top = err_top + cert.tau_s * np.abs(cc)
        cols.append((p @ m.b, -cert.tau_s))
        errs.append(np.abs(p) @ np.abs(m.b))
    if lu > 0.0:
        cu = lu ** 2 * (m.c_thrust.T @ m.c_thrust)
        top = top + cert.tau_u * cu
        err_top = err_top + cert.tau_u * np.abs(cu)
        cols.append((p @ m.b, -cert.tau_u))
        errs.append(np.abs(p) @ np.abs(m.b))
    if cert.mu is not None:
        cols.append((p @ m.b, -cert.mu))
        errs.append(np.abs(p) @ np.abs(m.b))
        if m.b_ref.any() and math.isfinite(cert.mu_ref):
            cols.append((p @ m.b_ref, -cert.mu_ref))
            errs.append(np.abs(p) @ np.abs(m.b_ref))
    size = n + len(cols)
    out = np.zeros((size, size))
    err = np.zeros((size, size))
    out[:n, :n] = 0.5 * (top + top.T)
    err[:n, :n] = err_top
    for j, ((col, diag), e) in enumerate(zip(cols, errs)):
        out[:n, n + j:n + j + 1], out[n + j:n + j + 1, :n], out[n + j, n + j] = col, col.T, diag
        err[:n, n + j:n + j + 1], err[n + j:n + j + 1, :n] = e, e.T
    return out, (size + 4) * _EPS * err


def _check(m: LoopMatrices, ls: float, lu: float, cert: _Cert) -> float:
    """min(margin of the matrix inequality, margin of P ≻ 0), with rounding slack; > _MARGIN: verified."""
    p = cert.p
    multipliers = ([cert.tau_s] if ls > 0.0 else []) + ([cert.tau_u] if lu > 0.0 else [])
    if cert.mu is not None:
        multipliers += [cert.mu]
    if not (all(math.isfinite(t) and t >= 0 for t in multipliers) and cert.alpha >= 0 and p.shape == (m.n, m.n)
            and np.all(np.isfinite(p)) and np.allclose(p, p.T, rtol=1e-12, atol=0)):
        return -math.inf
    mat, err = role_lmi(m, ls, lu, cert)
    return min(negative_margin(mat, err), negative_margin(-p, 4 * _EPS * np.abs(p)))


# --------------------------------------------------------------------------------------------- the SDPs
class _Programs:
    """The SDPs of one loop size and channel set in scaled coordinates (``Ē = TE``, ``T`` =
    :attr:`LoopMatrices.scale`), compiled once: ``feasibility`` (max ``t``: ``M ⪯ −tI``, ``P ⪰ tI``, ``tr P + Στ = 1``)
    and ``bound`` (min ``μ_w C_f² + μ_r a²`` at a decay rate ``α`` with ``P ⪰ e₁e₁ᵀ``, unscaled, so
    ``|e_z|² ≤ V``). Not thread-safe: callers hold ``_LOCK``."""

    def __init__(self, n: int, state: bool, thrust: bool, ref: bool) -> None:
        import cvxpy as cp

        self.state, self.thrust, self.ref = state, thrust, ref
        self.abar, self.bbar, self.brbar = cp.Parameter((n, n)), cp.Parameter((n, 1)), cp.Parameter((n, 1))
        self.cs, self.cu = cp.Parameter((n, n), PSD=True), cp.Parameter((n, n), PSD=True)
        self.alpha = cp.Parameter(nonneg=True)
        self.weight_w, self.weight_r = cp.Parameter(nonneg=True), cp.Parameter(nonneg=True)
        self.p = cp.Variable((n, n), symmetric=True)
        self.tau_s, self.tau_u = cp.Variable(nonneg=True), cp.Variable(nonneg=True)
        self.t, self.mu, self.mu_r = cp.Variable(), cp.Variable(nonneg=True), cp.Variable(nonneg=True)
        pb = self.p @ self.bbar
        core = self.abar.T @ self.p + self.p @ self.abar
        taus = []
        if state:
            core = core + self.tau_s * self.cs
            taus.append(self.tau_s)
        if thrust:
            core = core + self.tau_u * self.cu
            taus.append(self.tau_u)

        def col(v):
            return cp.reshape(v, (1, 1), order="C")

        def assemble(top, inputs):
            k = len(inputs)
            rows = [[top] + [c for c, _ in inputs]]
            for i, (c, d) in enumerate(inputs):
                rows.append([c.T] + [(-col(d) if j == i else np.zeros((1, 1))) for j in range(k)])
            return cp.bmat(rows)

        m2 = assemble(core, [(pb, t) for t in taus])
        bound_inputs = [(pb, t) for t in taus] + [(pb, self.mu)]
        if ref:
            bound_inputs.append((self.p @ self.brbar, self.mu_r))
        m3 = assemble(core + self.alpha * self.p, bound_inputs)
        k2, k3 = n + len(taus), n + len(bound_inputs)
        e1 = np.zeros((n, 1))
        e1[0, 0] = 1.0
        self.feasibility = cp.Problem(cp.Maximize(self.t), [0.5 * (m2 + m2.T) << -self.t * np.eye(k2),
                                                            self.p >> self.t * np.eye(n),
                                                            cp.trace(self.p) + sum(taus, start=0) == 1])
        objective = self.weight_w * self.mu + (self.weight_r * self.mu_r if ref else 0)
        self.bound = cp.Problem(cp.Minimize(objective), [0.5 * (m3 + m3.T) << 0, self.p >> e1 @ e1.T])

    def load(self, m: LoopMatrices, ls: float, lu: float) -> np.ndarray:
        t = m.scale
        self.abar.value = t[:, None] * m.a / t[None, :]
        self.bbar.value = t[:, None] * m.b
        self.brbar.value = t[:, None] * m.b_ref
        cs = m.c_state / t[None, :]
        cu = m.c_thrust / t[None, :]
        self.cs.value = _psd(ls ** 2 * (cs.T @ cs))
        self.cu.value = _psd(lu ** 2 * (cu.T @ cu))
        return t

    def proposal(self, t: np.ndarray, **extra) -> _Cert | None:
        if self.p.value is None or (self.state and self.tau_s.value is None) or (self.thrust and self.tau_u.value is None):
            return None
        p = 0.5 * (self.p.value + self.p.value.T)
        tau_s = float(self.tau_s.value) if self.state else math.nan
        tau_u = float(self.tau_u.value) if self.thrust else math.nan
        return _Cert(t[:, None] * p * t[None, :], tau_s, tau_u, **extra)


def _psd(x: np.ndarray) -> np.ndarray:
    return 0.5 * (x + x.T)


_LOCK = threading.Lock()


@functools.lru_cache(maxsize=16)
def _programs(n: int, state: bool, thrust: bool, ref: bool) -> _Programs:
    return _Programs(n, state, thrust, ref)


def _solve(problem) -> bool:
    from neso.certificate.lmi import _lmi_solve

    return _lmi_solve(problem)


def _verdict_proposal(m: LoopMatrices, ls: float, lu: float) -> _Cert | None:
    """A verified verdict certificate for channel gains ``(ls, lu)``, or None."""
    with _LOCK:
        prog = _programs(m.n, ls > 0.0, lu > 0.0, False)
        t = prog.load(m, ls, lu)
        if not _solve(prog.feasibility) or not (prog.t.value is not None and prog.t.value > 0):
            return None
        cert = prog.proposal(t)
    return cert if cert is not None and _check(m, ls, lu, cert) > _MARGIN else None


# --------------------------------------------------------------------------------------------- frontiers
@dataclass(frozen=True)
class _Frontier:
    lmax: float  # the largest L_s whose certificate verified at this K
    exact: float  # 1/‖C_s G‖_∞ (the bound at K = 0)
    cert: _Cert | None


_ADOPTED: dict[tuple, _Frontier] = {}  # frontiers found before, verified here (adopt_frontier)


def _key(kp, kd, omega_o, velocity_lag_s, loop_gain) -> tuple[float, float, float, float, float]:
    return float(kp), float(kd), float(omega_o), float(velocity_lag_s), float(loop_gain)


def adopt_frontier(kp: float, kd: float, omega_o: float, lmax: float, p, tau, *, velocity_lag_s: float = 0.0,
                   loop_gain: float = 0.0, tau_thrust: float = math.nan) -> bool:
    """Take a frontier found before — the largest ``L_s`` ``lmax`` at loop gain ``K`` and its certificate
    (``P`` (n×n), ``τ_s``, ``τ_u``) — without solving an SDP, iff it verifies here in numpy exactly as the
    bisection's own do (and ``lmax`` is below the exact ``1/‖G‖_∞``). False, and nothing adopted, otherwise."""
    key = _key(kp, kd, omega_o, velocity_lag_s, loop_gain)
    try:
        p = np.array(p, dtype=float)
        lmax, tau, tau_thrust = float(lmax), float(tau), float(tau_thrust)
        inputs = RoleInputs(*key[:3], lipschitz_state=lmax, loop_gain=key[4], velocity_lag_s=key[3])
    except (TypeError, ValueError):
        return False
    if not inputs.loop_closed:
        return False
    exact = max_certified_state_lipschitz(*key[:4])
    ls, lu = inputs.channels
    cert = _Cert(p, tau, tau_thrust)
    if p.shape != (inputs.matrices.n,) * 2 or not (0.0 < lmax <= exact) or not _check(inputs.matrices, ls, lu, cert) > _MARGIN:
        return False
    _ADOPTED[key] = _Frontier(lmax, exact, cert)
    return True


def frontier_certificate(kp: float, kd: float, omega_o: float, *, velocity_lag_s: float = 0.0,
                         loop_gain: float = 0.0) -> tuple[float, np.ndarray | None, float, float]:
    """``(lmax, P, τ_s, τ_u)`` of the verified frontier at these gains and loop gain (solved, or adopted), for
    :func:`adopt_frontier` later."""
    f = _frontier(*_key(kp, kd, omega_o, velocity_lag_s, loop_gain))
    if f.cert is None:
        return f.lmax, None, math.nan, math.nan
    return f.lmax, f.cert.p, f.cert.tau_s, f.cert.tau_u


@functools.lru_cache(maxsize=512)
def _frontier(kp: float, kd: float, omega_o: float, velocity_lag_s: float, loop_gain: float) -> _Frontier:
    """An adopted frontier (:func:`adopt_frontier`), else bisection on "the SDP at L_s is strictly feasible and
    its certificate verifies in numpy" below 1/‖G‖_∞ (monotone: a certificate at L is one at every smaller L), to
    a relative 1e-6. ``lmax`` 0 and no certificate when ``K ≥ 1`` or nothing verifies."""
    key = (kp, kd, omega_o, velocity_lag_s, loop_gain)
    if key in _ADOPTED:
        return _ADOPTED[key]
    exact = max_certified_state_lipschitz(kp, kd, omega_o, velocity_lag_s)
    if loop_gain >= 1.0:
        return _Frontier(0.0, exact, None)
    m = loop_matrices(kp, kd, omega_o, velocity_lag_s)

    def ok(lip: float):
        return _verdict_proposal(m, lip / (1.0 - loop_gain), loop_gain / (1.0 - loop_gain))

    best = ok(0.0)
    if best is None:
        return _Frontier(0.0, exact, None)
    lo, best = bisect_verified(ok, 0.0, exact, best, 1e-6)
    return _Frontier(lo, exact, best)


def max_certified_state_lipschitz_verified(kp: float, kd: float, omega_o: float, velocity_lag_s: float = 0.0,
                                           loop_gain: float = 0.0) -> float:
    """The largest ``L_s`` ((m/s²) per unit z) whose role certificate verified in numpy for gains ``kp``
    (1/s²), ``kd`` (1/s), ``omega_o`` (rad/s), the velocity's lag (s) and loop gain ``K``; just below
    :func:`max_certified_state_lipschitz` at ``K = 0``. Cached: what the services and the trainer use."""
    return _frontier(*_key(kp, kd, omega_o, velocity_lag_s, loop_gain)).lmax


# --------------------------------------------------------------------------------------------- the bound
def _bound_candidates(inputs: RoleInputs) -> list[_Cert]:
    """Bound certificates over decay rates, best (smallest eventual |e_z|) first: a log grid of ``α`` up to twice
    the slowest pole's rate, then a golden-section refinement around the best (the bound is unimodal in ``α`` in
    practice; any ``α`` gives a valid certificate, this only finds a tight one)."""
    m = inputs.matrices
    ls, lu = inputs.channels
    alpha_hi = 2.0 * float(-np.linalg.eigvals(m.a).real.max())
    ref = inputs.ref_input > 0.0
    found: dict[float, _Cert] = {}
    with _LOCK:
        prog = _programs(m.n, ls > 0.0, lu > 0.0, ref)
        t = prog.load(m, ls, lu)
        prog.weight_w.value = max(inputs.C_f, 1e-9) ** 2
        prog.weight_r.value = inputs.ref_input ** 2

        def at(x: float) -> float:
            if x not in found:
                prog.alpha.value = alpha_hi * math.exp(x)
                cert = None
                if _solve(prog.bound) and prog.mu.value is not None:
                    mu_r = float(prog.mu_r.value) + 1e-300 if ref and prog.mu_r.value is not None else math.nan
                    cert = prog.proposal(t, alpha=float(prog.alpha.value), mu=float(prog.mu.value) + 1e-300,
                                         mu_ref=mu_r)
                found[x] = cert
            return _error_bound(inputs, found[x]) if found[x] is not None else math.inf

        grid = list(np.linspace(math.log(1e-3), math.log(0.999), 12))
        values = [at(x) for x in grid]
        i = int(np.argmin(values))
        if math.isfinite(values[i]):
            lo, hi = grid[max(0, i - 1)], grid[min(len(grid) - 1, i + 1)]
            g = (math.sqrt(5.0) - 1.0) / 2.0
            c, d = hi - g * (hi - lo), lo + g * (hi - lo)
            for _ in range(10):
                if at(c) < at(d):
                    hi, d = d, c
                    c = hi - g * (hi - lo)
                else:
                    lo, c = c, d
                    d = lo + g * (hi - lo)
    return sorted((c for c in found.values() if c is not None), key=lambda c: _error_bound(inputs, c))


def _dissipated(inputs: RoleInputs, cert: _Cert) -> float:
    """``μ_w C_f² + μ_r a²``: what ``V`` settles below times ``α`` (inf for a certificate without the reference
    input asked about a reference that accelerates)."""
    if inputs.ref_input > 0 and not math.isfinite(cert.mu_ref):
        return math.inf
    ref = cert.mu_ref * inputs.ref_input ** 2 if inputs.ref_input > 0 else 0.0
    return cert.mu * inputs.C_f ** 2 + ref


def _error_bound(inputs: RoleInputs, cert: _Cert) -> float:
    """The eventual ``|e_z|`` bound (m) a bound certificate gives: ``sqrt(μ_w C_f² + μ_r a²)/α · (P⁻¹)₁₁)``."""
    try:
        inv11 = float(np.linalg.inv(cert.p)[0, 0])
    except np.linalg.LinAlgError:
        return math.inf
    if not (inv11 > 0 and cert.alpha > 0):
        return math.inf
    return math.sqrt(_dissipated(inputs, cert) / cert.alpha * inv11 * (1 + 1e-9))


def _norm_bound(inputs: RoleInputs, cert: _Cert) -> float:
    """The eventual ``‖E‖`` bound from the same ``V``: ``sqrt(μ_w C_f² + μ_r a²)/(α λ_min P))``."""
    lam_min = float(np.linalg.eigvalsh(cert.p)[0]) - 5 * _EPS * float(np.linalg.norm(cert.p))
    return math.sqrt(_dissipated(inputs, cert) / (cert.alpha * lam_min)) if lam_min > 0 else math.inf


# --------------------------------------------------------------------------------------------- the verdict
_KNOWN: dict[RoleInputs, "RoleCertificate"] = {}  # certificates found before, verified here (adopt_certificate)


def _point_key(inputs: RoleInputs) -> tuple:
    return _key(inputs.kp, inputs.kd, inputs.omega_o, inputs.velocity_lag_s, inputs.loop_gain) + (inputs.lipschitz_state,)


@functools.lru_cache(maxsize=1024)
def _point_verdict(kp, kd, omega_o, velocity_lag_s, loop_gain, lipschitz_state) -> _Cert | None:
    m = loop_matrices(kp, kd, omega_o, velocity_lag_s)
    return _verdict_proposal(m, lipschitz_state / (1.0 - loop_gain), loop_gain / (1.0 - loop_gain))


def certify_roles(inputs: RoleInputs, *, optimise_bound: bool = True, frontier: bool = True) -> RoleCertificate:
    """The role certificate for ``inputs`` (module docstring): holds iff ``K < 1`` and a certificate for ``L_s`` at
    that ``K`` verifies in numpy (the frontier's, which covers every smaller ``L_s``, or one solved at the point);
    with ``optimise_bound`` the eventual bounds from the bound SDP (the first candidate that verifies); with
    ``frontier`` the largest verified ``L_s`` at this ``K`` (``max_certified``; else NaN). A certificate adopted
    before (:func:`adopt_certificate`) is returned without solving."""
    known = _KNOWN.get(inputs)
    if known is not None and (math.isfinite(known.max_certified) or not frontier):
        return known
    lmax, front = math.nan, None
    if frontier:
        f = _frontier(*_key(inputs.kp, inputs.kd, inputs.omega_o, inputs.velocity_lag_s, inputs.loop_gain))
        lmax, front = f.lmax, f.cert
    base = dict(lipschitz_state=inputs.lipschitz_state, loop_gain=inputs.loop_gain, max_certified=lmax,
                C_f=inputs.C_f)
    if not inputs.loop_closed:
        return RoleCertificate(False, error_bound_m=math.inf, ultimate_bound=math.inf, notes=(
            f"loop gain through the thrust {inputs.loop_gain:.3g} >= 1: the controller's output drives the network "
            "harder than it corrects it",), **base)
    m = inputs.matrices
    ls, lu = inputs.channels
    verdict = front if (front is not None and inputs.lipschitz_state <= lmax
                        and _check(m, ls, lu, front) > _MARGIN) else _point_verdict(*_point_key(inputs))
    if verdict is None:
        above = f" (the largest verified {lmax:.4g})" if frontier else ""
        return RoleCertificate(False, error_bound_m=math.inf, ultimate_bound=math.inf,
                               notes=(f"state slope {inputs.lipschitz_state:.4g} not certified at loop gain "
                                      f"{inputs.loop_gain:.3g}{above}",), **base)
    if optimise_bound:
        best = None
        for cand in _bound_candidates(inputs):
            # the solver's optimum sits on the edge: give up a little decay rate and input gain until it verifies
            for shrink, slack in ((0.999, 1e-3), (0.99, 1e-2), (0.9, 0.1), (0.5, 1.0)):
                cert = _Cert(cand.p, cand.tau_s, cand.tau_u, cand.alpha * shrink, cand.mu * (1 + slack),
                             cand.mu_ref * (1 + slack))
                margin = _check(m, ls, lu, cert)
                if margin > _MARGIN:
                    if best is None or _error_bound(inputs, cert) < _error_bound(inputs, best[0]):
                        best = (cert, margin)
                    break
        if best is not None:
            cert, margin = best
            return RoleCertificate(True, error_bound_m=_error_bound(inputs, cert),
                                   ultimate_bound=_norm_bound(inputs, cert), P=cert.p, tau_state=cert.tau_s,
                                   tau_thrust=cert.tau_u, alpha=cert.alpha, mu=cert.mu, mu_ref=cert.mu_ref,
                                   margin=margin, notes=("V' <= -alpha V + mu w^2 (+ mu_ref zdd*^2); |e_z| <= "
                                                         "sqrt((mu C_f^2 + mu_ref a^2)/alpha (P^-1)_11)",), **base)
    return RoleCertificate(True, error_bound_m=math.inf, ultimate_bound=math.inf, P=verdict.p,
                           tau_state=verdict.tau_s, tau_thrust=verdict.tau_u, margin=_check(m, ls, lu, verdict),
                           notes=("verdict certificate only; no bound computed",), **base)


def error_bound_under(result: RoleCertificate, inputs: RoleInputs) -> float:
    """The eventual ``|e_z|`` bound (m) that ``result``'s bound certificate gives under ``inputs``' constant and
    reference (the same loop and channels; inf if it states no bound or does not verify for them)."""
    if not (result.holds and result.P is not None and math.isfinite(result.error_bound_m) and inputs.loop_closed):
        return math.inf
    cert = _Cert(np.asarray(result.P, float), result.tau_state, result.tau_thrust, result.alpha, result.mu,
                 result.mu_ref)
    ls, lu = inputs.channels
    return _error_bound(inputs, cert) if _check(inputs.matrices, ls, lu, cert) > _MARGIN else math.inf


def certificate_data(inputs: RoleInputs, result: RoleCertificate) -> dict | None:
    """What :func:`adopt_certificate` needs to take ``result`` (for ``inputs``) back later, JSON-safe: its bound
    certificate and, when it states one, its frontier's. None if it holds no bound certificate."""
    if not result.holds or result.P is None or not math.isfinite(result.error_bound_m):
        return None

    def num(v: float):
        return v if math.isfinite(v) else None

    out = {"P": np.asarray(result.P).tolist(), "tau_state": result.tau_state, "tau_thrust": num(result.tau_thrust),
           "alpha": result.alpha, "mu": result.mu, "mu_ref": num(result.mu_ref), "frontier": None}
    if math.isfinite(result.max_certified):
        lmax, p, tau_s, tau_u = frontier_certificate(inputs.kp, inputs.kd, inputs.omega_o,
                                                     velocity_lag_s=inputs.velocity_lag_s, loop_gain=inputs.loop_gain)
        if p is not None:
            out["frontier"] = {"lmax": lmax, "P": p.tolist(), "tau_state": num(tau_s), "tau_thrust": num(tau_u)}
    return out


def adopt_certificate(inputs: RoleInputs, data) -> bool:
    """Take a role certificate found before (:func:`certificate_data`) for exactly ``inputs`` without solving, iff
    every part of it verifies here in numpy as the solver's own results must: its verdict and bound certificate,
    and its frontier (when stated). False, and nothing adopted, otherwise."""
    def f(v):
        return math.nan if v is None else float(v)

    try:
        p = np.array(data["P"], dtype=float)
        cert = _Cert(p, f(data.get("tau_state")), f(data.get("tau_thrust")), f(data["alpha"]), f(data["mu"]),
                     f(data.get("mu_ref")))
        if not inputs.loop_closed or p.shape != (inputs.matrices.n,) * 2:
            return False
        ls, lu = inputs.channels
        if not (cert.alpha > 0 and _check(inputs.matrices, ls, lu, cert) > _MARGIN
                and _check(inputs.matrices, ls, lu, _Cert(p, cert.tau_s, cert.tau_u)) > _MARGIN):
            return False
        lmax = math.nan
        front = data.get("frontier")
        if front is not None:
            if not adopt_frontier(inputs.kp, inputs.kd, inputs.omega_o, front["lmax"], front["P"], f(front.get("tau_state")),
                                  velocity_lag_s=inputs.velocity_lag_s, loop_gain=inputs.loop_gain,
                                  tau_thrust=f(front.get("tau_thrust"))):
                return False
            lmax = float(front["lmax"])
    except (KeyError, TypeError, ValueError):
        return False
    _KNOWN[inputs] = RoleCertificate(True, inputs.lipschitz_state, inputs.loop_gain, lmax, inputs.C_f,
                                     _error_bound(inputs, cert), _norm_bound(inputs, cert), p, cert.tau_s, cert.tau_u,
                                     cert.alpha, cert.mu, cert.mu_ref, _check(inputs.matrices, ls, lu, cert),
                                     ("adopted: verified here",))
    return True


def verify_roles(inputs: RoleInputs, result: RoleCertificate, *, rtol: float = 1e-6) -> bool:
    """Re-check a role certificate from its ``P`` and multipliers (and ``α``, ``μ`` when it states a bound) only."""
    if not result.holds or result.P is None or not inputs.loop_closed:
        return False
    m = inputs.matrices
    ls, lu = inputs.channels
    p = np.asarray(result.P, dtype=float)
    if p.shape != (m.n, m.n) or _check(m, ls, lu, _Cert(p, result.tau_state, result.tau_thrust)) <= _MARGIN:
        return False
    if not math.isfinite(result.error_bound_m):
        return True
    cert = _Cert(p, result.tau_state, result.tau_thrust, result.alpha, result.mu, result.mu_ref)
    if _check(m, ls, lu, cert) <= _MARGIN:
        return False
    return (result.error_bound_m >= _error_bound(inputs, cert) * (1 - rtol)
            and result.ultimate_bound >= _norm_bound(inputs, cert) * (1 - rtol))
