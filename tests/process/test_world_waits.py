"""The simulated world starts once its loop is alive: `neso run source` alone publishes no state; started after it,
the estimator and the controller answer the world's sample 0 (a world that started first flew unanswered, and the
controller, taking the flight as one it joined, held the vehicle where it had fallen to: 6 cm below the hover in a
two-vehicle NatNet flight once the source started faster than the controller). Its clock starts once the controller
has answered sample 0: a first state the loop never got is sent again, and a loop that never answers does not hold the
world for longer than ``first_answer_wait_s``."""
from __future__ import annotations

import os
import signal
import threading
import time

from flight.source import SourceConfig
from runtime.probe import Probe
from runtime.schema import SetpointMsg, StateMsg
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


def _fly_with_a_stand_in_controller(answer_from_arrival: int | None) -> tuple[list, list[float], float, str]:
    """The source alone, waiting for a controller this test stands in for: it answers sample 0 from that sample's
    ``answer_from_arrival``-th arrival on (None: never). (states, their arrival times, when it answered, the source's
    output)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint), session(peer(endpoint)) as s:
        probe = Probe(s, topics=("state",))
        put = s.declare_publisher(probe.keys.topic("setpoint")).put
        arrivals_of_0, answered_s = [0], [float("nan")]
        lock = threading.Lock()

        def answer(sample) -> None:
            state = StateMsg.from_bytes(sample.payload.to_bytes())
            with lock:
                if state.seq != 0 or answer_from_arrival is None:
                    return
                arrivals_of_0[0] += 1
                if arrivals_of_0[0] >= answer_from_arrival and answered_s[0] != answered_s[0]:
                    answered_s[0] = time.monotonic()
                    put(SetpointMsg(seq=0, stamp_s=answered_s[0], state_stamp_s=state.stamp_s, t_s=state.t_s,
                                    roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, thrust_norm=0.0, thrust_n=0.0,
                                    acc_cmd_enu_mps2=(0.0, 0.0, -9.81), estimate_source="local_eso").to_bytes())

        sub = s.declare_subscriber(probe.keys.topic("state"), answer)
        token = s.liveliness().declare_token(probe.keys.alive("controller"))
        source = neso("run", "source", "--vehicle", "uav1", "--connect", endpoint, "--scenario", "nominal_landing",
                      "--duration", "1", "--wait-for", "controller")
        try:
            probe.wait_for("state", lambda m: m.seq >= 10, 30.0)
        finally:
            said = stop(source)
            token.undeclare()
            sub.undeclare()
        with probe.lock:
            return list(probe.messages["state"]), list(probe.arrivals["state"]), answered_s[0], said


def test_a_first_state_the_controller_did_not_get_is_sent_again_and_the_worlds_clock_starts_at_its_answer():
    states, arrived_s, answered_s, said = _fly_with_a_stand_in_controller(answer_from_arrival=2)
    assert [m.seq for m in states[:3]] == [0, 0, 1], [m.seq for m in states[:5]]
    assert states[0] == states[1], "the same sample 0, sent again"
    assert arrived_s[1] - arrived_s[0] >= SourceConfig().first_answer_resend_s * 0.9, "re-sent after its period"
    assert states[2].stamp_s >= answered_s, "sample 1 only after the answer: the world held its clock"
    assert states[2].t_s - states[0].t_s == 1.0 / SourceConfig().rate_hz, "one period of the world's time"
    assert "sample 0 answered after it was sent 2 times" in said, said[-2000:]


def test_a_controller_that_never_answers_holds_the_world_at_sample_0_no_longer_than_its_wait():
    states, _arrived_s, _answered_s, said = _fly_with_a_stand_in_controller(answer_from_arrival=None)
    wait_s = SourceConfig().first_answer_wait_s
    first_1 = next(i for i, m in enumerate(states) if m.seq == 1)
    assert all(m.seq == 0 for m in states[:first_1]) and first_1 >= 2, [m.seq for m in states[:first_1 + 1]]
    assert states[first_1].stamp_s - states[0].stamp_s >= wait_s, "held for the whole wait"
    assert f"no setpoint for sample 0 within {wait_s:g} s" in said and "the world's clock starts anyway" in said, \
        said[-2000:]
    assert [m.seq for m in states[first_1:]] == list(range(1, len(states) - first_1 + 1)), "then every sample once"


def test_a_world_that_stood_still_says_so_and_its_time_goes_on_by_one_period():
    """A source process stopped for a second (SIGSTOP: no CPU at all, as the 1.5 s that PX4's simulator link
    timed out on in one run) says how long its world stood still and where; its world's time does not jump."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with hub(endpoint), session(peer(endpoint)) as s:
        probe = Probe(s, topics=("state",))
        source = neso("run", "source", "--vehicle", "uav1", "--connect", endpoint, "--wait-for", "")
        try:
            before = probe.wait_for("state", lambda m: m.seq >= 10, 30.0)
            os.kill(source.pid, signal.SIGSTOP)
            time.sleep(1.0)
            os.kill(source.pid, signal.SIGCONT)
            probe.wait_for("state", lambda m: m.seq >= before.seq + 60, 30.0)
        finally:
            said = stop(source)
    states = probe.get("state")
    gaps = [(a, b) for a, b in zip(states, states[1:]) if b.stamp_s - a.stamp_s > 0.9]
    assert len(gaps) == 1, [(a.seq, b.seq, b.stamp_s - a.stamp_s) for a, b in gaps]
    a, b = gaps[0]
    assert b.seq == a.seq + 1 and abs(b.t_s - a.t_s - 1.0 / SourceConfig().rate_hz) < 1e-9, (a, b)
    stood = [line for line in said.splitlines() if "the world stood still" in line]
    assert len(stood) == 1 and f"before sample {b.seq} " in stood[0] and "the process had no CPU" in stood[0], \
        said[-2000:]
    assert float(stood[0].split("stood still ")[1].split(" s")[0]) >= 1.0, stood[0]
