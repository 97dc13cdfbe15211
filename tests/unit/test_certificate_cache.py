"""A role certificate found before is adopted only when it verifies here; the estimator's start reads it from
the cache without importing cvxpy (services/certificate_cache.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from neso.certificate import RoleInputs
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
