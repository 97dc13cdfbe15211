"""The simulated world's motion capture loses the vehicle for a second (`neso cmd source lose_tracking`): no
state is published meanwhile, the world flies on, the source says when it began and ended, none of its samples
counts as a missed deadline (by its sample numbers), and the hover comes back."""
from __future__ import annotations

import time

import numpy as np

from runtime.client import command
from runtime.schema import EventMsg
from tests.busutil import NesoUp, free_port, peer
from tests.helpers import named_samples


def test_a_second_without_motion_capture_is_no_state_then_the_hover_again(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    flight = NesoUp("--mission", "hover", "--hub", endpoint, "--no-dashboard", "--no-trainer", "--recordings-dir",
                    str(tmp_path), bus=peer(endpoint))
    events: list[EventMsg] = []
    flight.s.declare_subscriber(flight.probe.keys.every("event"),
                                lambda s: events.append(EventMsg.from_bytes(s.payload.to_bytes())))
    try:
        flight.probe.wait_for("setpoint", lambda m: m.estimate_source == "estimator" and m.seq > 150, 30.0)
        refused = command(flight.s, flight.probe.keys, "source", "lose_tracking", {"duration_s": 60}, timeout_s=8.0)
        assert not refused.ok and "0.02-10 s" in refused.message, refused
        reply = command(flight.s, flight.probe.keys, "source", "lose_tracking", {"duration_s": 1.0}, timeout_s=8.0)
        assert reply.ok, reply
        time.sleep(4.0)
    finally:
        out = flight.close()
    assert "Traceback" not in out, out[-3000:]
    states, truth = flight.probe.get("state"), flight.probe.get("truth")
    gaps = np.diff([m.t_s for m in states])
    assert 0.98 < gaps.max() < 1.05 and np.sum(gaps > 0.03) == 1, sorted(gaps)[-3:]
    assert len(truth) > len(states) + 45, "the world flew on meanwhile"
    texts = [e.text for e in events if e.service == "source"]
    assert any("lost the vehicle" in t for t in texts) and any("sees the vehicle again" in t for t in texts), texts
    since_lost = texts[next(i for i, t in enumerate(texts) if "lost the vehicle" in t):]
    # the second's samples without a state are no deadline: none of them is among the misses the source names. A
    # miss the source puts down to a busy machine may still come elsewhere (two flights side by side, load 8.67: one
    # setpoint lost on the bus 32 samples after the return, quiet run at 7472472; load 8.50: 13 of them, quiet run
    # 20 — before, the claim was read as fewer than 10 misses in all); one it cannot is a fault, and fails here
    unseen = {m.seq for m in truth} - {m.seq for m in states}
    assert 45 <= len(unseen) <= 55, "the world's lost second: its samples without a state"
    misses = [t for t in since_lost if "deadline miss" in t]
    missed = set().union(*map(named_samples, misses))
    assert not missed & unseen, (sorted(missed & unseen), since_lost)
    assert all("likely load, not a fault" in t for t in misses), misses
    assert not any(m.crashed for m in truth) and abs(truth[-1].pos_enu_m[2] - 1.0) < 0.05, truth[-1].pos_enu_m
