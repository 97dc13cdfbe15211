"""The `neso` commands a new user runs first, as real subprocesses with no bus running: offline
training into the registry, the networks listed (shipped and trained), a refused what-if."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from neso.learning import recipe_of
from neso.netfile import load_network
from flight.estimator import DEFAULT_NETWORK
from tests.busutil import REPO, free_port
from tests.helpers import EXAMPLE, flight_messages, write_recording

pytestmark = pytest.mark.offline  # offline training and the registry: no flight (runs beside the flights: tests/conftest.py)


def neso_run(*args: str, timeout_s: float = 180.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli.main", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout_s)


def test_train_with_no_bus_trains_here_stores_in_the_registry_and_networks_list_shows_both(tmp_path):
    rrd = tmp_path / "flight.rrd"
    write_recording(rrd, flight_messages(300, pathway="neural_eso"))
    registry = tmp_path / "registry"
    nobody = f"tcp/127.0.0.1:{free_port()}"  # no hub listens there
    out = neso_run("train", str(rrd), "--no-offer", "--epochs", "3", "--registry", str(registry), "--connect", nobody)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "no trainer of uav1 on the bus: training here, offline" in out.stdout
    tdr_label = recipe_of(load_network(Path(REPO, DEFAULT_NETWORK)).metadata).tdr_label  # the recipe's TDR label
    assert f"trained offline: uav1-{tdr_label}-" in out.stdout and "Traceback" not in out.stderr
    listed = neso_run("networks", "list", "--registry", str(registry), "--json")
    rows = json.loads(listed.stdout)
    shipped = [r for r in rows if r["where"] == "shipped"]
    trained = [r for r in rows if r["where"] == "registry"]
    on_disk = sorted((Path(REPO) / "networks").rglob("*.safetensors"))
    assert sorted(Path(REPO, r["path"]).resolve() for r in shipped) == [p.resolve() for p in on_disk]
    (default,) = [r for r in shipped if r["flown_by_default"]]
    assert Path(REPO, default["path"]).resolve() == Path(REPO, DEFAULT_NETWORK).resolve()
    assert len(trained) == 1 and trained[0]["parent"] == default["id"] and trained[0]["label"] == tdr_label
    table = neso_run("networks", "list", "--registry", str(registry)).stdout
    assert f"shipped  {default['id']} *" in table and "registry " in table

    refused = neso_run("train", str(rrd), "--offline", "--registry", str(registry))  # offer asked, offline
    assert refused.returncode == 1 and refused.stdout.count("\n") == 1 and "--no-offer" in refused.stdout


def test_offline_training_outside_the_checkout_warm_starts_from_the_shipped_network(tmp_path):
    """Issue 32: run from a user's own folder, `neso train FILE --no-offer --offline` failed with "No such file or
    directory: 'networks/base.safetensors'"; the estimator finds the shipped network from anywhere, so must this."""
    registry = tmp_path / "registry"
    out = subprocess.run([sys.executable, "-m", "cli.main", "train", str(EXAMPLE), "--no-offer", "--offline",
                          "--epochs", "2", "--registry", str(registry)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"tdr warm-started from {Path(REPO, DEFAULT_NETWORK)}" in out.stdout and "No such file" not in out.stdout
    (trained,) = registry.rglob("*.safetensors")
    assert load_network(trained).metadata["parent"] == load_network(Path(REPO, DEFAULT_NETWORK)).metadata["id"]


def test_what_if_with_a_negative_bound_is_refused_in_one_line_without_a_warning():
    out = neso_run("replay", "recordings/examples/nominal-landing-eso.rrd", "--what-if", "L_N=-1")
    assert out.returncode == 1 and out.stdout == "error: L_N=-1: must be a positive number\n", out.stdout
    assert out.stderr == "", out.stderr  # numpy's ComplexWarning leaked here


def test_an_estimator_whose_network_file_is_missing_says_so_in_one_line(tmp_path):
    missing = str(tmp_path / "nope.safetensors")
    r = neso_run("run", "estimator", "--connect", "tcp/127.0.0.1:9", "--network", missing, timeout_s=60)
    assert r.returncode == 2, r
    assert "Traceback" not in r.stderr, r.stderr
    assert f"[estimator] error: network {missing!r}" in r.stderr and "No such file" in r.stderr, r.stderr
