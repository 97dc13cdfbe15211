"""Network hot swap through the real bus command path of a `neso up` hover flight (real processes, real Zenoh).

Five bad candidates are offered and each is refused with its reason while the active network keeps
flying; then a good one goes into shadow, is promoted in flight without a step in the commanded
force, and is rolled back.
"""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from neso.netfile import network_to_bytes, save_network
from runtime.client import command
from runtime.launcher import interrupt
from runtime.probe import Probe
from runtime.schema import EventMsg, Keys
from tests.busutil import free_port, neso, peer, session
from tests.helpers import (FORCE_STEP_LIMIT_N, candidate, flight_messages, max_force_step_n, nan_weights, random_network,
                           with_header, with_meta, write_recording)

KEYS = Keys("uav1")


class Flight:
    def __init__(self, registry):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.registry = registry
        self.proc = neso("up", "--scenario", "nominal_landing", "--mission", "hover", "--hub", self.endpoint,
                         "--no-record", "--no-dashboard", "--registry", registry)
        self.output: list[str] = []
        threading.Thread(target=lambda: self.output.extend(self.proc.stdout), daemon=True).start()
        self._cm = session(peer(self.endpoint))
        self.s = self._cm.__enter__()
        self.probe = Probe(self.s, topics=("estimate", "setpoint", "network"))
        self.events: list[EventMsg] = []
        self.sub = self.s.declare_subscriber(KEYS.event("estimator"),
                                             lambda smp: self.events.append(EventMsg.from_bytes(smp.payload.to_bytes())))

    def cmd(self, name, **args):
        return command(self.s, KEYS, "estimator", name, args, timeout_s=5.0)

    def latest(self, topic):
        return self.probe.get(topic)[-1]

    def close(self):
        self.sub.undeclare()
        self._cm.__exit__(None, None, None)
        interrupt(self.proc)  # its output is being pumped by a thread


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    f = Flight(str(tmp_path_factory.mktemp("registry")))
    try:
        f.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > 50, 30.0)
        f.probe.wait_for("network", lambda m: m.active.get("id") == "base", 5.0)
        yield f
    finally:
        f.close()


def _files(tmp):
    good = network_to_bytes(candidate())
    over = candidate()
    from neso.network import LipschitzMLP

    f = (1.1 * over.lipschitz_bound / over.certified_lipschitz_state()) ** (1 / over.n_layers)  # 10 % over its bound
    over = LipschitzMLP(tuple(w * f for w in over.weights), over.biases, over.input_mean, over.input_std,
                        over.output_mean, over.output_std, 1e9, over.metadata, over.bound_units)
    bad = {
        "truncated": (good[: len(good) // 2], "truncated"),
        "nan": (nan_weights(good), "non-finite"),
        "shapes": (network_to_bytes(with_meta(random_network(3, sizes=(5, 16, 16, 1), bound=1.0), vehicle="uav1",
                                              val_loss=0.1)), "wrong layer shapes"),
        "over_bound": (with_header(network_to_bytes(over), lipschitz_bound=repr(candidate().lipschitz_bound)),
                       "certificate fails"),
        "unknown_inputs": (with_header(good, feature_set="sonar@1"), "unknown feature set"),
        "other_vehicle": (network_to_bytes(candidate(vehicle="uav2")), "for vehicle 'uav2'"),
    }
    paths = {}
    for name, (data, reason) in bad.items():
        path = tmp / f"{name}.safetensors"
        path.write_bytes(data)
        paths[name] = (str(path), reason)
    return paths


def test_bad_candidates_are_refused_with_the_reason_and_the_active_network_keeps_flying(flight, tmp_path):
    for name, (path, reason) in _files(tmp_path).items():
        n_events = len(flight.events)
        reply = flight.cmd("offer", path=path)
        # ok=False says "refused"; the message says why, once (`neso cmd` printed "refused: refused: …")
        assert not reply.ok and reason in reply.message and not reply.message.startswith("refused"), (name, reply.message)
        time.sleep(0.3)
        assert any(reason in e.text and e.level == "warning" for e in flight.events[n_events:]), name
        net = flight.latest("network")
        assert net.active["id"] == "base" and net.candidate == {} and net.shadow_error_rms_mps2 == -1.0, name
        assert flight.latest("estimate").network_id == "base", name


def test_a_good_candidate_runs_in_shadow_is_promoted_bumplessly_and_rolled_back(flight, tmp_path):
    path = str(tmp_path / "good.safetensors")
    save_network(path, candidate(seed=5))
    reply = flight.cmd("offer", path=path)
    assert reply.ok and "shadow" in reply.message, reply.message
    shadow = flight.probe.wait_for("network", lambda m: m.candidate.get("id") == "cand-5"
                                   and m.shadow_error_rms_mps2 >= 0 and m.seq > 0, 3.0)
    assert shadow.candidate["state"] == "shadow" and shadow.active["id"] == "base"
    time.sleep(1.0)
    before = flight.latest("estimate").seq
    reply = flight.cmd("promote")
    assert reply.ok, reply.message
    flight.probe.wait_for("estimate", lambda m: m.network_id == "cand-5", 2.0)
    first = min((m for m in flight.probe.get("estimate") if m.network_id == "cand-5"), key=lambda m: m.seq)
    assert first.seq <= before + 10
    time.sleep(0.5)
    sps = {m.seq: m for m in flight.probe.get("setpoint") if first.seq - 10 <= m.seq <= first.seq + 10}
    pairs = [[sps[k - 1], sps[k]] for k in sps if k - 1 in sps]  # consecutive samples only (a loaded machine drops some)
    assert len(pairs) >= 8 and max(max_force_step_n(p) for p in pairs) <= FORCE_STEP_LIMIT_N + 1e-6
    ests = {m.seq: m for m in flight.probe.get("estimate")}
    jump = abs(ests[first.seq].f_hat_mps2[2] - ests[first.seq - 1].f_hat_mps2[2])
    typical = np.median([abs(ests[k].f_hat_mps2[2] - ests[k - 1].f_hat_mps2[2])
                         for k in range(first.seq - 40, first.seq - 1) if k in ests and k - 1 in ests])
    assert jump <= 10 * typical + 0.02, f"f̂ step {jump} at the swap, typical {typical}"
    net = flight.probe.wait_for("network", lambda m: m.active.get("id") == "cand-5", 2.0)
    assert net.previous["id"] == "base" and net.candidate == {}
    reply = flight.cmd("rollback")
    assert reply.ok, reply.message
    flight.probe.wait_for("estimate", lambda m: m.network_id == "base" and m.seq > first.seq, 2.0)
    net = flight.probe.wait_for("network", lambda m: m.active.get("id") == "base" and m.previous, 2.0)
    assert net.previous["id"] == "cand-5"
    assert not flight.cmd("promote").ok, "nothing to promote after a rollback"


def test_neso_train_has_the_trainer_train_on_a_recording_and_offer_the_result(flight, tmp_path):
    rrd = tmp_path / "eso-flight.rrd"
    write_recording(rrd, flight_messages(300, pathway="eso"))
    proc = neso("train", str(rrd), "--base", "--epochs", "3", "--connect", flight.endpoint)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert "job 1 queued" in out and "job 1 done" in out and "offer accepted" in out, out
    net = flight.probe.wait_for("network", lambda m: m.candidate.get("id", "").startswith("uav1-eso-"), 5.0)
    assert net.active["id"] == "base" and net.candidate["state"] == "shadow"
    listing = neso("networks", "list", "--registry", flight.registry)
    out, _ = listing.communicate(timeout=30)
    assert listing.returncode == 0 and net.candidate["id"] in out and "eso-flight.rrd" in out, out
    bad = neso("train", str(tmp_path / "missing.rrd"), "--connect", flight.endpoint)
    out, _ = bad.communicate(timeout=60)
    assert bad.returncode == 1 and "no such recording" in out, out
