"""The PX4-log commands as a user runs them (real processes): import both shared logs, `rerun rrd
verify`, the catalog with duration and source, refusals (one line, exit 1, nothing written), teacher
pairs, what-if, MCAP export, and `neso train FILE.ulg` against a real trainer service on a real bus."""
from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from recordings.reader import read_recording, rerun_cli
from tests.busutil import REPO, free_port, hub, neso, stop
from tests.ulogfiles import CUBE_LOG, SITL_LOG, without_topics

pytestmark = pytest.mark.offline  # log import, export and training from logs: no flight (runs beside the flights: tests/conftest.py)


def run(*args: str, timeout_s: float = 120.0) -> tuple[int, str]:
    out = subprocess.run([sys.executable, "-m", "cli.main", *args], cwd=REPO, capture_output=True, text=True,
                         timeout=timeout_s)
    return out.returncode, out.stdout + out.stderr


def test_both_logs_import_verify_and_are_listed_with_duration_and_source(tmp_path, rerun_home):
    for log in (SITL_LOG, CUBE_LOG):
        code, out = run("recordings", "import", str(log), "--out", str(tmp_path))
        assert code == 0 and f"imported {log.name}" in out and "mass 1 kg (ASSUMED" in out, out
        rrd = tmp_path / f"{log.stem}.rrd"
        verified = subprocess.run([rerun_cli(), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
        assert verified.returncode == 0, verified.stdout + verified.stderr
    code, out = run("recordings", "list", str(tmp_path))
    assert code == 0, out
    sitl = next(line for line in out.splitlines() if "px4-sitl-takeoff-hover.rrd" in line)
    cube = next(line for line in out.splitlines() if "cubeorange-flight.rrd" in line)
    assert "PX4 log px4-sitl-takeoff-hover.ulg (v1.15.0, PX4_SITL)" in sitl and re.search(r"\b30\.7 s\b", sitl), sitl
    assert "PX4 log cubeorange-flight.ulg (v1.11.2, CUBEPILOT_CUBEORANGE)" in cube and re.search(r"\b6\.3 s\b", cube)
    assert "imported" in sitl and "imported" in cube
    code, out = run("recordings", "dataset", str(tmp_path / "px4-sitl-takeoff-hover.rrd"), "--label", "eso")
    assert code == 0 and re.match(r"1\d\d training pairs \(eso labels\) of vehicle uav1", out), out
    code, out = run("replay", str(tmp_path / "px4-sitl-takeoff-hover.rrd"), "--what-if", "pathway=neural_eso")
    assert code == 0 and "f̂ what-if − f̂ ESO offline" in out, out
    code, out = run("recordings", "export", str(tmp_path / "px4-sitl-takeoff-hover.rrd"), "--mcap",
                    str(tmp_path / "sitl.mcap"))
    assert code == 0 and "neso/uav1/state 308" in out and (tmp_path / "sitl.mcap").stat().st_size > 10_000, out


def test_bad_input_is_one_line_exit_1_and_nothing_written(tmp_path):
    sitl = SITL_LOG.read_bytes()
    cases = {"truncated.ulg": sitl[:3000], "random.ulg": bytes(range(256)) * 400,
             "no-position.ulg": without_topics(sitl, "vehicle_local_position")}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    expected = {"truncated.ulg": "truncated", "random.ulg": "not a PX4 ULog",
                "no-position.ulg": "lacks what the method needs: topic vehicle_local_position",
                "missing.ulg": "no such file"}
    for name, needle in expected.items():
        out_dir = tmp_path / f"out-{name}"
        code, out = run("recordings", "import", str(tmp_path / name), "--out", str(out_dir))
        lines = out.strip().splitlines()
        assert code == 1 and len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], out
        assert not out_dir.exists(), f"{name}: nothing may be written"


def test_neso_train_takes_a_px4_log_and_reports_the_network(tmp_path, rerun_home):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint):
        trainer = neso("run", "trainer", "--connect", endpoint, "--registry", str(tmp_path / "registry"),
                       "--recordings-dir", str(tmp_path / "recordings"))
        try:
            code, out = run("train", str(SITL_LOG), "--base", "--epochs", "40", "--no-offer",
                            "--import-dir", str(tmp_path / "imports"), "--connect", endpoint, "--timeout", "240",
                            timeout_s=300)
        finally:
            stop(trainer)
    assert code == 0, out
    assert "imported px4-sitl-takeoff-hover.ulg" in out, out
    done = re.search(r"job \d+ done: (\S+) at (\S+): (\d+) eso samples \(state@1, 1 kg[;)].*? from 1 recording\(s\), "
                     r"val loss ([\d.e+-]+) × the mean's; slopes ∂f_N/∂input: pos_z_m .*certificate (holds|FAILS)", out)
    assert done, out
    assert 100 < int(done.group(3)) < 200 and os.path.isfile(done.group(2))
    rec = read_recording(tmp_path / "imports" / "px4-sitl-takeoff-hover.rrd")
    assert rec.properties["import"]["file_name"] == "px4-sitl-takeoff-hover.ulg"
