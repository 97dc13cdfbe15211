"""A flight is a flight: the recorder in the MAVLink flow (`neso up --vehicle mavlink`, the sim as a
PX4 on MAVLink, real MAVSDK, real Zenoh, real files), and Ctrl-C stopping everything at once.

One `neso up`, in order: untouched for 2 s longer than the recorder's longest window (nothing flies: no recording;
12 s, 30 s before: the recorder decides on 0.5-10 s windows); the controller armed and
commanding a take-off while the vehicle stays disarmed (what made 104 recordings of 0.1 s: the
controller's thrust said "flying", the telemetry said "disarmed", ten times a second): still none;
then a real flight, PX4 armed and in offboard, take-off, hover, land: exactly one recording;
then SIGINT to `neso up`: every process gone within 3 s (the recorder within its grace), none killed.
"""
from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

from recordings.reader import read_recording
from runtime.client import command
from runtime.graph import role as graph_role
from runtime.probe import Probe
from services.recorder import RecorderConfig
from tests.busutil import children_of, free_port, neso, peer, role_pid, session, wait_for

TOPICS = ("state", "setpoint", "reference", "telemetry", "recording")
_RECORDER = RecorderConfig()
#: longer than every window the recorder decides on (a flight's start, its end, a source's silence, a resume)
UNTOUCHED_S = max(_RECORDER.start_after_s, _RECORDER.idle_end_s, _RECORDER.silence_end_s,
                  _RECORDER.resume_window_s) + 2.0


def _files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.glob("*.rrd") if not p.name.startswith("."))


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_the_mavlink_flow_records_one_flight_per_flight_and_stops_within_3_s_of_ctrl_c(tmp_path, rerun_home):
    recordings = tmp_path / "recordings"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    old_home = os.environ.get("HOME")
    os.environ["HOME"] = str(tmp_path)  # MAVSDK writes its cache under $HOME/.cache/mavsdk
    try:
        proc = neso("up", "--vehicle", "mavlink", "--start", "ground", "--mission", "idle", "--hub", endpoint,
                    "--mavlink-port", str(free_port()), "--no-dashboard", "--no-trainer",
                    "--recordings-dir", str(recordings))
    finally:
        if old_home is not None:
            os.environ["HOME"] = old_home
    output: list[str] = []
    threading.Thread(target=lambda: output.extend(proc.stdout), daemon=True).start()
    try:
        with session(peer(endpoint)) as s:
            probe = Probe(s, topics=TOPICS)

            def cmd(service: str, name: str) -> None:
                reply = command(s, probe.keys, service, name, {}, timeout_s=8.0)
                assert reply.ok, (service, name, reply.message)

            probe.wait_for("telemetry", lambda m: m.connected, 40.0)
            time.sleep(UNTOUCHED_S)
            assert _files(recordings) == [], "nothing flew, yet something was recorded"

            cmd("controller", "arm")  # the controller flies a take-off; PX4 stays disarmed
            cmd("controller", "takeoff")
            t0 = time.monotonic()
            probe.wait_for("setpoint", lambda m: m.stamp_s > t0 and m.thrust_n > 0, 5.0)
            time.sleep(8.0)
            assert probe.get("telemetry")[-1].armed is False
            assert _files(recordings) == [], "thrust commanded to a disarmed vehicle is no flight"
            t0 = time.monotonic()
            cmd("controller", "land")
            probe.wait_for("setpoint", lambda m: m.stamp_s > t0 and m.thrust_n == 0.0, 10.0)

            # as an operator does with PX4: its "Ready for takeoff!" (on its console) before arming
            wait_for("the simulated PX4 is ready for takeoff", lambda: any("Ready for takeoff" in line
                                                                            for line in output), 10)
            cmd("px4_gateway", "arm")
            cmd("px4_gateway", "offboard_start")
            t0 = time.monotonic()
            cmd("controller", "takeoff")
            hover = probe.wait_for("reference", lambda m: m.stamp_s > t0 and m.segment == "hover", 20.0)
            probe.wait_for("reference", lambda m: m.seq > hover.seq + 150, 10.0)  # 3 s of hover
            cmd("controller", "land")
            cmd("px4_gateway", "land")
            t0 = time.monotonic()
            probe.wait_for("telemetry", lambda m: m.stamp_s > t0 and not m.armed, 20.0)
            probe.wait_for("recording", lambda m: m.stamp_s > t0 and not m.recording, 10.0)
            files = _files(recordings)
            assert len(files) == 1, [f.name for f in files]
    finally:
        kids = children_of(proc.pid)
        try:
            recorder = role_pid(proc.pid, "recorder")
        except AssertionError:  # none: the run failed before it started (the error above says why)
            recorder = None
        sent = time.monotonic()
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        gone_s: dict[int, float] = {}
        while (proc.poll() is None or len(gone_s) < len(kids)) and time.monotonic() - sent < 15:
            gone_s.update({k: time.monotonic() - sent for k in kids if k not in gone_s and not _alive(k)})
            time.sleep(0.02)
        stopped_s = time.monotonic() - sent
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    log = "".join(output)
    print(f"stopped {stopped_s:.2f} s after SIGINT; the recorder {gone_s.get(recorder, float('nan')):.2f} s")
    print("".join(line for line in output if "recorder |" in line and "health" not in line)[-3000:])
    others = {k: t for k, t in gone_s.items() if k != recorder}
    assert len(others) == len(kids) - 1 and max(others.values()) < 3.0, f"{others} s to stop (pid: s)"
    # the recorder may take its grace to finish the flight's file (niced, it is slow beside a CPU hog)
    assert recorder in gone_s and stopped_s < graph_role("recorder").stop_grace_s, f"{stopped_s:.2f} s to stop"
    assert "did not stop" not in log and "killing it" not in log, log[-2000:]
    rec = read_recording(files[0])
    start, summary = rec.properties["start"], rec.properties["summary"]
    assert start["reason"] == "flying for 0.5 s: armed and in the air (telemetry)", start
    assert summary["end_reason"].startswith("landed: not flying for 2 s"), summary
    assert summary["duration_s"] > 5.0, summary  # take-off, 3 s of hover, the landing
