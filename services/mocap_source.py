"""The source's motion-capture paths (:mod:`services.source` chooses them): a mocap system read through the
``motioncapture`` library (:func:`run_mocap`), and the simulated world behind a simulated Motive streaming NatNet
on loopback, read back exactly as in a lab (:func:`run_sim_natnet`)."""
from __future__ import annotations

import contextlib
import sys
import threading
import time
from dataclasses import replace

import numpy as np

from flight.source import MocapSource, SourceConfig
from runtime.schema import SetpointMsg


def run_sim_natnet(node, config: SourceConfig) -> None:
    """The world in a child process (services/natnet_world.py) streams NatNet on loopback; this process
    reads it exactly as in a lab (:func:`run_mocap`, the motioncapture optitrack client), forwards the
    setpoints to the world and publishes the world's truth."""
    import multiprocessing

    from runtime.schema import TruthMsg
    from services.natnet_world import run_world

    ctx = multiprocessing.get_context("spawn")
    conn, child_conn = ctx.Pipe()
    world = ctx.Process(target=run_world, args=(child_conn, config), name="natnet-world", daemon=True)
    world.start()
    if not conn.poll(60.0):
        raise SystemExit("source: the simulated Motive did not start within 60 s")
    _, port = conn.recv()
    put_truth = node.publisher("truth")
    send_lock = threading.Lock()

    def on_setpoint(msg: SetpointMsg, received_s: float) -> None:
        with send_lock:
            conn.send_bytes(msg.to_bytes())

    def relay_truth() -> None:
        try:
            while True:
                put_truth(TruthMsg.from_bytes(conn.recv_bytes()))
        except (EOFError, OSError):
            return

    node.subscribe("setpoint", on_setpoint)
    threading.Thread(target=relay_truth, name="truth", daemon=True).start()
    mocap = replace(config.mocap, type="optitrack", hostname="127.0.0.1", port=port, interface="127.0.0.1",
                    frame={"y": "y_up", "z": "enu"}[config.natnet.up_axis])
    node.event("info", f"state from NatNet: simulated world → simulated Motive (NatNet 4.1, 127.0.0.1:{port}, "
                       f"{config.natnet.up_axis}-up) → motioncapture optitrack client → this source")
    n_total = int(round(config.duration_s * config.rate_hz)) if config.duration_s > 0 else None
    try:
        run_mocap(node, replace(config, mocap=mocap), n_total=n_total)
    finally:
        with send_lock, contextlib.suppress(OSError):  # the world may have gone already
            conn.send_bytes(b"")
        world.join(timeout=3.0)
        if world.is_alive():
            world.terminate()


def natnet_rigid_bodies(host: str, port: int, timeout_s: float = 2.0) -> tuple[tuple[int, ...], list[str]]:
    """(NatNet version, rigid-body names) a NatNet server at ``host:port`` streams: asked as its clients
    ask (NAT_CONNECT, NAT_REQUEST_MODELDEF). ``SystemExit`` with one line when nobody answers."""
    import socket

    from sim import natnet

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(timeout_s)
        try:
            s.sendto(natnet.packet(natnet.NAT_CONNECT), (host, port))
            info = natnet.parse_server_info(natnet.split(s.recv(65536))[1])
            s.sendto(natnet.packet(natnet.NAT_REQUEST_MODELDEF), (host, port))
            message_id, payload = natnet.split(s.recv(65536))
            if message_id != natnet.NAT_MODELDEF:
                raise natnet.NatNetError(f"message {message_id} in answer to NAT_REQUEST_MODELDEF")
        except (OSError, natnet.NatNetError) as exc:
            raise SystemExit(f"source: no NatNet server answered at {host}:{port} ({exc}); is Motive streaming "
                             "(Edit → Settings → Streaming: Enable) and is this the command port?") from None
    names = list(natnet.parse_rigid_body_names(payload).values()) if info.natnet_version[:2] == (4, 1) else []
    return info.natnet_version, names


def run_mocap(node, config: SourceConfig, *, n_total: int | None = None) -> None:
    """Frames from the motioncapture library on a thread of their own (``waitForNextFrame`` blocks); this
    thread watches the stream: no frame for ``stream_timeout_s`` is a stopped stream, frames without the
    rigid body are a lost rigid body (each an event when it starts and when it ends, frames counted in
    health). ``n_total``: stop after that many states."""
    import motioncapture

    mc_config = config.mocap
    core = MocapSource(mc_config, config.rate_hz, clock=time.monotonic)
    put_state = node.publisher("state")
    name = mc_config.rigid_body
    where = f"{mc_config.hostname}:{mc_config.port}" if mc_config.type == "optitrack" else mc_config.hostname
    options = {"hostname": mc_config.hostname}
    if mc_config.type == "optitrack":
        version, streamed = natnet_rigid_bodies(mc_config.hostname, mc_config.port)
        if streamed and name not in streamed:
            print(f"source: rigid body {name!r} is not streamed by the NatNet server at {where}; it streams "
                  f"{streamed} (--rigid-body, or Motive's Assets pane: the rigid body's name and Streaming on)",
                  file=sys.stderr, flush=True)
            raise SystemExit(2)
        node.log(f"NatNet {'.'.join(map(str, version))} at {where}, rigid bodies {streamed}")
        options.update(port_command=str(mc_config.port), interface_ip=mc_config.interface)
    node.log(f"connecting to {mc_config.type} at {where}, rigid body {name!r}, frame {mc_config.frame}")
    mc = motioncapture.connect(mc_config.type, options)
    seen = [0]
    watch = {"last_frame_s": time.monotonic(), "stopped_since": None, "lost_since": None, "lost_frames": 0}

    stopping = [False]

    def read_frames() -> None:
        while not node.stopping and not stopping[0]:
            mc.waitForNextFrame()
            now = time.monotonic()
            body = mc.rigidBodies.get(name)
            if stopping[0]:
                return
            with node.lock:
                seen[0] += 1
                watch["last_frame_s"] = now
                if watch["stopped_since"] is not None:
                    node.event("info", f"mocap stream from {where} back after {now - watch['stopped_since']:.2f} s")
                    watch["stopped_since"] = None
                if body is None:
                    if core.seq >= 0:
                        watch["lost_frames"] += 1
                        node.stats.count("tracking_lost_frames")
                        if watch["lost_since"] is None:
                            watch["lost_since"] = now
                            node.event("warning", f"rigid body {name!r} lost: frames come without it (not tracked); "
                                                  "no state until it is back")
                    continue
                if watch["lost_since"] is not None:
                    node.event("info", f"rigid body {name!r} tracked again after {now - watch['lost_since']:.2f} s")
                    watch["lost_since"] = None
                q = body.rotation
                state = core.frame(now, np.asarray(body.position), (q.w, q.x, q.y, q.z))
                if state is not None:
                    put_state(state)
                    node.stats.output(time.monotonic() - state.stamp_s)

    kind = f"{mc_config.type} (NatNet {'.'.join(map(str, version[:2]))} at {where})" if mc_config.type == "optitrack" \
        else mc_config.type

    def status() -> str:
        if watch["stopped_since"] is not None:
            return f"mocap {kind}: STREAM STOPPED {time.monotonic() - watch['stopped_since']:.1f} s ({seen[0]} frames)"
        if core.seq < 0:
            return f"mocap {kind}: {seen[0]} frames, rigid body {name!r} not seen yet"
        lost = "LOST, " if watch["lost_since"] is not None else ""
        return f"mocap {kind}: {lost}{seen[0]} frames, sample {core.seq}, {watch['lost_frames']} frames without the body"

    node.status_hook = status
    reader = threading.Thread(target=read_frames, name="mocap-frames", daemon=True)
    reader.start()
    while not node.stopping and (n_total is None or core.seq + 1 < n_total):
        node.wait(0.05)
        with node.lock:
            silent_s = time.monotonic() - watch["last_frame_s"]
            if silent_s > mc_config.stream_timeout_s and watch["stopped_since"] is None:
                watch["stopped_since"] = watch["last_frame_s"]
                node.stats.count("stream_stops")
                node.event("warning", f"mocap stream from {where} stopped: no frame for {silent_s:.2f} s; no state "
                                      "until it is back")
    stopping[0] = True
    reader.join(timeout=1.0)  # it leaves at its next frame; a stopped stream leaves it blocked in the library (a daemon)
    node.log(f"done: {seen[0]} frames, {core.seq + 1} states, {watch['lost_frames']} frames without {name!r}")
