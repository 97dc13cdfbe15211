"""A role certificate found before is adopted only when it verifies here; the estimator's start reads it from
the cache without importing cvxpy (services/certificate_cache.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np

from neso.certificate.roles import adopt_frontier, frontier_certificate, max_certified_state_lipschitz
from services.certificate_cache import warm
from tests.busutil import REPO

GAINS = (9.5, 5.5, 14.0)  # gains nothing else in the suite certifies


def test_only_a_certificate_that_verifies_is_adopted():
    lmax, p, tau = frontier_certificate(*GAINS)
    exact = max_certified_state_lipschitz(*GAINS)
    assert 0.999 * exact < lmax < exact
    assert not adopt_frontier(*GAINS, exact * 1.01, p, tau), "a bound above 1/‖G‖∞"
    assert not adopt_frontier(*GAINS, lmax, p * np.diag([1, 1, 1, 1, -1]), tau), "a P that does not verify"
    assert not adopt_frontier(*GAINS, lmax, p[:4, :4], tau) and not adopt_frontier(*GAINS, "x", p, tau)
    assert adopt_frontier(*GAINS, lmax, p, tau)


def test_the_cache_is_written_once_and_adopted_without_cvxpy_in_a_fresh_process(tmp_path):
    path = tmp_path / "role-certificates.json"
    assert warm(*GAINS, path=path) == "solved" and path.is_file()
    probe = (f"import sys; from pathlib import Path; from services.certificate_cache import warm; "
             f"print(warm(*{GAINS!r}, path=Path({str(path)!r})), 'cvxpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONPATH=REPO))
    assert out.stdout.split() == ["adopted", "False"], out.stdout + out.stderr
    data = json.loads(path.read_text())
    frontier = next(iter(data["frontiers"].values()))
    frontier["p"][0][0] = -frontier["p"][0][0]  # tampered: solved again, never trusted
    path.write_text(json.dumps(data))
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, PYTHONPATH=REPO))
    assert out.stdout.split() == ["solved", "True"], out.stdout + out.stderr
    path.write_text("not json")
    assert warm(*GAINS, path=path) in ("adopted", "solved")  # this process adopted it above; nothing raised
