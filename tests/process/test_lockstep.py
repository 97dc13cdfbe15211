"""Exactness: a lockstep run through separate processes reproduces the in-process runner.

Every sample reaches a subscriber once and in order. The flight runs until the test's probe holds every sample the
runner flew — no deadline cuts it short (the wait ends only when no sample has come for 30 s: the loop stalled) —
so a sample missing between two that arrived is one the system lost. The test read its probe as soon as `neso up`
had ended before: on a loaded machine the tail of the flight was still on its way to the test process (140 of 550
samples "missing" in a full run; 268 of 550 with its interpreter kept busy, ``NESO_TEST_LOAD_GIL=3 pytest -p
tests.load``), though the system had published every one."""
from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from neso.eso import EsoConfig
from neso.estimator import NeuralEsoConfig
from neso.methods import build_estimator
from neso.netfile import load_network
from neso.trajectories import Landing
from neso.types import LOOP_PERIOD_S, OMEGA_O_RPS
from runtime.probe import Probe
from sim.runner import fly
from sim.scenarios import make_scenario
from tests.busutil import REPO, free_port, neso, peer, session, stop

pytestmark = pytest.mark.offline  # lockstep: nothing here flies in real time (tests/conftest.py)

NETWORK = f"{REPO}/networks/base.safetensors"
STALL_S = 30.0


def test_lockstep_processes_reproduce_the_in_process_runner():
    seed, duration_s = 7, 11.0
    estimator = build_estimator("neural_eso", NeuralEsoConfig(eso=EsoConfig(omega_o_rps=OMEGA_O_RPS, dt_s=LOOP_PERIOD_S)),
                                {"base": load_network(NETWORK)})
    log = fly(sim_config=make_scenario("nominal_landing"), estimator=estimator, trajectory=Landing(end_height_m=0.1),
              seed=seed, duration_s=duration_s)
    n = len(log.t_s)

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with session(peer(endpoint)) as s:
        probe = Probe(s)
        token = s.liveliness().declare_token(probe.keys.alive("probe"))
        proc = neso("up", "--lockstep", "--scenario", "nominal_landing", "--mission", "landing_test", "--seed",
                    str(seed), "--network", NETWORK, "--hub", endpoint, "--wait-for", "probe", "--no-dashboard",
                    "--no-record", "--no-trainer")  # --duration 0: it flies on until stopped here
        try:
            count, progress_s = 0, time.monotonic()
            while count < n:
                assert proc.poll() is None, "neso up ended"
                if len(probe.get("truth")) > count:
                    count, progress_s = len(probe.get("truth")), time.monotonic()
                assert time.monotonic() - progress_s < STALL_S, \
                    f"the loop stalled: no sample for {STALL_S:.0f} s after {count} of {n}"
                time.sleep(0.05)
        finally:
            out = stop(proc)
        token.undeclare()
        truth, setpoints = probe.get("truth")[:n], probe.get("setpoint")
    assert "Traceback" not in out, out[-3000:]
    seqs = [m.seq for m in truth]
    lost = sorted(set(range(max(seqs) + 1)) - set(seqs))
    assert not lost, f"lost: samples {lost[:10]}… ({len(lost)}) never arrived while later ones did"
    assert seqs == list(range(n)), "every sample arrives once, in order"

    pos = np.array([m.pos_enu_m for m in truth])
    t = np.array([m.t_s for m in truth])
    answers: dict[int, float] = {}  # a state the source re-sent (no setpoint within 1 s) is answered again, alike
    for m in setpoints:
        assert answers.setdefault(m.seq, m.thrust_n) == m.thrust_n, f"sample {m.seq} answered twice, differently"
    thrust = np.array([answers[k] for k in range(n)])
    assert np.max(np.abs(t - log.t_s)) == 0.0
    err = np.max(np.abs(pos - log.pos_true_m))
    assert err <= 1e-9, f"trajectory differs by {err} m"
    assert np.max(np.abs(thrust - log.thrust_n)) <= 1e-9
    assert abs(pos[-1, 2] - 0.1) < 0.03, "the landing test really descended to 0.1 m"


def test_a_paced_lockstep_flight_is_no_faster_than_its_pace_and_loses_nothing():
    """``--lockstep-pace 4``: at most 4× real time — every state's wall-clock stamp at least a quarter period after
    the one before, a lower bound a loaded machine can only lengthen (it failed in CI at 0.993 s for 199 periods when
    the pace was a fixed grid: a late first sample was caught up) — every sample once and in order. Without
    ``--lockstep`` the pace is refused in one line."""
    pace, rate_hz, duration_s = 4.0, 50.0, 4.0
    refused = subprocess.run([sys.executable, "-m", "cli.main", "up", "--lockstep-pace", "4", "--no-dashboard"],
                             cwd=REPO, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and refused.stdout.strip() == \
        "neso up: --lockstep-pace 4: a multiple of real time ≥ 0, with --lockstep", refused.stdout + refused.stderr
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with session(peer(endpoint)) as s:
        probe = Probe(s)
        token = s.liveliness().declare_token(probe.keys.alive("probe"))
        proc = neso("up", "--lockstep", "--lockstep-pace", str(pace), "--duration", str(duration_s), "--rate",
                    str(rate_hz), "--hub", endpoint, "--wait-for", "probe", "--no-dashboard", "--no-record",
                    "--no-trainer")
        try:
            n = int(duration_s * rate_hz)
            progress_s, count = time.monotonic(), 0
            while count < n:  # the flight ends by itself after its duration; the tail may still be on its way
                if len(probe.get("truth")) > count:
                    count, progress_s = len(probe.get("truth")), time.monotonic()
                assert time.monotonic() - progress_s < STALL_S, f"no sample for {STALL_S:.0f} s after {count} of {n}"
                time.sleep(0.05)
        finally:
            out = stop(proc, timeout_s=20.0)
        token.undeclare()
        truth = probe.get("truth")
    assert "Traceback" not in out, out[-3000:]
    assert [m.seq for m in truth] == list(range(n)), "every sample once, in order"
    wall_s, world_s = truth[-1].stamp_s - truth[0].stamp_s, truth[-1].t_s - truth[0].t_s
    assert world_s == pytest.approx((n - 1) / rate_hz)
    assert wall_s >= world_s / pace * (1 - 1e-3), (wall_s, world_s)
    gaps_s = [b.stamp_s - a.stamp_s for a, b in zip(truth, truth[1:])]
    assert min(gaps_s) >= 1.0 / rate_hz / pace - 1e-6, (min(gaps_s), gaps_s.index(min(gaps_s)))
    print(f"\n{n} samples: {world_s:.2f} s of the world in {wall_s:.2f} s of the wall clock ({world_s / wall_s:.2f}× "
          f"real time, at most {pace:g}×)")


def test_a_short_lockstep_flight_is_recorded_whole(tmp_path):
    """``neso up --lockstep --duration 3``, as fast as its services answer: the flight's recording holds every one of
    its 150 states and setpoints, from sample 0. Such a flight once went unrecorded (loaded run 39; every time on a
    quiet machine too): it was over before the recorder's 0.5 s of flying had passed on the wall clock, the only clock
    its flights began by. The world also waits for the recorder now, and the recorder says it is alive once
    subscribed."""
    from recordings.reader import read_recording

    n = 150
    r = subprocess.run([sys.executable, "-m", "cli.main", "up", "--lockstep", "--duration", str(n / 50),
                        "--hub", f"tcp/127.0.0.1:{free_port()}", "--no-dashboard", "--no-trainer",
                        "--recordings-dir", str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "Traceback" not in r.stdout + r.stderr, r.stdout[-3000:] + r.stderr[-3000:]
    files = sorted(tmp_path.glob("*.rrd"))
    assert len(files) == 1, (files, r.stdout[-3000:])
    rec = read_recording(files[0])
    for topic in ("state", "setpoint"):
        # a set: a state unanswered for a second is sent again (a loaded machine), and both are recorded
        assert sorted({m.seq for m in rec.channel(topic).messages()}) == list(range(n)), (topic, r.stdout[-3000:])
