"""The simulated world starts once its loop is alive: `neso run source` alone publishes no state; started after it,
the estimator and the controller answer the world's sample 0 (a world that started first flew unanswered, and the
controller, taking the flight as one it joined, held the vehicle where it had fallen to: 6 cm below the hover in a
two-vehicle NatNet flight once the source started faster than the controller)."""
from __future__ import annotations

import time

from runtime.probe import Probe
from tests.busutil import free_port, hub, neso, peer, session, stop


def test_the_simulated_world_waits_for_its_estimator_and_controller_then_they_answer_its_first_sample():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint), session(peer(endpoint)) as s:
        probe = Probe(s, topics=("state", "setpoint", "truth"))
        common = ("--vehicle", "uav1", "--connect", endpoint)
        source = neso("run", "source", *common, "--scenario", "nominal_landing", "--duration", "6")
        loop = []
        try:
            time.sleep(3.0)  # the source up and waiting (it starts in ~1 s)
            assert source.poll() is None and not probe.get("state"), "no world before its loop"
            loop = [neso("run", "estimator", *common), neso("run", "controller", *common, "--mission", "hover")]
            probe.wait_for("setpoint", lambda m: m.seq >= 100, 30.0)
        finally:
            said = {p.args[4]: stop(p) for p in [source, *loop]}
    states, setpoints = probe.get("state"), probe.get("setpoint")
    assert states[0].seq == 0 and setpoints[0].seq == 0, (states[0].seq, setpoints[0].seq)
    assert "joined a flight" not in said["controller"], said["controller"][-2000:]
    assert "real time: ['estimator', 'controller'] alive, starting" in said["source"], said["source"][-2000:]
    assert abs(probe.get("truth")[-1].pos_enu_m[2] - states[0].pos_enu_m[2]) < 0.05, "held where it started"
