"""`neso demo tdr --world px4`: the Total Disturbance Retraining loop with real PX4 v1.16.0 SITL in the loop (a flight
of its own, ~3.5 min): take-off as an operator does, the lemniscate recorded, a TDR network trained from the
recording, certified, predicted, offered only if predicted better, promoted in flight, the lemniscate again."""
from __future__ import annotations

import json
import math
import subprocess
import sys

from tests.busutil import REPO


def test_the_tdr_loop_flies_with_px4_in_the_loop(tmp_path):
    report_path = tmp_path / "report.json"
    done = subprocess.run([sys.executable, "-m", "cli.main", "demo", "tdr", "--world", "px4", "--epochs", "30",
                           "--dashboard-port", "0", "--workdir", str(tmp_path / "work"), "--json", str(report_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=600)
    print(done.stdout[-3000:])
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    report = json.loads(report_path.read_text())
    assert report["world"] == "px4" and len(report["lemniscate_start_t_s"]) == 2
    assert math.isfinite(report["rmse_before_cm"]) and math.isfinite(report["rmse_after_cm"])
    assert report["cycles_before_samples"] >= 1400 and report["cycles_after_samples"] >= 1400  # five 6 s cycles
    assert " done: " in report["trainer_summary"] and report["certificate"].get("holds") is True
    predicted = report["predicted"]["change"]
    assert report["offered"] == (predicted < 0), (report["offered"], predicted)  # offered only if predicted better
    assert report["missed_setpoints"] <= 0.01 * max(report["states"], 1) or not report["offered"], report["missed_setpoints"]
    if report["offered"]:
        assert report["swap_answered"] and report["canary"], report
