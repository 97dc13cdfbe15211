"""The whole TDR loop in simulation through `neso up` (real processes, real Zenoh, real `.rrd` files, real time).

Fly the near-ground lemniscate under Neural-ESO with the base network while the recorder writes the
flight; stop the recording; the trainer service trains a TDR network from the `.rrd` starting from
the active network, certifies and stores it and offers it; the estimator's gate puts it in shadow;
it is promoted in flight; the lemniscate is flown again. ~100 s on two cores.
"""
from __future__ import annotations

import json
import os

import pytest

from cli.demo import FORCE_STEP_LIMIT_N, fly_tdr_loop
from tests.busutil import free_port

pytestmark = pytest.mark.slow  # ~100 s: the whole loop in real time


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("tdr")
    report = fly_tdr_loop(hub=f"tcp/127.0.0.1:{free_port()}", workdir=str(workdir), log=lambda *_: None)
    print("\n".join(report.lines()))
    return report, workdir


def test_a_network_retrained_from_the_recording_is_promoted_in_flight_without_a_bump(loop):
    report, workdir = loop
    assert os.path.isfile(report.recording) and report.recording.startswith(str(workdir))
    sidecars = list((workdir / "registry" / "uav1").glob("*.json"))
    assert len(sidecars) == 1
    info = json.loads(sidecars[0].read_text())
    assert info["id"] == report.network_id and info["parent"] == "base-L1.0" and info["label"] == "tdr"
    assert info["recordings"] == [report.recording] and info["certified_phys"] <= info["lipschitz_phys"] * (1 + 1e-6)
    assert info["val_loss"] >= 0 and info["certificate"]["max_certified_lipschitz"] > 0
    assert report.cycles_before_samples > 1000 and report.cycles_after_samples > 1000, "5 cycles each (1500 samples)"
    # the total estimate is continuous: the step at the swap is no larger than the flight's usual steps
    assert report.f_hat_step_at_swap_mps2 <= report.f_hat_step_p99_mps2
    assert report.force_step_at_swap_n <= FORCE_STEP_LIMIT_N + 1e-9
    # deadlines: the swap sample is answered on time; around it and elsewhere at most what the shared
    # machine's load causes (measured 2-3 % of samples over the whole flight at load average ~9 on 2 cores)
    assert report.swap_answered
    assert report.missed_near_swap <= 3, report.missed_by_phase
    assert report.missed_setpoints <= 0.06 * report.states, report.missed_by_phase


@pytest.mark.xfail(strict=True, reason=(
    "not in this simulator: TDR makes the near-ground lemniscate worse here (measured 1.64 -> 2.69, "
    "1.59 -> 3.66, 1.11 -> 20.0 and 1.06 -> 2.92 cm in four runs; offline `neso experiment paper`: 1.18 -> 1.86 cm). "
    "The scenario's out-of-distribution disturbance is zero-mean Dryden gusts (correlation 0.1-0.2 s, "
    "sim/turbulence.py) that no function of the state predicts, and the TDR network learns the closed-loop "
    "identity T_{k-1} = m(g + a_d - f_hat_{k-1}) instead (README, 'What the simulation shows')."))
def test_z_rmse_after_the_swap_is_at_least_40_percent_lower(loop):
    report, _ = loop
    assert report.improvement >= 0.40, f"{report.rmse_before_cm:.2f} -> {report.rmse_after_cm:.2f} cm"
