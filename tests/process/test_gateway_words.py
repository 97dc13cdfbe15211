"""PX4's own words on the bus: the gateway (`neso run px4_gateway`, real MAVSDK) facing a vehicle on MAVLink UDP that
says several things at once, as PX4 does on landing ("Landing detected", then "Disarmed by landing" and a pre-flight
check within milliseconds; on a loaded machine its words also arrive bunched). Every one reaches the telemetry, in
order: a telemetry message carries one text, and the gateway published only the newest at its 10 Hz (the recording
of a PX4 flight then lacked "Disarmed by landing")."""
from __future__ import annotations

import os
import time

from pymavlink import mavutil

from runtime.probe import Probe
from tests.busutil import free_port, hub, neso, peer, session, stop, wait_for

mavlink = mavutil.mavlink
WORDS = ("Landing detected", "Disarmed by landing", "Preflight Fail: height estimate not stable",
         "Preflight Fail: High Accelerometer Bias")


def test_every_word_the_vehicle_says_reaches_the_telemetry_in_order_however_close_together(tmp_path):
    endpoint, port = f"tcp/127.0.0.1:{free_port()}", free_port()
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1,
                                         source_component=mavlink.MAV_COMP_ID_AUTOPILOT1, dialect="common")

    def heartbeat() -> None:
        vehicle.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                   mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4 << 16 | 3 << 24,
                                   mavlink.MAV_STATE_STANDBY)

    with hub(endpoint), session(peer(endpoint)) as s:
        probe = Probe(s, topics=("telemetry",))
        gateway = neso("run", "px4_gateway", "--vehicle", "uav1", "--connect", endpoint, "--mavlink",
                       f"udpin://127.0.0.1:{port}", env=dict(os.environ, HOME=str(tmp_path)))  # MAVSDK's cache
        try:
            def connected() -> bool:
                heartbeat()
                return any(m.connected for m in probe.get("telemetry"))
            wait_for("the gateway connects to the vehicle", connected, 60, 0.1)
            for text in WORDS:  # one burst: four STATUSTEXTs within a millisecond
                vehicle.mav.statustext_send(mavlink.MAV_SEVERITY_INFO, text.encode())
            wait_for("the last word on the telemetry", lambda: (heartbeat() or True) and any(
                WORDS[-1] in m.status_text for m in probe.get("telemetry")), 10, 0.1)
            time.sleep(0.3)
        finally:
            out = stop(gateway)
            vehicle.close()
        said = [m.status_text for m in probe.get("telemetry") if m.status_text]
    first = [text for k, text in enumerate(said) if k == 0 or said[k - 1] != text]  # each change once
    assert first == [f"INFO: {w}" for w in WORDS], (first, out[-2000:])
