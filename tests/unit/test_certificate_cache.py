"""A role certificate found before is adopted only when it verifies here; the estimator's start reads it from
the cache without importing cvxpy (services/certificate_cache.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from neso.certificate import POLICY, RoleInputs
from neso.certificate.roles import (adopt_certificate, adopt_frontier, certificate_data, certify_roles,
                                    frontier_certificate, max_certified_state_lipschitz)
from neso.types import velocity_lag_s
from services.certificate_cache import warm
from tests.busutil import REPO

GAINS = (9.5, 5.5, 14.0)  # gains nothing else in the suite certifies
LAG = velocity_lag_s()


def test_only_a_frontier_that_verifies_is_adopted():
    lmax, p, tau, _ = frontier_certificate(*GAINS, velocity_lag_s=LAG)
    exact = max_certified_state_lipschitz(*GAINS, LAG)
    assert 0.999 * exact < lmax < exact
    assert not adopt_frontier(*GAINS, exact * 1.01, p, tau, velocity_lag_s=LAG), "a bound above 1/‖G‖∞"
    assert not adopt_frontier(*GAINS, lmax, p * np.diag([1, 1, 1, 1, -1, 1]), tau, velocity_lag_s=LAG), "a P that fails"
    assert not adopt_frontier(*GAINS, lmax, p[:5, :5], tau, velocity_lag_s=LAG)
    assert not adopt_frontier(*GAINS, "x", p, tau, velocity_lag_s=LAG)
    assert not adopt_frontier(*GAINS, lmax, p, tau), "the same numbers for the loop without the velocity lag"
    assert adopt_frontier(*GAINS, lmax, p, tau, velocity_lag_s=LAG)


def test_only_a_bound_certificate_that_verifies_is_adopted():
    inputs = RoleInputs(*GAINS, lipschitz_state=2.0, loop_gain=0.05, exogenous_rate_mps3=1.0, velocity_lag_s=LAG)
    data = certificate_data(inputs, certify_roles(inputs))
    assert data is not None and data["frontier"] is not None
    tampered = dict(data, alpha=data["alpha"] * 10)
    assert not adopt_certificate(inputs, tampered), "a decay rate its P does not give"
    assert not adopt_certificate(inputs, dict(data, P=(-np.array(data["P"])).tolist()))
    assert not adopt_certificate(RoleInputs(*GAINS, lipschitz_state=4.0, loop_gain=0.05, velocity_lag_s=LAG), data)
    assert not adopt_certificate(inputs, {"P": "x"})
    assert adopt_certificate(inputs, data)
    adopted = certify_roles(inputs)
    assert adopted.notes == ("adopted: verified here",) and adopted.error_bound_m > 0


def test_the_cache_is_written_once_and_adopted_without_cvxpy_in_a_fresh_process(tmp_path):
    path = tmp_path / "role-certificates.json"
    question = f"RoleInputs(*{GAINS!r}, lipschitz_state=1.5, exogenous_rate_mps3=0.5, velocity_lag_s={LAG!r})"
    probe = (f"import sys; from pathlib import Path; from neso.certificate import RoleInputs; "
             f"from services.certificate_cache import warm; "
             f"print(warm([{question}], path=Path({str(path)!r})), 'cvxpy' in sys.modules)")

    def run() -> list[str]:
        out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=120,
                             env=dict(os.environ, PYTHONPATH=REPO))
        return out.stdout.split() or [out.stderr]

    assert run() == ["solved", "True"] and path.is_file()
    assert run() == ["adopted", "False"]
    data = json.loads(path.read_text())
    entry = next(iter(data["certificates"].values()))
    entry["P"][0][0] = -entry["P"][0][0]  # tampered: solved again, never trusted
    path.write_text(json.dumps(data))
    assert run() == ["solved", "True"]
    path.write_text("not json")
    assert warm([RoleInputs(*GAINS, lipschitz_state=1.5, velocity_lag_s=LAG)], path=path) in ("adopted", "solved")


@pytest.mark.slow  # one whole bisection (~10 s) at gains nothing else in the suite certifies: left to make test
def test_a_flight_budget_found_before_is_verified_not_bisected_and_a_wrong_one_is_bisected_again(tmp_path):
    """The trainer's and `neso experiment paper`'s budgets (services/certificate_cache.py: adopt_budgets,
    keep_budgets): one kept by a process is taken by a fresh one after one verdict (two role certificates: the
    network's at that slope, PD+ESO's), not the bisection's ~17; one that does not hold, or is no number, or was
    found by other certificate code, is never used."""
    from neso.certificate import LoopPlant
    from neso.certificate.flight import FOUND_BUDGETS, adopt_budget, budget_key, flight_budget
    from neso.control import ControlConfig
    from services.certificate_cache import adopt_budgets, keep_budgets

    plant = LoopPlant.of(ControlConfig())
    budget = flight_budget(*GAINS, plant=plant, exogenous_fraction=0.05)
    key = budget_key(*GAINS, plant, 0.05, ("attitude",), POLICY)
    assert FOUND_BUDGETS[key] == budget > 0
    path = tmp_path / "flight-budgets.json"
    assert keep_budgets(path).startswith("kept") and keep_budgets(path) == "nothing new"
    probe = ("from pathlib import Path; from neso.certificate import LoopPlant; "
             "from neso.control import ControlConfig; "
             "from neso.certificate.flight import flight_budget, flight_certificate; "
             "from services.certificate_cache import adopt_budgets; "
             f"n = adopt_budgets(Path({str(path)!r})); "
             f"b = flight_budget(*{GAINS!r}, plant=LoopPlant.of(ControlConfig()), exogenous_fraction=0.05); "
             "print(n, repr(b), flight_certificate.cache_info().misses)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, PYTHONPATH=REPO))
    adopted, found, asked = out.stdout.split() or [out.stderr] * 3  # asked: verdicts it had to find
    # the file holds every budget this worker found (others too, in a whole run); the fresh process asks only this one
    assert int(adopted) >= 1 and (float(found), int(asked)) == (budget, 1), out.stdout + out.stderr
    # above the largest that holds: verified, refused, bisected again, to the bisection's tolerance (1e-4 relative)
    # of the first. Exact equality failed 1 of 6 runs here (its output not kept), when the first was adopted from a
    # file a whole run wrote; the likely cause, not shown: that run's bisection had some verdicts answered by
    # role certificates other tests had adopted, whose bounds can differ at the margin from ones solved here
    assert adopt_budget(key, budget * 1.01)
    again = flight_budget(*GAINS, plant=plant, exogenous_fraction=0.05)
    assert abs(again - budget) <= 2e-4 * budget, (again, budget)
    assert not any(adopt_budget(key, v) for v in ("x", None, -1.0, 0.0, float("nan"), float("inf")))
    path.write_text(json.dumps({"version": "other code", "budgets": {key: budget}}))
    assert adopt_budgets(path) == 0, "a budget found by other certificate code is not read"
