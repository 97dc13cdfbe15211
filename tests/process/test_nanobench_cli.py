"""`neso recordings import` on NanoBench CSVs as a user runs it (real processes, the shipped real flights): the good
flights written and listed, every bad one refused in one line (exit 1, nothing written for it), and a PX4 option
refused for a CSV."""
from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from bench.nanobench import SUBSET, subset_files
from tests.busutil import REPO

pytestmark = pytest.mark.offline  # CSV import: no flight (runs beside the flights: tests/conftest.py)


def run(*args: str, timeout_s: float = 120.0) -> tuple[int, str]:
    out = subprocess.run([sys.executable, "-m", "cli.main", *args], cwd=REPO, capture_output=True, text=True,
                         timeout=timeout_s)
    return out.returncode, out.stdout + out.stderr


def test_import_writes_the_good_flights_and_refuses_each_bad_one_in_a_line(tmp_path, rerun_home):
    train, _ = subset_files()
    copy = tmp_path / "copy.csv.xz"
    shutil.copy(train[0], copy)
    never, extrapolated = SUBSET / "refused" / "B7_oval_slow_rep1.csv.xz", SUBSET / "refused" / "B6_linear_ramp_rep4.csv.xz"
    out = tmp_path / "out"
    code, text = run("recordings", "import", str(train[0]), str(train[1]), str(copy), str(never), str(extrapolated),
                     "--out", str(out))
    errors = [line for line in text.splitlines() if line.startswith("error: ")]
    assert code == 1 and len(errors) == 3, text
    assert f"{copy}: byte-identical to {train[0]}" in errors[0], text
    assert "never flew" in errors[1] and "motor ratio reaches" in errors[2], text
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name.replace(".csv.xz", ".rrd") for p in train[:2])
    assert text.count("imported ") == 2 and "median of the 2 flight(s)" in text, text
    code, text = run("recordings", "list", str(out))
    assert code == 0 and text.count("NanoBench ") == 2 and "(Crazyflie 2.1, Vicon)" in text, text

    only_bad = tmp_path / "only-bad"
    code, text = run("recordings", "import", str(never), "--out", str(only_bad))
    assert code == 1 and text.strip().splitlines() == [f"error: {never}: never flew: the motors never ran (2.1 s of rows)"]
    assert not only_bad.exists()
    code, text = run("recordings", "import", str(train[0]), "--hover-thrust", "0.5", "--out", str(only_bad))
    assert code == 1 and "--hover-thrust and --thrust-source are for PX4 logs" in text and not only_bad.exists(), text
