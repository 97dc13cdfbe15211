"""The simulated world behind ``source --mocap-stream natnet``: a child process that flies the vehicle in
real time and shows it to the source only through a simulated Motive (NatNet on loopback).

Why a process of its own: libmotioncapture's ``connect`` holds Python's GIL while it waits for the
server's answer, so a server in the source's own process could never answer it; and it is what a lab
has, the motion capture on another machine. Over a pipe to the source: setpoints in (msgpack bytes,
the newest acts from the next period, as in the direct simulator), truth out (one ``TruthMsg`` per
period, ``seq`` counting the world's periods). Every mocap sample the world takes (noise and latency from
the scenario's ``sim.mocap.MocapConfig``, its rate too unless ``--natnet-rate``) leaves as a NatNet frame at its exposure time
plus that latency (:class:`sim.natnet_server.WorldStream`), through the jitter, dropouts and lost
windows of ``--natnet-*``. With ``--natnet-feed`` (several vehicles, one Motive) the world runs no server: it
feeds its samples to the shared simulated Motive (:class:`sim.natnet_server.FeedStream`, ``sim/natnet_motive.py``).
With ``--link mavlink`` the world is also the simulated PX4 (sim/mavlink_vehicle.py) that the px4_gateway flies,
as the source's own ``--link mavlink`` does: a PX4 vehicle in a room with OptiTrack.
"""
from __future__ import annotations

import math
import signal
import time

from flight.source import SimSource, SourceConfig
from runtime.schema import SetpointMsg, state_measurement
from sim.natnet_server import FeedStream, NatNetServer, NatNetServerConfig, StreamModel, WorldStream

BODY_ID = 1
WORLD_GO = b"go"  # the source's word on the pipe to start the world: its loop is alive


def _mavlink_vehicle(config: SourceConfig, core: SimSource):
    """``--link mavlink``: the world presents itself as a PX4 on ``--mavlink-out`` (sim/mavlink_vehicle.py), flown by
    the px4_gateway; what it prints on its console goes to this process's output as the source's."""
    from sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

    return MavlinkVehicle(VehicleConfig(target=config.mavlink_out, log_path=config.mavlink_log,
                                        hover_thrust_norm=core.sim.config.params.hover_thrust_norm),
                          dt_s=1.0 / config.rate_hz, console=lambda text: print(f"[source] {text}", flush=True))


def skip_ahead_s(late_s: float, frame_s: float) -> float:
    """How far a world ``late_s`` behind the wall clock moves its clock on: the whole Motive frames (``frame_s``
    each) that cover it. Before, it moved by ``late_s`` itself, so on a loaded machine a state's time stepped off
    Motive's frame grid (0.78 ms off it, `tests/process/test_natnet_jitter.py` with one core busy)."""
    return math.ceil(late_s / frame_s - 1e-9) * frame_s


def stream_model(config: SourceConfig, latency_s: float) -> StreamModel:
    nn = config.natnet
    return StreamModel(latency_s=latency_s, jitter_std_s=nn.jitter_ms / 1e3, dropout=nn.dropout,
                       lost=nn.lost_windows(), up_axis=nn.up_axis)


def run_world(conn, config: SourceConfig) -> None:
    """The child's main: ``("ready", command_port)`` once the server listens; from :data:`WORLD_GO` on, a truth per
    period until the pipe closes or brings an empty message."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group; the source ends us
    core = SimSource(config, clock=time.monotonic, mocap_rate_hz=config.natnet.rate_hz)
    samples: list = []
    core.sim.mocap_out = samples
    nn = config.natnet
    model = stream_model(config, core.scenario.mocap.latency_s)
    server = None if nn.feed_port else NatNetServer(NatNetServerConfig(
        bodies={config.mocap.rigid_body: BODY_ID}, command_port=nn.port, data_port=nn.port + 1,
        version=nn.version_tuple())).start()
    vehicle = _mavlink_vehicle(config, core) if config.link == "mavlink" else None
    stream = None
    try:
        anchor_s = time.monotonic() - core.sim.t_s
        stream = (FeedStream(nn.feed_port, model, body_id=nn.body_id, anchor_s=anchor_s) if server is None else
                  WorldStream(server, model, body_id=BODY_ID, anchor_s=anchor_s, seed=config.seed))
        conn.send(("ready", nn.port if server is None else server.command_port))
        if conn.recv_bytes() != WORLD_GO:  # the source says go once its loop is alive; an empty message: stop
            return
        stream.anchor_s = time.monotonic() - core.sim.t_s
        period = 1.0 / config.rate_hz
        next_tick = time.monotonic()
        while True:
            while conn.poll():
                data = conn.recv_bytes()
                if not data:
                    return
                if vehicle is None:  # a MAVLink vehicle flies what the gateway sends it, not the bus's setpoints
                    core.take(SetpointMsg.from_bytes(data))
            if vehicle is not None:
                core.setpoint = vehicle.control(core.sim._measurement(), on_ground=bool(core.sim.truth.on_ground))
            state, truth = core.step()
            if vehicle is not None:
                vehicle.publish(state_measurement(state), t_s=truth.t_s)
            for s in samples:
                stream.sample(s.t_s, s.pos_enu_m, (s.roll_rad, s.pitch_rad, s.yaw_rad))
            samples.clear()
            conn.send_bytes(truth.to_bytes())
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -period:  # fell behind by more than a period: the world's clock moves on with the wall's,
                # by whole Motive frames, as a real Motive's exposures stay on its frame grid whatever a world does
                skip = skip_ahead_s(-delay, 1.0 / core.scenario.mocap.rate_hz)  # rate 0: the model's
                stream.anchor_s += skip
                next_tick += skip
    except (EOFError, BrokenPipeError, OSError):
        return
    finally:
        if vehicle is not None:
            vehicle.close()
        if server is not None:
            server.close()
        elif stream is not None:
            stream.close()
