"""The source's motion-capture paths (:mod:`services.source` chooses them): a mocap system (:func:`run_mocap`:
OptiTrack through this project's NatNet client, :mod:`services.natnet_client`, with Motive's own frame times;
Vicon, Qualisys, VRPN, ... through the ``motioncapture`` library, stamped on arrival), and the simulated world
behind a simulated Motive streaming NatNet on loopback, read back exactly as in a lab (:func:`run_sim_natnet`).

Before the node joins the bus the NatNet server is asked what it streams (:func:`natnet_offer`, retried): nobody
answering is one line and exit 1, a ``--rigid-body`` it does not stream one line naming those it does and exit 2,
for every NatNet version the client reads. What it said is the source's read-only description (its parameters:
``kind``, ``natnet_version``, ``server``, ``server_app``, ``rigid_body``), which every recording keeps.
"""
from __future__ import annotations

import contextlib
import sys
import threading
import time
from dataclasses import replace

import numpy as np

from flight.mocap_time import CaptureClock, StreamStats
from flight.source import MocapConfig, MocapSource, SourceConfig
from runtime.schema import SetpointMsg


def natnet_offer(mc: MocapConfig):
    """What the NatNet server at ``--mocap-host``:``--mocap-port`` streams (:func:`services.natnet_client.query_server`),
    with ``--rigid-body`` among its rigid bodies; SystemExit with one line otherwise (exit 1: nobody answered or
    a version not read here; exit 2: not that rigid body)."""
    from services.natnet_client import NatNetUnavailable, query_server

    where = f"{mc.hostname}:{mc.port}"
    try:
        offer = query_server(mc.hostname, mc.port)
    except NatNetUnavailable as exc:
        print(f"source: no NatNet server answered at {where} ({exc}); is Motive streaming (Edit → Settings → "
              "Streaming: Enable) and is this the command port?", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    streamed = list(offer.bodies.values())
    if mc.rigid_body not in streamed:
        print(f"source: rigid body {mc.rigid_body!r} is not streamed by the NatNet server at {where}; it streams "
              f"{streamed} (--rigid-body, or Motive's Assets pane: the rigid body's name and Streaming on)",
              file=sys.stderr, flush=True)
        raise SystemExit(2)
    return offer


def natnet_description(offer, rigid_body: str, **more: str) -> dict[str, str]:
    """The source's description of a NatNet stream (its read-only parameters, recorded with every flight)."""
    info = offer.info
    return {"kind": "natnet", "natnet_version": ".".join(map(str, info.natnet_version)),
            "server": f"{offer.host}:{offer.port}",
            "server_app": f"{info.app_name} {'.'.join(map(str, info.app_version))}", "rigid_body": rigid_body, **more}


def start_world(config: SourceConfig):
    """The simulated world with its simulated Motive in a child process (services/natnet_world.py): (process,
    pipe, the Motive's command port). Its Motive answers at once; its world steps from :data:`WORLD_GO` on."""
    import multiprocessing

    from services.natnet_world import run_world

    ctx = multiprocessing.get_context("spawn")
    conn, child_conn = ctx.Pipe()
    world = ctx.Process(target=run_world, args=(child_conn, config), name="natnet-world", daemon=True)
    world.start()
    if not conn.poll(60.0):
        raise SystemExit("source: the simulated Motive did not start within 60 s")
    _, port = conn.recv()
    return world, conn, port


def world_mocap(config: SourceConfig, port: int) -> MocapConfig:
    """How this source reads the simulated Motive on loopback: as a lab reads its Motive."""
    return replace(config.mocap, type="optitrack", hostname="127.0.0.1", port=port, interface="127.0.0.1",
                   frame={"y": "y_up", "z": "enu"}[config.natnet.up_axis])


def run_sim_natnet(node, config: SourceConfig, world, offer) -> None:
    """The world in a child process (:func:`start_world`) streams NatNet on loopback; this process reads it exactly
    as in a lab (:func:`run_mocap`), forwards the setpoints to the world and publishes the world's truth."""
    from runtime.schema import TruthMsg

    process, conn, port = world
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
    from services.natnet_world import WORLD_GO
    from services.source import wait_for_loop

    wait_for_loop(node, config.wait_for, required=False)
    with send_lock:
        conn.send_bytes(WORLD_GO)  # the world's first step
    node.event("info", f"state from NatNet: simulated world → simulated Motive (NatNet {offer.version}, "
                       f"127.0.0.1:{port}, {config.natnet.up_axis}-up) → this source's NatNet client")
    n_total = int(round(config.duration_s * config.rate_hz)) if config.duration_s > 0 else None
    try:
        run_mocap(node, replace(config, mocap=world_mocap(config, port)), offer=offer, n_total=n_total)
    finally:
        with send_lock, contextlib.suppress(OSError):  # the world may have gone already
            conn.send_bytes(b"")
        process.join(timeout=3.0)
        if process.is_alive():
            process.terminate()


class _NatNetFrames:
    """Frames of a NatNet server through :class:`services.natnet_client.FrameStream`, as (Motive's mid-exposure s,
    its capture on this machine's monotonic clock, arrival s, pose or None when the rigid body is not tracked);
    frames out of order are counted and ``"late"`` (:class:`flight.mocap_time.StreamStats`)."""

    def __init__(self, offer, mc: MocapConfig, stats: StreamStats) -> None:
        from services.natnet_client import FrameStream

        self.stream = FrameStream(offer, mc.interface)
        self.body_id = next(i for i, n in offer.bodies.items() if n == mc.rigid_body)
        self.clock_hz = float(offer.info.clock_hz)
        self.capture = CaptureClock()
        self.stats = stats

    def next(self, timeout_s: float):
        got = self.stream.read(timeout_s)
        if got is None:
            return None
        frame, arrival_s = got
        mid_s, transmit_s = frame.mid_exposure_ticks / self.clock_hz, frame.transmit_ticks / self.clock_hz
        capture_s = self.capture.capture_s(arrival_s, mid_s, transmit_s)
        if not self.stats.add(capture_s, arrival_s, max(0.0, transmit_s - mid_s)):
            return "late"
        body = next((b for b in frame.bodies if b.id == self.body_id and b.tracked), None)
        if body is None:
            return mid_s, capture_s, None
        qx, qy, qz, qw = body.quat_xyzw
        return mid_s, capture_s, (np.asarray(body.pos_m), (qw, qx, qy, qz))

    def close(self) -> None:
        self.stream.close()


class _LibraryFrames:
    """Frames of the ``motioncapture`` library (``waitForNextFrame`` blocks until one; no frame times: stamped on
    arrival)."""

    def __init__(self, mc: MocapConfig, stats: StreamStats) -> None:
        import motioncapture

        self.mc = motioncapture.connect(mc.type, {"hostname": mc.hostname})
        self.name = mc.rigid_body
        self.stats = stats

    def next(self, timeout_s: float):
        self.mc.waitForNextFrame()
        now = time.monotonic()
        body = self.mc.rigidBodies.get(self.name)
        self.stats.add(now, now, 0.0)
        if body is None:
            return now, now, None
        q = body.rotation
        return now, now, (np.asarray(body.position), (q.w, q.x, q.y, q.z))  # no frame time: its arrival

    def close(self) -> None:
        pass


def run_mocap(node, config: SourceConfig, *, offer=None, n_total: int | None = None) -> None:
    """Frames on a thread of their own; this thread watches the stream: no frame for ``stream_timeout_s`` is a
    stopped stream, frames without the rigid body are a lost rigid body (each an event when it starts and when it
    ends, frames counted in health). ``offer``: the NatNet server's (:func:`natnet_offer`) for OptiTrack.
    ``n_total``: stop after that many states. The stream's figures (rate, latency, jitter, gaps: 
    :class:`flight.mocap_time.StreamStats`) go into the health counters every second."""
    mc_config = config.mocap
    core = MocapSource(mc_config, config.rate_hz, clock=time.monotonic)
    put_state = node.publisher("state")
    name = mc_config.rigid_body
    where = f"{mc_config.hostname}:{mc_config.port}" if offer is not None else mc_config.hostname
    stats = StreamStats()
    if offer is not None:
        node.log(f"NatNet {offer.version} at {where} ({offer.tries} {'query' if offer.tries == 1 else 'queries'}), "
                 f"rigid bodies {list(offer.bodies.values())}")
    node.log(f"connecting to {mc_config.type} at {where}, rigid body {name!r}, frame {mc_config.frame}")
    frames = _NatNetFrames(offer, mc_config, stats) if offer is not None else _LibraryFrames(mc_config, stats)
    seen = [0]
    watch = {"last_frame_s": time.monotonic(), "stopped_since": None, "lost_since": None, "lost_frames": 0}
    stopping = [False]

    def read_frames() -> None:
        while not node.stopping and not stopping[0]:
            got = frames.next(0.1)
            if got is None or stopping[0]:
                continue
            now = time.monotonic()
            with node.lock:
                seen[0] += 1
                watch["last_frame_s"] = now
                if watch["stopped_since"] is not None:
                    node.event("info", f"mocap stream from {where} back after {now - watch['stopped_since']:.2f} s")
                    watch["stopped_since"] = None
                if got == "late":
                    continue
                frame_s, capture_s, pose = got
                if pose is None:
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
                state = core.frame(frame_s, *pose, capture_stamp_s=capture_s)
                if state is not None:
                    put_state(state)
                    node.stats.output(time.monotonic() - state.stamp_s)

    kind = f"{mc_config.type} (NatNet {offer.version} at {where})" if offer is not None else mc_config.type

    def status() -> str:
        for key, value in stats.summary().items():
            node.stats.set_counter(key, value)
        node.stats.set_counter("rigid_body_tracked", float(core.seq >= 0 and watch["lost_since"] is None
                                                           and watch["stopped_since"] is None))
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
    reader.join(timeout=1.0)  # NatNet: within 0.1 s; the library's reader stays blocked on a stopped stream (a daemon)
    frames.close()
    node.log(f"done: {seen[0]} frames, {core.seq + 1} states, {watch['lost_frames']} frames without {name!r}, "
             f"{stats.out_of_order} out of order")
