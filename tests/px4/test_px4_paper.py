"""`neso experiment paper --world px4`, reduced, end to end: the built-in pipeline (1 trial, 5 epochs, one recipe)
trains the networks, real PX4 v1.16.0 SITL flies N-ESO (the trained network in the loop) on the nominal landing
and the lemniscate (two PX4 boots, real MAVSDK, ~80 s), and the JSON holds figures from flights that happened,
beside the built-in world's."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

from sim.tuning import TUNED_GAINS
from tests.busutil import REPO
from tests.px4 import px4_env


def _neso(*args: str, env: dict | None = None, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli.main", "experiment", "paper", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_the_paper_experiments_fly_on_px4_and_the_json_is_real(tmp_path):
    out, details = tmp_path / "paper-px4.json", tmp_path / "details.json"
    started = time.monotonic()
    # the tuned baseline at the gains the search states (tests/sim/test_tuning.py flies the search itself; PX4 flies
    # only N-ESO here): without them the built-in part searches first (~70 s of this test on a quiet machine)
    tuned = [f"--tuned={k}={g.kp:g},{g.kd:g},{g.omega_o_rps:g}" for k, g in TUNED_GAINS.items()]
    done = _neso("--world", "px4", "--trials", "1", "--epochs", "5", "--recipes", "certified", *tuned,
                 "--px4-experiments", "nominal_landing,lemniscate_near_ground", "--px4-methods", "neural_eso",
                 "--json", str(out), "--details", str(details),
                 env=dict(os.environ, **px4_env(tmp_path)))
    print(f"\n{done.stdout[-3000:]}\nreduced run: {time.monotonic() - started:.0f} s")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    res, det = json.loads(out.read_text()), json.loads(details.read_text())
    flights = det["px4_flights"]["paper"]
    assert len(flights) == 2 and all("failed" not in f for f in flights), flights
    # the version PX4 itself reported in these flights (AUTOPILOT_VERSION), not a constant
    assert all(f["autopilot"].startswith("PX4 v1.16.0 ") for f in flights), [f["autopilot"] for f in flights]
    assert res["world"] == "px4" and res["px4_version"] == flights[0]["autopilot"].removeprefix("PX4 ")
    assert res["gains"] == "paper"
    for f in flights:  # each flight happened: PX4 answered every sensor period of it in the air, and armed itself
        assert f["airborne_exchanges"] > 5 * 50 * 10 and f["exchanges"] > f["airborne_exchanges"]
        assert f["link_dropped"] == 0 and f["link_stalls"] == 0 and f["armed_after_s"] > 0 and f["airborne_at_start_s"] > f["armed_after_s"] / 2
        assert 0.0 <= f["saturated_percent"] <= 100.0
        assert 0.05 < f["hover_thrust_learnt"] < 0.95
        assert f["not_offboard_periods"] == 0  # PX4 flew our setpoints the whole experiment, no failsafe of its own
    for scenario in ("nominal_landing", "lemniscate_near_ground"):
        px4, builtin = res["experiments"][scenario], res["builtin"]["experiments"][scenario]
        assert px4["metric"] == builtin["metric"]
        assert list(px4["methods"]) == ["neural_eso"]
        for method in ("neural_eso",):
            (ours,) = px4["methods"][method]["trials"]
            # N-ESO as the method flies: the README's figures are 0.3-1.5 cm (0.58 and 1.45 cm in this reduced run)
            assert ours is not None and math.isfinite(ours) and 0.0 < ours < 3.0, (scenario, method, ours)
            assert ours != builtin["methods"][method]["trials"][0]  # flown in another world, not copied
            sat = res["saturation_percent"][scenario][method]["mean"]
            assert sat is not None and 0.0 <= sat <= 100.0
    # the saturation figures are those of the flights listed
    for f in flights:
        assert res["saturation_percent"][f["scenario"]][f["method"]]["trials"] == [f["saturated_percent"]]
