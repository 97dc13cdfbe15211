"""Motion capture that comes late and unevenly: the simulated Motive sends each frame a further |N(0, 50 ms)| late
(frames overtake each other: ~100 ms of jitter as preflight measures it, p99 − p50 of capture → arrival, half the
frames overtaken) and loses the rigid body for 100 ms, while a simulated PX4 (`neso up --vehicle mavlink --mocap
natnet`) hovers on it through the gateway. Preflight reports the jitter and the latency (warnings: the vehicle may
still arm); the flight goes on (airborne, not crashed, no gap reaching the gateway's 0.3 s; how well it hovers is
printed, not bounded: height 0.90-1.08 m, RMS 2-3 cm from 1 m in two runs); every state carries its frame's own
capture time (steps of whole frame periods), not its arrival. Before, the source stamped states on UDP receipt, so
with this jitter their times stepped by their arrival.

Where the loop stops holding, measured with this test: at |N(0, 100 ms)| (~200 ms of jitter, two thirds of the frames
overtaken, states at ~29 Hz for a 50 Hz loop) it hovered at RMS 19 cm in one run and swung 0.05-1.52 m (RMS 59 cm) in
another, which failed this test in a full `make test`; at |N(0, 200 ms)| (405 ms) it swung 0.05-2.0 m. So the test
flies at half the first: a hover this claims must hold every run, and preflight's jitter warning is the operator's cue
well before that edge."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np

from runtime.client import command
from sim.natnet_server import free_udp_port
from tests.busutil import REPO, NesoUp, free_port, peer, wait_for

JITTER_MS, LOST = 50, "20:0.1"  # |N(0, 50 ms)| a frame: ~100 ms of jitter as preflight measures it (p99 - p50)


def test_preflight_reports_the_jitter_the_hover_goes_on_and_states_keep_their_frames_times(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    old = dict(os.environ)
    os.environ["HOME"] = str(tmp_path)  # MAVSDK writes its cache under $HOME/.cache/mavsdk
    try:
        flight = NesoUp("--vehicle", "mavlink", "--mavlink-port", str(free_port()), "--mocap", "natnet",
                        "--natnet-port", str(free_udp_port()), "--natnet-jitter", str(JITTER_MS), "--natnet-lost",
                        LOST, "--mission", "idle", "--start", "ground", "--hub", endpoint, "--no-dashboard",
                        "--no-trainer", "--recordings-dir", str(tmp_path / "recordings"), bus=peer(endpoint),
                        topics=("state", "truth", "telemetry"))
    finally:
        os.environ.clear()
        os.environ.update(old)
    try:
        def cmd(service: str, name: str, **args):
            return command(flight.s, flight.probe.keys, service, name, args, timeout_s=8.0)

        wait_for("the simulated PX4 is ready for takeoff", lambda: any("Ready for takeoff" in line
                                                                       for line in flight.output), 60)
        time.sleep(6.0)  # 5 s of the stream's figures in the source's health
        done = subprocess.run([sys.executable, "-m", "cli.main", "preflight", "--connect", endpoint], cwd=REPO,
                              capture_output=True, text=True, timeout=60)
        print(f"\n{done.stdout}")
        jitter, latency = (next(line for line in done.stdout.splitlines() if f"motion capture {item} " in line)
                           for item in ("jitter", "latency"))
        assert jitter.startswith("WARNING") and float(jitter.split("jitter")[1].split("ms")[0]) > 50, jitter
        assert "p99" in latency and float(latency.split("p99 ")[1].split(" ms")[0]) > 100, latency
        assert done.returncode == 0, "jitter and latency warn; the vehicle may arm"

        wait_for("offboard", lambda: cmd("px4_gateway", "offboard_start").ok, 30, 1.0)
        wait_for("armed", lambda: cmd("px4_gateway", "arm").ok, 30, 1.0)
        assert cmd("controller", "arm").ok and cmd("controller", "takeoff").ok
        wait_for("airborne", lambda: flight.probe.get("truth")[-1].pos_enu_m[2] > 0.9, 30)
        wait_for("the lost 100 ms passed", lambda: flight.probe.get("truth")[-1].t_s > 24.0, 60)
        time.sleep(3.0)
    finally:
        out = flight.close()
    assert "Traceback" not in out, out[-3000:]
    truth = flight.probe.get("truth")
    airborne = next(k for k, m in enumerate(truth) if m.pos_enu_m[2] > 0.9)
    after = truth[airborne:]
    z = np.array([m.pos_enu_m[2] for m in after])
    xy = np.array([np.hypot(*m.pos_enu_m[:2]) for m in after])
    print(f"after take-off ({len(after) / 50:.0f} s): height {z.min():.2f}-{z.max():.2f} m (RMS from 1 m "
          f"{np.sqrt(np.mean((z - 1.0) ** 2)) * 100:.0f} cm), horizontal within {xy.max() * 100:.0f} cm")
    events = [line.split("] ", 1)[-1] for line in out.splitlines() if "warning:" in line or "error:" in line]
    print("\n".join(events[-12:]))
    assert not any(m.crashed for m in truth) and z.min() > 0.1, "the flight goes on: airborne, not crashed"
    assert not any("PX4 told it failed" in e for e in events), "no gap of the states reached the gateway's 0.3 s"
    assert any("rigid body 'uav1' lost" in e for e in events), "the 100 ms without the rigid body happened"
    states = [m for m in flight.probe.get("state") if m.t_s > 2.0]
    steps_ms = np.diff([m.t_s for m in states]) * 1e3
    off_grid_ms = np.abs(steps_ms - 10.0 * np.round(steps_ms / 10.0))
    arrival_ms = np.diff([m.stamp_s for m in states]) * 1e3
    print(f"{len(states)} states: time steps {np.percentile(steps_ms, [1, 50, 99]).round(1)} ms (whole 10 ms frames "
          f"up to {off_grid_ms.max():.3f} ms); their arrival steps {np.percentile(arrival_ms, [1, 50, 99]).round(1)} ms")
    assert len(states) > 500 and off_grid_ms.max() < 0.1, "each state at its frame's capture: whole 100 Hz frames"
    assert np.percentile(arrival_ms, 99) - np.percentile(arrival_ms, 1) > 20.0, "while their arrival is jittered"
    assert all(0.0 < m.stamp_s - m.capture_stamp_s < 2.0 for m in states), "published after its capture"
    vel_err = [np.linalg.norm(np.subtract(s.vel_enu_mps, t.vel_enu_mps)) for s, t in _pairs(states, truth)]
    print(f"velocity error vs the truth: RMS {np.sqrt(np.mean(np.square(vel_err))):.3f} m/s (a figure: the source's "
          "15 Hz filter over frames ~40 ms apart, the truth paired within a frame)")


def _pairs(states, truth):
    """Each state with the world's truth nearest its capture (both on this machine's monotonic clock: the truth
    is stamped as the world steps, in real time)."""
    stamps = np.array([m.stamp_s for m in truth])
    for s in states:
        yield s, truth[int(np.argmin(np.abs(stamps - s.capture_stamp_s)))]
