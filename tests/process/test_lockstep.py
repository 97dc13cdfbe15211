"""Exactness: a lockstep run through separate processes reproduces the in-process runner."""
from __future__ import annotations

import numpy as np

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

NETWORK = f"{REPO}/networks/base.safetensors"


def test_lockstep_processes_reproduce_the_in_process_runner():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    seed, duration_s = 7, 11.0
    with session(peer(endpoint)) as s:
        probe = Probe(s)
        token = s.liveliness().declare_token(probe.keys.alive("probe"))
        proc = neso("up", "--lockstep", "--duration", str(duration_s), "--scenario", "nominal_landing",
                    "--mission", "landing_test", "--seed", str(seed), "--network", NETWORK, "--hub", endpoint,
                    "--wait-for", "probe", "--no-dashboard")
        try:
            proc.wait(timeout=120)
        finally:
            out = stop(proc)
        token.undeclare()
        truth, setpoints = probe.get("truth"), probe.get("setpoint")
    assert proc.returncode == 0, out

    estimator = build_estimator("neural_eso", NeuralEsoConfig(eso=EsoConfig(omega_o_rps=OMEGA_O_RPS, dt_s=LOOP_PERIOD_S)),
                                {"base": load_network(NETWORK)})
    log = fly(sim_config=make_scenario("nominal_landing"), estimator=estimator, trajectory=Landing(end_height_m=0.1),
              seed=seed, duration_s=duration_s)

    n = len(log.t_s)
    assert [m.seq for m in truth] == list(range(n)), "every sample arrives once, in order"
    pos = np.array([m.pos_enu_m for m in truth])
    t = np.array([m.t_s for m in truth])
    thrust = np.array([m.thrust_n for m in sorted(setpoints, key=lambda m: m.seq)])
    assert np.max(np.abs(t - log.t_s)) == 0.0
    err = np.max(np.abs(pos - log.pos_true_m))
    assert err <= 1e-9, f"trajectory differs by {err} m"
    assert np.max(np.abs(thrust - log.thrust_n)) <= 1e-9
    assert abs(pos[-1, 2] - 0.1) < 0.03, "the landing test really descended to 0.1 m"
