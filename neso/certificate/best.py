"""The public choice of Lemma 1's methods: dispatch by method and the tightest verified certificate for given gains
(the verdict for what flies is :mod:`neso.certificate.flight`).
"""
from __future__ import annotations

import functools
import math

from neso.certificate.core import METHODS, CertificateInputs, CertificateResult, Method
from neso.certificate.lmi import LMI_STRUCTURE, _lmi_frontier, certify_lmi
from neso.certificate.literal import certify_literal
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
