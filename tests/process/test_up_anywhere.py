"""`neso up` from a folder outside the checkout flies the network the project ships (a user's own flight
folder), and a service that refuses its configuration stops the run at once instead of being restarted."""
from __future__ import annotations

import subprocess
import sys

from flight.estimator import DEFAULT_NETWORK, PROJECT_ROOT
from tests.busutil import free_port


def up(cwd, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli.main", "up", "--hub", f"tcp/127.0.0.1:{free_port()}",
                           "--no-dashboard", "--no-trainer", "--recordings-dir", str(cwd / "rec"), *args],
                          cwd=cwd, capture_output=True, text=True, timeout=120)


def test_up_from_another_folder_flies_the_shipped_network(tmp_path):
    r = up(tmp_path, "--duration", "3")
    assert r.returncode == 0, r.stdout[-3000:]
    assert f"[estimator] network {PROJECT_ROOT / DEFAULT_NETWORK}: id base" in r.stdout, r.stdout[-3000:]
    assert "restarting (restart" not in r.stdout and "Traceback" not in r.stdout, r.stdout[-3000:]
    assert list((tmp_path / "rec").rglob("*.rrd")), "the flight was recorded where the user runs"


def test_a_missing_network_ends_the_run_in_one_line_without_restarts(tmp_path):
    r = up(tmp_path, "--duration", "30", "--network", "mine.safetensors")
    assert r.returncode == 2, r.stdout[-3000:]
    assert r.stdout.count("[estimator] error: network 'mine.safetensors'") == 1, r.stdout[-3000:]
    assert "estimator exited with 2: it refused its configuration" in r.stdout, r.stdout[-3000:]
    assert "restarting (restart" not in r.stdout and "Traceback" not in r.stdout, r.stdout[-3000:]
