"""Latency the NatNet path adds: a pose leaving the simulated Motive → the state on the bus.

Real processes: a hub and ``neso run source --backend mocap --mocap-type optitrack`` (the motioncapture
library's optitrack client, as in a lab); in this process the simulated Motive
(:class:`sim.natnet_server.NatNetServer`, multicast on loopback, z-up) streaming one rigid body at
``rate_hz`` whose x is the frame's number in mm (distinct in float32), and a subscriber of the state.
Per state: its arrival (``time.monotonic()``) − the instant its frame was due to leave the server
(the world's modelled mocap latency is not in it: this is what the protocol, the client, the source and
the bus add). ``source``: the same frame's due instant → the state's own ``stamp_s`` (the source's
share, before the bus). The source publishes at the control rate (50 Hz), so a few frames per state.
"""
from __future__ import annotations

import threading
import time

from bench.bus_latency import latency_stats
from runtime.schema import Keys, StateMsg
from sim import natnet
from sim.natnet_server import NatNetServer, NatNetServerConfig, free_udp_port
from tests.busutil import free_port, neso, peer, session, stop

COLUMNS = ("NatNet → state on the bus", "samples", "p50 µs", "p99 µs", "max µs", "notes")


def measure(rate_hz: float, duration_s: float = 4.0) -> dict:
    """Latencies in seconds: ``bus`` (frame due → state arrives at a subscriber), ``source`` (frame due →
    the state's ``stamp_s``); ``frames`` sent."""
    hub_ep = f"tcp/127.0.0.1:{free_port()}"
    server = NatNetServer(NatNetServerConfig(command_port=free_udp_port(), data_port=free_udp_port())).start()
    due: dict[int, float] = {}
    arrivals: list[tuple[float, StateMsg]] = []
    hub = neso("run", "hub", "--listen", hub_ep)
    source = neso("run", "source", "--backend", "mocap", "--mocap-type", "optitrack", "--mocap-port",
                  str(server.command_port), "--mocap-interface", "127.0.0.1", "--frame", "enu", "--connect", hub_ep)
    stopping = threading.Event()

    def stream() -> None:
        k, next_s = 0, time.monotonic()
        while not stopping.is_set():
            k += 1
            due[k] = next_s
            server.submit(next_s, next_s, [natnet.BodyPose(1, (k * 1e-3, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0))])
            next_s += 1.0 / rate_hz
            stopping.wait(max(0.0, next_s - time.monotonic()))

    try:
        with session(peer(hub_ep)) as s:
            s.declare_subscriber(Keys("uav1").topic("state"), lambda sample: arrivals.append(
                (time.monotonic(), StateMsg.from_bytes(sample.payload.to_bytes()))))
            streamer = threading.Thread(target=stream, daemon=True)
            streamer.start()
            deadline = time.monotonic() + 60.0
            while len(arrivals) < 50:  # connected, streaming, and past the start
                if time.monotonic() > deadline:
                    raise RuntimeError("the source never published a state from the NatNet stream")
                time.sleep(0.05)
            arrivals.clear()
            time.sleep(duration_s)
            stopping.set()
            streamer.join()
            time.sleep(0.2)
    finally:
        stopping.set()
        stop(source)
        stop(hub)
        server.close()
    bus, src = [], []
    for arrived_s, msg in list(arrivals):
        k = round(msg.pos_enu_m[0] * 1e3)
        if k in due:
            bus.append(arrived_s - due[k])
            src.append(msg.stamp_s - due[k])
    return {"bus": bus, "source": src, "frames": len(due)}


def natnet_rows(duration_s: float = 4.0) -> list[tuple[str, ...]]:
    """The table's rows; the figures also go to ``out/bench.json`` under ``"natnet"`` (µs by frame rate)."""
    import numpy as np

    from bench.table import write_results

    rows, figures = [], {}
    for rate_hz in (120.0, 360.0):
        r = measure(rate_hz, duration_s)
        if r["bus"]:
            p50, p99 = np.percentile(np.array(r["bus"]) * 1e6, [50, 99])
            figures[f"{rate_hz:g}_hz"] = {"samples": len(r["bus"]), "p50_us": round(float(p50)), "p99_us": round(float(p99))}
        rows.append((f"frame leaves the simulated Motive → state at a bus subscriber, {rate_hz:g} Hz frames",
                     *latency_stats(r["bus"]), f"{r['frames']} frames, a state every 20 ms"))
        rows.append(("  of which: frame → the source's stamp (UDP, libmotioncapture, MocapSource)",
                     *latency_stats(r["source"]), "incl. the server's sender thread waking"))
    write_results({"natnet": figures})
    return rows


if __name__ == "__main__":
    from bench.table import print_table

    print_table(COLUMNS, natnet_rows())
