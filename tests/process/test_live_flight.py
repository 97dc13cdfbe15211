"""One real-time hover flight through `neso up` (real processes, real Zenoh), driven through its faults.

The tests share the flight and run in file order: live parameters, bad input, `kill -9` of the
estimator, `kill -9` of the hub, then Ctrl-C. Each checks the vehicle against its reference
with the simulator's truth.
"""
from __future__ import annotations

import math
import os
import random
import signal
import subprocess
import tempfile
import time

import numpy as np
import pytest

from runtime.client import get_params, set_params
from runtime.schema import EventMsg, HealthMsg, Keys, ParamStateMsg
from tests.busutil import REPO, NesoUp, children_of, flood_windows, free_port, neso, peer, role_pid, stop
from tests.helpers import FORCE_STEP_LIMIT_N, malformed_payloads, max_force_step_n, named_samples

KEYS = Keys("uav1")


class Flight(NesoUp):
    def __init__(self):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        workdir = tempfile.mkdtemp(prefix="neso-live-flight-")
        super().__init__("--scenario", "nominal_landing", "--mission", "hover", "--hub", self.endpoint, "--no-dashboard",
                         "--no-trainer", "--recordings-dir", f"{workdir}/recordings", bus=peer(self.endpoint),
                         topics=("state", "truth", "estimate", "setpoint", "reference", "network"), workdir=workdir)
        self.health: dict[str, HealthMsg] = {}
        self.param_states: list[ParamStateMsg] = []
        self.events: list[EventMsg] = []
        self.subs = [self.s.declare_subscriber(KEYS.every("health"), self._on_health),
                     self.s.declare_subscriber(KEYS.every("params"), self._on_params),
                     self.s.declare_subscriber(KEYS.every("event"),
                                               lambda s: self.events.append(EventMsg.from_bytes(s.payload.to_bytes())))]

    def _on_health(self, sample):
        msg = HealthMsg.from_bytes(sample.payload.to_bytes())
        self.health[msg.service] = msg

    def _on_params(self, sample):
        self.param_states.append(ParamStateMsg.from_bytes(sample.payload.to_bytes()))

    def wait_health(self, services, timeout_s=10.0):
        """Until every one of ``services`` has reported its health once (1 Hz)."""
        deadline = time.monotonic() + timeout_s
        while not set(services) <= set(self.health):
            assert time.monotonic() < deadline, f"no health from {set(services) - set(self.health)}"
            time.sleep(0.05)

    def wait_flying(self, timeout_s=30.0):
        self.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > 50, timeout_s)

    def tracking_error_m(self, since_seq: int, until_seq: float = math.inf) -> float:
        """Largest ‖truth − reference‖ over samples ``since_seq`` ≤ seq < ``until_seq``."""
        refs = {m.seq: m.pos_enu_m for m in self.probe.get("reference") if since_seq <= m.seq < until_seq}
        truth = {m.seq: m.pos_enu_m for m in self.probe.get("truth") if since_seq <= m.seq < until_seq}
        common = sorted(set(refs) & set(truth))
        assert len(common) > 10
        return max(float(np.linalg.norm(np.subtract(truth[k], refs[k]))) for k in common)

    def latest_seq(self, topic="state") -> int:
        msgs = self.probe.get(topic)
        return msgs[-1].seq if msgs else -1

    def pid_of(self, role: str) -> int:
        return role_pid(self.proc.pid, role)

    def close(self) -> str:
        for sub in self.subs:
            sub.undeclare()
        return super().close(kill=True)  # the faults above leave nothing worth a clean stop


@pytest.fixture(scope="module")
def flight():
    f = Flight()
    try:
        f.wait_flying()
        yield f
    finally:
        f.close()


def _bound(stem: str) -> float:
    """The physical L_N a shipped network states (the estimator's lipschitz_bound unit)."""
    from neso.netfile import load_network

    return load_network(f"{REPO}/networks/{stem}.safetensors").lipschitz_bound_physical()


def test_live_pathway_and_bound_changes_take_effect_within_one_period_bumplessly(flight):
    half = _bound("base-x0.5")
    for pathway, bound in (("eso", _bound("base")), ("neural_eso", half)):
        before = flight.latest_seq()
        # the reply waits for the new L_N's certificate, solved before the check (0.35 s idle; CI with a busy machine
        # let 2 s pass): what is claimed is counted in samples from the reply, so the reply may take its time
        reply = set_params(flight.s, KEYS, "estimator", {"pathway": pathway, "lipschitz_bound": bound}, timeout_s=10.0)
        acked_s = time.monotonic()
        assert reply.ok, reply.error
        first = flight.probe.wait_for("estimate", lambda m: m.pathway == pathway and m.seq > before, 2.0)
        # the newest state the source had published when the ack came, by the source's own stamps (the machine's
        # monotonic clock): not the newest this test had received by then, which lags a loaded test process (sample
        # 111 when the change took effect at 119, loaded run 21 at 9a6065f)
        flight.probe.wait_for("state", lambda m: m.stamp_s > acked_s, 2.0)
        acked = max(m.seq for m in flight.probe.get("state") if m.stamp_s <= acked_s)
        assert first.seq <= acked + 2, f"took effect at sample {first.seq}, ack after {acked}"
        time.sleep(0.5)
        sps = sorted((m for m in flight.probe.get("setpoint") if first.seq - 10 <= m.seq <= first.seq + 10),
                     key=lambda m: m.seq)
        assert max_force_step_n(sps) <= FORCE_STEP_LIMIT_N + 1e-6, "no step beyond the increment limit"
    state = flight.param_states[-1]
    assert state.service == "estimator" and state.values["lipschitz_bound"] == half and "base-x0.5" in state.note
    assert flight.probe.get("estimate")[-1].network_id == f"base-x0.5@L{half:.4g}"


def _neso_out(*args) -> tuple[int, str]:
    proc = neso(*args)
    out = stop(proc, timeout_s=15) if proc.wait(15) is None else proc.stdout.read()
    return proc.returncode, out


def test_params_cli_acknowledges_and_refuses_with_the_reason(flight):
    base = _bound("base")
    code, out = _neso_out("params", "set", "estimator", f"lipschitz_bound={base!r}", "--connect", flight.endpoint)
    assert code == 0 and "accepted" in out, out
    code, out = _neso_out("params", "set", "estimator", "lipschitz_bound=50", "--connect", flight.endpoint)
    assert code == 1 and "refused" in out and "above" in out, out
    assert get_params(flight.s, KEYS, "estimator").values["lipschitz_bound"] == base


def test_the_services_refuse_changes_outside_the_certificate_with_the_margin_unless_overridden(flight):
    """L_N (estimator) and k_p (controller) are checked by the process that applies them; an override is
    applied and leaves an event."""
    events = []
    subs = [flight.s.declare_subscriber(KEYS.event(svc), lambda smp: events.append(EventMsg.from_bytes(
        smp.payload.to_bytes()))) for svc in ("estimator", "controller")]
    try:
        double = _bound("base-x2")  # stable, but its |e_z| bound more than twice PD+ESO's: not certified to fly well
        code, out = _neso_out("params", "set", "estimator", f"lipschitz_bound={double!r}", "--connect", flight.endpoint)
        assert code == 1 and "certificate FAILS" in out and "fly well" in out and "cm" in out and "override" in out, out
        code, out = _neso_out("params", "set", "controller", "kd_z=0.5", "--connect", flight.endpoint)
        assert code == 1 and "certificate FAILS" in out and "margin -" in out, out
        assert get_params(flight.s, KEYS, "controller").values["kd_z"] == 6.0
        code, out = _neso_out("params", "set", "controller", "kd_z=0.5", "override=true", "--connect", flight.endpoint)
        assert code == 0 and "accepted" in out, out
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not any("by override" in e.text for e in events):
            time.sleep(0.05)
        assert any(e.service == "controller" and e.level == "warning" and "by override" in e.text and
                   "certificate FAILS" in e.text for e in events), [e.text for e in events]
        # the estimator hears the new gains and reports what flies no longer holds
        net = flight.probe.wait_for("network", lambda m: m.certificate.get("kd") == 0.5, 5.0)
        assert net.certificate["holds"] is False
        code, out = _neso_out("params", "set", "controller", "kd_z=6", "--connect", flight.endpoint)
        assert code == 0, out
        net = flight.probe.wait_for("network", lambda m: m.certificate.get("kd") == 6.0, 5.0)
        assert net.certificate["holds"] is True
    finally:
        for sub in subs:
            sub.undeclare()


def test_ten_thousand_malformed_payloads_per_key_are_counted_and_the_flight_goes_on(flight):
    rng = random.Random(1)
    counts = {t: malformed_payloads(t, flight.probe.get(t)[-1].to_bytes(), 10_000, rng)
              for t in ("state", "setpoint", "estimate")}
    pids = {r: flight.pid_of(r) for r in ("source", "estimator", "controller")}
    flight.wait_health(pids)  # run alone, the test comes before the services' first reports
    before = {s: dict(h.rejected) for s, h in flight.health.items()}
    # Ten 1 s windows, quiet and flooded in turn (2000 payloads per key in each flooded one: a flood, not a
    # denial of service), so a burst of the shared machine's own load is as likely to fall on either kind; the
    # flood goes to the services only, not to this session's probe (decoding 6000 junk payloads a second here
    # cost the machine a quarter of a core that a real flood, sent from elsewhere, does not take from the flight).
    windows = flood_windows(flight.s, KEYS, counts, flight.latest_seq, 10)
    expected = {("estimator", "state"), ("controller", "state"), ("estimator", "setpoint"), ("source", "setpoint"),
                ("controller", "estimate")}

    def counted() -> dict:
        return {(s, t): flight.health[s].rejected[t] - before[s].get(t, 0.0) for s, t in expected}

    deadline = time.monotonic() + 15.0  # health reports come at 1 Hz, later on a loaded machine
    while min(counted().values()) < 10_000 and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.5)  # one report more: none counted twice
    assert counted() == {k: 10_000 for k in expected}, "rejected payloads counted per (service, topic)"
    assert {r: flight.pid_of(r) for r in pids} == pids, "no service crashed or restarted"
    # the flight goes on as if unflooded, judged in the flight's own samples against the quiet windows flown between
    # the flooded ones (the shared machine's load falls on both kinds alike): the estimator answered every sample of
    # a flooded window, as of the quiet ones (rejecting costs a sample time, never its estimate), the hover stayed
    # as close to its reference as in the quiet windows, and the estimator's f̂ flies again once the flood is over.
    # How much of that time a sample's deadline can spare is a figure of the machine's CPU, not of the flood's
    # handling: the flood costs ~0.3 of a core in the loop's three processes and ~0.2 in the recorder (measured),
    # and under a CPU quota it pushes into throttling, estimates came past the controller's deadline (3 samples or
    # 60 ms) and it flew on its local ESO (CI: 18 and 27 of 250 flooded samples, 0 quiet; a quota of 1.2 cores
    # here: 9-27 flooded, 1-6 quiet), with a core to spare 0-2 of 250. So the deadline misses and the estimate
    # latency are printed here and measured, quiet beside flooded, in `make bench` (bench.flood).
    estimated = {m.seq for m in flight.probe.get("estimate")}
    unestimated = {kind: sum(seq not in estimated for first, end in ws for seq in range(first, end))
                   for kind, ws in windows.items()}
    flown = {m.seq for m in flight.probe.get("setpoint") if m.estimate_source == "estimator"}
    by_window = {kind: [sum(seq not in flown for seq in range(first, end)) for first, end in ws]
                 for kind, ws in windows.items()}
    missed = {kind: sum(counts) for kind, counts in by_window.items()}
    samples = {kind: sum(end - first for first, end in ws) for kind, ws in windows.items()}
    worst_m = {kind: max(flight.tracking_error_m(first, end) for first, end in ws) for kind, ws in windows.items()}
    print(f"samples flown without the estimator's f̂ (past the controller's deadline): {missed} of {samples} "
          f"(by window {by_window}); estimate latency p99 (ms): {_estimate_latency_p99_ms(flight, windows)}; worst "
          f"tracking error of a window (cm): { {k: round(v * 100, 1) for k, v in worst_m.items()} }")
    assert min(samples.values()) > 200, samples
    assert unestimated == {"quiet": 0, "flood": 0}, f"samples the estimator never answered: {unestimated}"
    assert worst_m["flood"] <= worst_m["quiet"] + 0.01, worst_m
    after = flight.latest_seq()
    flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > after, 5.0)


def _estimate_latency_p99_ms(flight, windows) -> dict[str, float]:
    """Per kind of window, the 99th percentile of estimate stamp − state stamp (one monotonic clock), ms."""
    state_s = {m.seq: m.stamp_s for m in flight.probe.get("state")}
    est_s = {m.seq: m.stamp_s for m in flight.probe.get("estimate")}
    return {kind: round(float(np.percentile([est_s[k] - state_s[k] for first, end in ws for k in range(first, end)
                                             if k in est_s and k in state_s], 99)) * 1e3, 1)
            for kind, ws in windows.items()}


def test_kill_9_of_the_estimator_falls_back_within_3_periods_and_resumes_after_restart(flight):
    old_pid = flight.pid_of("estimator")
    start = flight.latest_seq()
    n_events = len(flight.events)
    misses_before = flight.health["source"].counters.get("deadline_misses", 0.0)
    os.kill(old_pid, signal.SIGKILL)
    local = flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "local_eso" and m.seq > start, 2.0)
    last_estimator = max(m.seq for m in flight.probe.get("setpoint")
                         if m.estimate_source == "estimator" and m.seq < local.seq)
    assert local.seq - last_estimator <= 4, f"estimates stopped after {last_estimator}, local ESO from {local.seq}"
    back = flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > local.seq, 30.0)
    assert flight.pid_of("estimator") != old_pid, "the launcher restarted it"
    time.sleep(1.0)
    assert flight.tracking_error_m(start) < 0.05
    seqs = [m.seq for m in flight.probe.get("setpoint") if m.seq >= start]
    assert max(np.diff(seqs)) <= 4, "at most 3 samples without a setpoint"
    print(f"fallback after {local.seq - last_estimator} samples; estimator back at sample {back.seq}")
    # the operator is told why those samples were late: the source names the stage, the controller what it saw
    # the report naming the kill's samples (the first one may be about earlier ones a busy machine made late)
    killed = set(range(last_estimator + 1, local.seq + 1))
    misses = [e.text for e in flight.events[n_events:] if e.service == "source" and "deadline miss" in e.text]
    about_kill = [t for t in misses if named_samples(t) & killed]
    assert about_kill, (sorted(killed), misses)
    stages = about_kill[0].split("(late in: ", 1)[1].split(")", 1)[0]  # "estimator 3" or "controller 2, estimator 3"
    assert "estimator" in stages and "the estimator did not answer in time" in about_kill[0], about_kill
    assert any(e.service == "controller" and "the estimator's newest answer was for sample" in e.text
               for e in flight.events[n_events:])
    assert flight.health["source"].counters["deadline_misses"] > misses_before
    assert flight.health["controller"].counters["local_eso_fallbacks"] >= 1
    print("source:", about_kill[0])


def test_killing_the_hub_leaves_the_running_peers_talking(flight):
    hub_pid = flight.pid_of("hub")
    os.kill(hub_pid, signal.SIGKILL)
    killed_at = flight.latest_seq()
    flight.probe.wait_for("setpoint", lambda m: m.seq > killed_at + 100, 10.0)  # the world's next 2 s
    after = [m for m in flight.probe.get("setpoint") if killed_at < m.seq <= killed_at + 100]
    assert len(after) >= 80, f"only {len(after)} setpoints for the 100 samples after the hub died"
    local = [m.seq for m in after if m.estimate_source != "estimator"]
    assert not local, f"hub killed after sample {killed_at}; local ESO at samples {local}"
    assert flight.tracking_error_m(killed_at) < 0.05


def test_ctrl_c_stops_everything_within_3_s_with_nothing_left_behind(flight):
    """Ctrl-C reaches every process of the group, and the launcher's SIGTERM follows within milliseconds: a second
    signal inside the first one's handler hung the recorder and the source for good (tests/process/test_signals.py)."""
    tree = [flight.proc.pid] + children_of(flight.proc.pid)
    assert len(tree) >= 5
    names = {pid: open(f"/proc/{pid}/cmdline").read().replace("\0", " ")[-60:] for pid in tree}
    n0 = len(flight.output)
    started = time.monotonic()
    os.killpg(flight.proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    try:
        flight.proc.wait(10)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"not stopped in 10 s: {[names[p] for p in tree if os.path.exists(f'/proc/{p}')]}; "
                             f"said since: {''.join(flight.output[n0:])[-2000:]}") from None
    elapsed = time.monotonic() - started
    assert elapsed < 3.0, f"took {elapsed:.2f} s"
    time.sleep(0.2)
    alive = [p for p in tree if os.path.exists(f"/proc/{p}") and open(f"/proc/{p}/stat").read().split()[2] != "Z"]
    assert alive == [], f"left behind: {alive}"
