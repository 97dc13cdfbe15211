"""The public choice: dispatch by method, the tightest verified certificate for given gains, and the verdict
for what flies (:class:`FlightCertificate`).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

from neso.certificate.core import METHODS, CertificateInputs, CertificateResult, Method
from neso.certificate.lmi import LMI_STRUCTURE, _lmi_frontier, certify_lmi
from neso.certificate.literal import certify_literal
from neso.certificate.roles import max_certified_state_lipschitz_verified
from neso.certificate.tight import certify_tight

# --------------------------------------------------------------------------------------------- public API


def certify(inputs: CertificateInputs, method: Method = "tight") -> CertificateResult:
    """Dispatch to :func:`certify_literal`, :func:`certify_tight` or :func:`certify_lmi`."""
    if method == "literal":
        return certify_literal(inputs)
    if method == "tight":
        return certify_tight(inputs)
    if method == "lmi":
        return certify_lmi(inputs)
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
        if method == "lmi":
            return certify_lmi(inp, optimise_bound=False).holds
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


@functools.lru_cache(maxsize=256)
def _best_method(kp: float, kd: float, omega_o: float, lambda_c_rule: str) -> tuple[str, float]:
    """``(method, max certified L_N)`` of the tightest verified certificate for these gains: the LMI (full ``P``),
    which contains tight and literal (module docstring), unless its frontier has no verified certificate, then
    tight."""
    front = _lmi_frontier(kp, kd, omega_o, lambda_c_rule, LMI_STRUCTURE)
    if front.cert is not None:
        return "lmi", front.lmax
    inputs = CertificateInputs(kp=kp, kd=kd, omega_o=omega_o, lipschitz=0.0, lambda_c_rule=lambda_c_rule)
    return "tight", certify_tight(inputs, optimise_bound=False).max_certified_lipschitz


def max_certified_lipschitz_best(kp: float, kd: float, omega_o: float, lambda_c_rule: str = "corrected") -> float:
    """Largest ``L_N`` ((m/s²) per unit z, physical) the tightest verified certificate allows for gains ``kp``
    (1/s²), ``kd`` (1/s), ``omega_o`` (rad/s); the verdict holds for every ``L_N`` up to it. Cached per gains
    (``make bench`` measures a cold call, a call for new gains and a cached one)."""
    return _best_method(float(kp), float(kd), float(omega_o), lambda_c_rule)[1]


@functools.lru_cache(maxsize=256)
def best_certificate(inputs: CertificateInputs) -> CertificateResult:
    """The tightest verified certificate for ``inputs`` (``method`` says which: ``lmi`` unless it has no verified
    certificate for these gains). Cached per inputs; the result is shared, do not mutate its arrays."""
    method = _best_method(float(inputs.kp), float(inputs.kd), float(inputs.omega_o), inputs.lambda_c_rule)[0]
    return certify(inputs, method)


@dataclass(frozen=True)
class FlightCertificate:
    """The verdict for what flies: a network's certified physical Lipschitz constant in its state inputs
    (:meth:`neso.network.LipschitzMLP.certified_lipschitz_state`) against the largest the role certificate
    verified for the z gains and observer bandwidth (:func:`flight_budget`; :mod:`neso.certificate.roles`:
    sharper than Lemma 1, whose LMI gives :func:`max_certified_lipschitz_best`).

    ``lipschitz_phys`` (in the state inputs), ``max_certified``: (m/s²) per unit z. ``kp`` 1/s², ``kd`` 1/s,
    ``omega_o`` rad/s. ``margin``: ``max_certified − lipschitz_phys`` (> 0 iff it holds).
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
        return (f"certificate {verdict}: L_N {self.lipschitz_phys:.4g} (m/s²)/unit z physical (state inputs) vs "
                f"{self.max_certified:.4g} certified for kp {self.kp:g}, kd {self.kd:g}, ω_o {self.omega_o:g} "
                f"(margin {self.margin:+.4g}, {rel:+.0f} %)")

    def to_dict(self) -> dict:
        return {"holds": self.holds, "lipschitz_phys": self.lipschitz_phys, "max_certified": self.max_certified,
                "margin": self.margin, "kp": self.kp, "kd": self.kd, "omega_o": self.omega_o, "text": self.text()}


def flight_budget(kp: float, kd: float, omega_o: float) -> float:
    """The largest physical Lipschitz constant in the state inputs, (m/s²) per unit z, that flies certified
    with z gains ``kp`` (1/s²), ``kd`` (1/s) and ``omega_o`` (rad/s): the role certificate's verified frontier.
    What the services check and the trainer spends. Cached per gains."""
    return max_certified_state_lipschitz_verified(float(kp), float(kd), float(omega_o))


def flight_certificate(lipschitz_phys: float, *, kp: float, kd: float, omega_o: float) -> FlightCertificate:
    """The certificate for a network whose physical Lipschitz constant in its state inputs is ``lipschitz_phys``,
    flown with these z gains (the planar axes carry no network: ``L_N = 0`` there, which every positive gain
    certifies)."""
    lmax = flight_budget(kp, kd, omega_o)
    return FlightCertificate(bool(lipschitz_phys < lmax), float(lipschitz_phys), float(lmax), float(kp), float(kd),
                             float(omega_o))
