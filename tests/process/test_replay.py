"""`neso replay` as real processes: the example flight back on a real bus at its pace, and the
web viewer served on loopback at the ports asked for."""
from __future__ import annotations

import os
import signal
import time
import urllib.request
from pathlib import Path

import numpy as np

from recordings.reader import read_recording
from runtime.probe import Probe
from tests.busutil import free_port, hub, neso, peer, session, stop

EXAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "examples" / "nominal-landing-eso.rrd"


def test_to_bus_publishes_the_recorded_flight_at_its_pace_under_another_name(rerun_home):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    recorded = read_recording(EXAMPLE)
    with hub(endpoint), session(peer(endpoint)) as s:
        probe = Probe(s, vehicle="replay1")
        original = Probe(s, vehicle="uav1")
        time.sleep(0.3)
        proc = neso("replay", str(EXAMPLE), "--to-bus", "--speed", "4", "--as", "replay1", "--connect", endpoint)
        try:
            first = probe.wait_for("state", lambda m: True, 20.0)
            started = time.monotonic()
            proc.wait(30)
            elapsed = time.monotonic() - started
            out = proc.stdout.read()
        finally:
            stop(proc)
        time.sleep(0.2)
        assert proc.returncode == 0, out
        assert "published 3000 of 3000" in out, out
        states = probe.get("state")
        assert first.source == "replay" and all(m.source == "replay" for m in states)
        assert original.get("state") == [], "nothing under the recorded name"
        rec_states = recorded.channel("state").messages()
        assert len(states) == 600
        np.testing.assert_array_equal([m.pos_enu_m for m in states], [m.pos_enu_m for m in rec_states])
        assert [m.seq for m in probe.get("estimate")] == list(range(600))
        stamps = np.array([m.stamp_s for m in states])  # the replay's clock: each sample stamped as it went out
        assert np.all(np.diff(stamps) > 0), "stamped with the replay's clock"
        # its pace, against the recording's own time: 4× the recorded pace over the flight (a sample a loaded machine
        # published late does not shift the ones after it: the schedule is the recording's)
        due = (np.array([m.t_s for m in rec_states]) - rec_states[0].t_s) / 4.0
        pace = np.polyfit(due, stamps - stamps[0], 1)[0]
        print(f"replay ×4: {elapsed:.2f} s for {due[-1]:.2f} s of the recording ÷ 4; pace {pace:.3f} of ×4")
        assert abs(pace - 1.0) < 0.05, pace


def test_web_viewer_is_served_on_loopback_at_the_given_ports_and_stops_with_ctrl_c(rerun_home):
    web, grpc = free_port(), free_port()
    proc = neso("replay", str(EXAMPLE), "--web", "--web-port", str(web), "--grpc-port", str(grpc))
    try:
        deadline = time.monotonic() + 30
        page = None
        while time.monotonic() < deadline and page is None:
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=2).read()
            except OSError:
                time.sleep(0.2)
        assert page is not None and b"<html" in page.lower()
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(10)
    time.sleep(0.5)
    left = [p for p in os.listdir("/proc") if p.isdigit() and _cmdline_has(p, f"--web-viewer-port {web}")]
    assert left == [], "the viewer stopped with it"


def _cmdline_has(pid: str, text: str) -> bool:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return text in f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False


def test_recordings_cli_lists_the_catalog_and_counts_training_pairs(tmp_path, rerun_home):
    (tmp_path / "landing.rrd").write_bytes(EXAMPLE.read_bytes())
    listing = neso("recordings", "list", str(tmp_path))
    out = listing.communicate(timeout=60)[0]
    assert listing.returncode == 0, out
    header, row = out.splitlines()[:2]
    assert header.split()[:10] == ["flight", "seg", "vehicle", "source", "scenario", "duration", "pathway", "network",
                                   "L_N", "size"]
    assert row.split()[3] == "sim", "the states came from the simulator"
    assert "uav1" in row and "nominal_landing" in row and "12.0 s" in row and "eso" in row and "base-L1.0" in row
    (tmp_path / "broken.rrd").write_bytes(b"not a recording")
    listing = neso("recordings", "list", str(tmp_path))
    out = listing.communicate(timeout=60)[0]
    assert listing.returncode == 1 and "UNREADABLE" in out
    counting = neso("recordings", "dataset", str(tmp_path / "landing.rrd"), "--label", "eso")
    out = counting.communicate(timeout=60)[0]
    assert counting.returncode == 0 and out.startswith("576 training pairs (eso labels) of vehicle uav1"), out
    refusing = neso("recordings", "dataset", str(tmp_path / "landing.rrd"), "--label", "tdr")
    out = refusing.communicate(timeout=60)[0]
    assert refusing.returncode == 1 and "no usable 'tdr' samples" in out, out
