"""Latency the PX4 gateway adds: a setpoint published on the bus → SET_ATTITUDE_TARGET at the vehicle.

Real processes: a hub and ``neso run px4_gateway`` (MAVSDK 4.x, hover learning off so the
thrust passes unchanged); in this process the MAVLink vehicle endpoint of the simulator
(:class:`sim.mavlink_vehicle.MavlinkVehicle`, no physics: it only answers and logs) and a
publisher of setpoints at the control rate, each with a unique thrust (0.2 + k·10⁻⁴, distinct
in MAVLink's float32). Per setpoint: (first arrival at the vehicle of that thrust, stamped with
``time.monotonic()`` by the vehicle's receiver thread) − the setpoint's ``stamp_s``. MAVSDK's
20 Hz re-sends of an old setpoint are not counted (first arrival only). A probe subscriber in this
process gives the bare bus delivery of the same setpoints beside it.

Then the gateway's watchdog with the motion capture lost: motion-capture states and setpoints at the
control rate, the vehicle in offboard, then neither for ``LOST_S``. While lost the watchdog tells the
vehicle each tick that the external vision failed (ODOMETRY quality −1, through MAVSDK's MavlinkDirect)
and sends a level attitude (MAVSDK's Offboard): two gRPC calls to ``mavsdk_server`` a tick. Measured at
the vehicle: the first failed pose after the last state, and the interval between failed poses, on a
quiet machine beside one with a busy process on every core (nice 0, as another user's work would be).
"""
from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from bench.bus_latency import latency_stats
from runtime.client import command
from runtime.schema import Keys, SetpointMsg, StateMsg
from services.px4_gateway import GatewayConfig
from tests.busutil import free_port, neso, peer, session, stop

COLUMNS = ("gateway latency", "samples", "p50 µs", "p99 µs", "max µs", "notes")
LOST_S = 3.0  # the motion capture lost, each time


def measure(rate_hz: float = 50.0, duration_s: float = 20.0) -> dict:
    """Latencies in seconds: ``vehicle`` (bus → vehicle) and ``bus`` (bus → probe), plus ``sent``/``lost``;
    ``watchdog``: :func:`_lose`'s figures on a quiet machine (``quiet``) and with every core busy (``busy``)."""
    from neso.types import StateMeasurement
    from sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

    hub_ep, mav_port = f"tcp/127.0.0.1:{free_port()}", free_port()
    home = tempfile.mkdtemp(prefix="neso-bench-home-")
    old_home = os.environ.get("HOME")
    os.environ["HOME"] = home  # MAVSDK's cache
    try:
        hub = neso("run", "hub", "--listen", hub_ep)
        gateway = neso("run", "px4_gateway", "--connect", hub_ep, "--mavlink", f"udpin://127.0.0.1:{mav_port}",
                       "--no-learn-hover")
    finally:
        if old_home is not None:
            os.environ["HOME"] = old_home
    vehicle = MavlinkVehicle(VehicleConfig(target=f"udpout:127.0.0.1:{mav_port}"), dt_s=1.0 / rate_hz)
    stop_telemetry = threading.Event()

    def telemetry() -> None:  # the vehicle's clock is the world's (its heartbeat, its timeouts): here the wall clock
        start_s = time.monotonic()
        while not stop_telemetry.wait(0.02):
            meas = StateMeasurement(time.monotonic() - start_s, np.zeros(3), np.zeros(3), 0.0, 0.0, 0.0)
            vehicle.control(meas, on_ground=True)
            vehicle.publish(meas, t_s=meas.t_s)

    threading.Thread(target=telemetry, daemon=True).start()
    keys = Keys("uav1")
    stamps: dict[int, float] = {}
    bus: list[float] = []
    try:
        with session(peer(hub_ep)) as s:
            s.declare_subscriber(keys.topic("setpoint"),
                                 lambda sample: bus.append(time.monotonic() - SetpointMsg.from_bytes(
                                     sample.payload.to_bytes()).stamp_s))
            pub = s.declare_publisher(keys.topic("setpoint"), express=True)
            deadline = time.monotonic() + 60.0
            while not any(e["kind"] == "setpoint" for e in list(vehicle.log)):  # gateway connected and streaming
                if time.monotonic() > deadline:
                    raise RuntimeError("the gateway never streamed a setpoint to the vehicle")
                pub.put(_setpoint(0, 0.3).to_bytes())
                time.sleep(0.1)
            time.sleep(0.5)
            bus.clear()
            n = int(duration_s * rate_hz)
            next_s = time.monotonic()
            for k in range(1, n + 1):
                msg = _setpoint(k, 0.2 + (k % 5000) * 1e-4)
                stamps[k] = msg.stamp_s
                pub.put(msg.to_bytes())
                next_s += 1.0 / rate_hz
                time.sleep(max(0.0, next_s - time.monotonic()))
            time.sleep(0.5)
            bus_s = list(bus)  # this phase's: the probe goes on receiving the watchdog phase's setpoints
            states = s.declare_publisher(keys.topic("state"), express=True)
            watchdog = {"quiet": _lose(vehicle, s, keys, states, pub, busy=False, rate_hz=rate_hz),
                        "busy": _lose(vehicle, s, keys, states, pub, busy=True, rate_hz=rate_hz)}
    finally:
        stop_telemetry.set()
        stop(gateway)
        stop(hub)
        vehicle.close()
    first: dict[int, float] = {}
    for e in list(vehicle.log):
        if e["kind"] == "setpoint":
            k = int(round((e["thrust"] - 0.2) / 1e-4))
            if 1 <= k <= len(stamps) and abs(e["thrust"] - (0.2 + k * 1e-4)) < 2e-5 and k not in first:
                first[k] = e["t"]
    latency = [first[k] - stamps[k] for k in sorted(first)]
    return {"vehicle": latency, "bus": bus_s, "sent": len(stamps), "lost": len(stamps) - len(first), "watchdog": watchdog}


def _lose(vehicle, s, keys: Keys, states, setpoints, *, busy: bool, rate_hz: float) -> dict:
    """Motion-capture states and setpoints for 2 s (the vehicle taken to offboard), then none for ``LOST_S``.
    ``first_s``: the last state's put → the first failed pose at the vehicle; ``intervals_s`` between failed
    poses; ``failed``: how many. ``busy``: a busy process on every core throughout."""
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 1)] \
        if busy else []
    try:
        next_s = time.monotonic()
        for k in range(int(2.0 * rate_hz)):
            now = time.monotonic()
            states.put(StateMsg(seq=k, stamp_s=now, t_s=k / rate_hz, pos_enu_m=(0.1, 0.2, 1.0),
                                vel_enu_mps=(0.0, 0.0, 0.0), roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.2,
                                source="mocap").to_bytes())
            setpoints.put(_setpoint(k, 0.3).to_bytes())
            last_s = time.monotonic()
            if k == int(rate_hz) and vehicle.mode_name != "offboard":
                reply = command(s, keys, "px4_gateway", "offboard_start", timeout_s=8.0)
                if not reply.ok:
                    raise RuntimeError(f"the vehicle did not take offboard: {reply.message}")
            next_s += 1.0 / rate_hz
            time.sleep(max(0.0, next_s - time.monotonic()))
        time.sleep(LOST_S)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    failed = [e["t"] for e in list(vehicle.log) if e["kind"] == "odometry" and e.get("quality") == -1
              and last_s < e["t"] < last_s + LOST_S]
    return {"first_s": failed[0] - last_s if failed else None, "intervals_s": list(np.diff(failed)),
            "failed": len(failed), "mode": vehicle.mode_name}


def _setpoint(k: int, thrust: float) -> SetpointMsg:
    now = time.monotonic()
    return SetpointMsg(seq=k, stamp_s=now, state_stamp_s=now, t_s=k * 0.02, roll_rad=0.05, pitch_rad=-0.03,
                       yaw_rad=0.2, thrust_norm=thrust, thrust_n=9.81 * thrust / 0.5, acc_cmd_enu_mps2=(0.0, 0.0, 0.0),
                       estimate_source="estimator")


def gateway_rows(duration_s: float = 20.0, rate_hz: float = 50.0) -> list[tuple[str, ...]]:
    r = measure(rate_hz, duration_s)
    return [
        (f"setpoint on the bus → SET_ATTITUDE_TARGET at the vehicle, {rate_hz:g} Hz", *latency_stats(r["vehicle"]),
         f"{r['lost']} of {r['sent']} never arrived"),
        ("  bus alone (same setpoints → a probe subscriber)", *latency_stats(r["bus"]), "Zenoh delivery, for comparison"),
        *(_watchdog_row(r["watchdog"][load], load) for load in ("quiet", "busy")),
    ]


def _watchdog_row(w: dict, load: str) -> tuple[str, ...]:
    first = "none" if w["first_s"] is None else f"first {w['first_s'] * 1e3:.0f} ms after the last state"
    return (f"mocap lost {LOST_S:g} s: interval between failed poses at the vehicle ({load})",
            *latency_stats(w["intervals_s"]),
            f"{w['failed'] / (LOST_S - (w['first_s'] or 0.0)):.1f} a second, {first} (tells after {GatewayConfig().pose_lost_after_s * 1e3:.0f} "
            f"ms + a tick); vehicle in {w['mode']}")
