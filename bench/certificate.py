"""Bench rows: the stability certificates side by side — max certified ``L_N`` of literal, tight, LMI (block and
full ``P``) and the role certificate (in the state inputs, the velocity filter's lag in the loop) over a grid of gains with the time each takes, what
:func:`neso.certificate.best_certificate` and :func:`neso.certificate.flight_budget` (the one the services use) cost
cold (fresh process), for new gains and cached, and how tight each bound is against a simulated worst case.

``python -m bench.certificate`` prints only these tables (~1 min on 2 busy cores); ``make bench`` includes them.
``L_N`` in (m/s²) per unit z (physical); bounds on ‖E‖ in mixed SI (m, m/s, m, m/s, m/s²).
"""
from __future__ import annotations

import itertools
import json
import subprocess
import sys
import time

import numpy as np

GRID_COLUMNS = ("kp", "kd", "ω_o", "literal", "tight", "LMI block", "LMI full", "full/tight",
                "tight ms", "LMI full ms (SDPs)", "roles", "roles/LMI", "roles ms")
KP, KD, OMEGA_O = (4.0, 10.0, 20.0), (3.0, 6.0, 10.0), (10.0, 15.0, 20.0, 30.0)
FLOWN = (10.0, 6.0, 15.0)  # controller z gains and estimator ω_o as the services start


def grid_rows(kps=KP, kds=KD, omegas=OMEGA_O) -> list[tuple[str, ...]]:
    """One row per gain set: the max certified ``L_N`` of each method, tight's and the LMI's solve time (cold
    for those gains; the LMI's cvxpy programs already compiled, as in any process after its first call)."""
    from neso import certificate as c
    from neso.certificate import POLICY, lmi, roles, tight as tight_method

    lag = POLICY.velocity_lag_s  # the loop the services certify: the measured velocity's lag in it
    lmi._lmi_programs("full"), lmi._lmi_programs("block"), roles._programs(6, True, False, False)  # compile once
    rows = []
    for kp, kd, w in itertools.product(kps, kds, omegas):
        base = c.CertificateInputs(kp=kp, kd=kd, omega_o=w, lipschitz=0.0)
        lit = c.certify_literal(base).max_certified_lipschitz
        tight_method._optimise_tight.cache_clear()
        t0 = time.perf_counter()
        tight = c.certify_tight(base, optimise_bound=False).max_certified_lipschitz
        t_tight = time.perf_counter() - t0
        block = lmi._lmi_frontier(kp, kd, w, "corrected", "block")
        full = lmi._lmi_frontier(kp, kd, w, "corrected", "full")
        roles._frontier.cache_clear()
        roles.max_certified_state_lipschitz.cache_clear()
        t0 = time.perf_counter()
        role = roles.max_certified_state_lipschitz_verified(kp, kd, w, lag)
        t_roles = time.perf_counter() - t0
        flown = " ← flown" if (kp, kd, w) == FLOWN else ""
        rows.append((f"{kp:g}", f"{kd:g}", f"{w:g}{flown}", f"{lit:.4g}", f"{tight:.4g}", f"{block.lmax:.4g}",
                     f"{full.lmax:.4g}", f"{full.lmax / tight:.2f}", f"{t_tight * 1e3:.0f}",
                     f"{full.solve_time_s * 1e3:.0f} ({full.solves})", f"{role:.4g}", f"{role / full.lmax:.2f}",
                     f"{t_roles * 1e3:.0f}"))
    return rows


TIMING_COLUMNS = ("best_certificate / max_certified_lipschitz_best", "seconds")

_COLD = """
import json, time
t0 = time.perf_counter()
from neso.certificate import max_certified_lipschitz_best
t1 = time.perf_counter()
max_certified_lipschitz_best(10.0, 6.0, 15.0)
t2 = time.perf_counter()
max_certified_lipschitz_best(12.0, 6.0, 15.0)
t3 = time.perf_counter()
for _ in range(1000):
    max_certified_lipschitz_best(10.0, 6.0, 15.0)
t4 = time.perf_counter()
from neso.certificate import flight_budget
flight_budget(10.0, 6.0, 15.0)
t5 = time.perf_counter()
flight_budget(12.0, 6.0, 15.0)
t6 = time.perf_counter()
print(json.dumps(dict(imp=t1 - t0, cold=t2 - t1, new=t3 - t2, cached=(t4 - t3) / 1000, roles_cold=t5 - t4,
                      roles_new=t6 - t5)))
"""


def timing_rows() -> list[tuple[str, str]]:
    """A fresh interpreter: import, first call (cvxpy import, compile, bisection), new gains, cached."""
    out = subprocess.run([sys.executable, "-c", _COLD], capture_output=True, text=True, timeout=300, check=True)
    t = json.loads(out.stdout.strip().splitlines()[-1])
    return [("import neso.certificate", f"{t['imp']:.3f}"),
            ("first call in a fresh process (kp 10, kd 6, ω_o 15): cvxpy import + compile + bisection",
             f"{t['cold']:.3f}"),
            ("new gains, same process (kp 12)", f"{t['new']:.3f}"),
            ("cached gains", f"{t['cached']:.1e}"),
            ("flight_budget (the trainer's budget: the verdict the services fly by, bisected), first call",
             f"{t['roles_cold']:.3f}"),
            ("flight_budget, new gains (kp 12)", f"{t['roles_new']:.3f}")]


BOUND_COLUMNS = ("eventual bound on ‖E‖ at the flown gains", "L_N = ½ tight max", "L_N = ½ LMI max")


def bound_rows() -> list[tuple[str, str, str]]:
    """Tight's and the LMI's eventual bounds against the largest ‖E‖ the worst-case error system reaches from rest
    in 10 s (``Δḟ`` at Lemma 1's bound, signed to raise the LMI's V: :func:`tests.helpers.worst_case_run`)."""
    from dataclasses import replace

    from neso.certificate import CertificateInputs, certify_lmi, certify_tight
    from tests.helpers import worst_case_run

    base = CertificateInputs(*FLOWN, lipschitz=0.0)
    cols = []
    for lip in (0.5 * certify_tight(base).max_certified_lipschitz, 0.5 * certify_lmi(base).max_certified_lipschitz):
        inp = replace(base, lipschitz=lip)
        tight, lmi = certify_tight(inp), certify_lmi(inp)
        _, e = worst_case_run(inp, lmi.P, np.zeros((1, 5)), steps=10000)
        cols.append((lip, tight, lmi, float(np.linalg.norm(e[:, 0], axis=1).max())))

    def fmt(v: float) -> str:
        return "fails" if not np.isfinite(v) else f"{v:.3g}"

    return [("L_N, (m/s²)/unit z", *(f"{c[0]:.3g}" for c in cols)),
            ("tight: V' < 0 outside (decrease ball)", *(fmt(c[1].ultimate_bound) for c in cols)),
            ("tight: eventual (sublevel set)", *(fmt(c[1].ultimate_bound_sublevel) for c in cols)),
            ("LMI (full P): eventual", *(fmt(c[2].ultimate_bound) for c in cols)),
            ("simulated worst case from rest: max ‖E‖", *(f"{c[3]:.3g}" for c in cols))]


def print_tables(table) -> None:
    table(GRID_COLUMNS, grid_rows())
    print(flush=True)
    table(TIMING_COLUMNS, timing_rows())
    print(flush=True)
    table(BOUND_COLUMNS, bound_rows())


if __name__ == "__main__":
    from bench.table import print_table

    print_tables(print_table)
