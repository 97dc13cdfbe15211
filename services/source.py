"""``source`` on the bus: the thin adapter around :class:`flight.source.SimSource` and
:class:`flight.source.MocapSource` (what each does is documented in :mod:`flight.source`).

Real time: one sample every period on the wall clock, the newest setpoint acts; lockstep: sample k+1
once setpoint k has arrived. Command ``scenario`` restarts the world as a new flight.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from dataclasses import replace

from flight.deadline import DeadlineWatch
import numpy as np

from flight.source import MocapSource, SimSource, SourceConfig, frame_matrix
from runtime.options import add_options, config_from_options
from runtime.schema import SetpointMsg, StateMsg


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, SourceConfig)


def config_from_args(args) -> SourceConfig:
    return config_from_options(SourceConfig, args, lockstep=getattr(args, "lockstep", False))


def run(args, bus) -> int:
    from runtime.node import Node, run_node

    config = config_from_args(args)
    node = Node("source", vehicle=args.vehicle, bus=bus, config=config)
    if config.backend == "mocap":
        frame_matrix(config.mocap.frame)  # refuse a bad frame before joining the bus
        return run_node(node, lambda n: _run_mocap(n, config))
    if config.mocap_stream == "natnet":
        problem = natnet_refusal(config)  # refused before joining the bus: one line, exit 2
        if problem:
            print(f"source: {problem}", file=sys.stderr, flush=True)
            raise SystemExit(2)
        return run_node(node, lambda n: _run_sim_natnet(n, config))
    if config.link == "mavlink":
        if config.lockstep:
            raise SystemExit("source: --link mavlink runs in real time only (MAVSDK streams on its own clock)")
        return run_node(node, lambda n: _run_sim_mavlink(n, config))
    if config.link == "px4":
        if config.lockstep:
            raise SystemExit("source: --link px4 runs in real time only (PX4 and MAVSDK keep wall-clock timeouts)")
        from services.px4_world import px4_in_the_loop

        return run_node(node, lambda n: _run_sim(n, config, world=lambda sim: px4_in_the_loop(n, config, sim)))
    return run_node(node, lambda n: _run_sim(n, config))


def _run_sim(node, config: SourceConfig, world=None) -> None:
    """``world``: wraps the simulator of the flight (PX4 in the loop), None: the simulator as it is."""
    core = SimSource(config, clock=time.monotonic)
    if world is not None:
        core.sim = world(core.sim)
    put_state, put_truth = node.publisher("state"), node.publisher("truth")
    arrived = threading.Condition(node.lock)
    misses = [0]
    watch = DeadlineWatch()
    last_state: list[StateMsg] = []

    def on_setpoint(msg: SetpointMsg, received_s: float) -> None:
        core.take(msg)
        watch.arrived(msg, received_s)
        arrived.notify_all()

    node.subscribe("setpoint", on_setpoint)
    node.status_hook = lambda: (f"{'lockstep' if config.lockstep else 'real time'}, scenario {core.config.scenario}, "
                                f"t={core.sim.t_s:.2f} s, sample {core.seq}, deadline misses {misses[0]}")
    next_scenario: list[str] = []

    def on_command(name: str, args: dict) -> tuple[bool, str]:
        from sim.scenarios import SCENARIOS

        if name == "lose_tracking":
            if config.lockstep:
                return False, "a lockstep flight waits for every state's setpoint: it cannot lose tracking"
            duration = args.get("duration_s", 1.0)
            if not isinstance(duration, (int, float)) or not 0.02 <= duration <= 10.0:
                return False, f"lose_tracking needs duration_s in 0.02-10 s, got {duration!r}"
            core.lose_tracking(float(duration))
            return True, (f"the world's motion capture loses the vehicle for {duration:g} s from t={core.sim.t_s:.2f} s: "
                          "no state until then")
        if name != "scenario":
            return False, f"unknown command {name!r}; the sim source takes: scenario, lose_tracking"
        wanted = args.get("name")
        if wanted not in SCENARIOS:
            return False, f"scenario {wanted!r} is not one of {sorted(SCENARIOS)}"
        if config.lockstep or world is not None:
            return False, f"a {'lockstep' if config.lockstep else 'PX4'} flight cannot switch scenario (restart it)"
        next_scenario[:] = [wanted]
        return True, f"world restarts with {wanted} at the next period (a new flight from sample 0)"

    node.on_command(on_command)
    if config.lockstep:
        _wait_for_services(node, config.wait_for)
    n_total = int(round(config.duration_s * config.rate_hz)) if config.duration_s > 0 else None
    period = 1.0 / config.rate_hz
    next_tick = time.monotonic()
    while not node.stopping and (n_total is None or core.seq + 1 < n_total):
        with node.lock:
            if next_scenario:
                core = SimSource(replace(core.config, scenario=next_scenario.pop()), clock=time.monotonic)
                node.event("info", f"world restarted with scenario {core.config.scenario}")
            elif not config.lockstep and last_state and last_state[0].seq == core.seq \
                    and core.setpoint_seq != core.seq:
                misses[0] += 1
                node.stats.count("deadline_misses")
                watch.missed(core.seq, last_state[0].stamp_s, time.monotonic())
            state, truth = core.step()
            put_truth(truth)
            if core.tracked:
                if last_state and last_state[0].seq < state.seq - 1:
                    node.event("info", f"the world's motion capture sees the vehicle again at t={truth.t_s:.2f} s "
                                       f"({state.seq - 1 - last_state[0].seq} samples without a state)")
                _publish_state(node, config, state, put_state, last_state, watch, arrived, core)
            else:  # the world's motion capture does not see it (command lose_tracking): no state
                node.stats.count("untracked_samples")
                if last_state and last_state[0].seq == state.seq - 1:
                    node.event("warning", f"the world's motion capture lost the vehicle at t={truth.t_s:.2f} s: "
                                          "no state until it is back")
        if not config.lockstep:
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                node.wait(delay)
            elif delay < -period:
                next_tick = time.monotonic()  # fell behind by more than a period: re-anchor
    node.log(f"done: {core.seq + 1} samples, t={core.sim.t_s:.2f} s, deadline misses {misses[0]}")
    node.event("info", f"flight finished after {core.seq + 1} samples ({core.sim.t_s:.2f} s)")


def _run_sim_mavlink(node, config: SourceConfig) -> None:
    """Real time; the setpoint of each period comes from the simulated PX4 (its mode decides:
    offboard attitude targets, or its own hold/take-off/land), not from the bus."""
    from runtime.schema import state_measurement
    from sim.mavlink_vehicle import MavlinkVehicle, VehicleConfig

    core = SimSource(config, clock=time.monotonic)
    vehicle = MavlinkVehicle(VehicleConfig(target=config.mavlink_out, log_path=config.mavlink_log,
                                           hover_thrust_norm=core.sim.config.params.hover_thrust_norm),
                             dt_s=1.0 / config.rate_hz, console=node.log)
    put_state, put_truth = node.publisher("state"), node.publisher("truth")
    node.status_hook = lambda: (f"real time, MAVLink vehicle on {config.mavlink_out}: mode {vehicle.mode_name}, "
                                f"armed {vehicle.armed}, t={core.sim.t_s:.2f} s, sample {core.seq}")
    node.log(f"MAVLink PX4 stand-in sending to {config.mavlink_out}" + (f", log {config.mavlink_log}" if config.mavlink_log else ""))
    n_total = int(round(config.duration_s * config.rate_hz)) if config.duration_s > 0 else None
    period = 1.0 / config.rate_hz
    meas = core.sim._measurement()
    next_tick = time.monotonic()
    try:
        while not node.stopping and (n_total is None or core.seq + 1 < n_total):
            with node.lock:
                core.setpoint = vehicle.control(meas, on_ground=bool(core.sim.truth.on_ground))
                state, truth = core.step()
                meas = state_measurement(state)
                vehicle.publish(meas, t_s=truth.t_s)
                put_state(state)
                put_truth(truth)
                node.stats.output(time.monotonic() - state.stamp_s)
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                node.wait(delay)
            elif delay < -period:
                next_tick = time.monotonic()
    finally:
        vehicle.close()
    node.log(f"done: {core.seq + 1} samples, t={core.sim.t_s:.2f} s")


def _publish_state(node, config: SourceConfig, state: StateMsg, put_state, last_state: list, watch: DeadlineWatch,
                   arrived: threading.Condition, core: SimSource) -> None:
    """One state on the bus (under the node lock); in lockstep, until its setpoint has come."""
    put_state(state)
    last_state[:] = [state]
    node.stats.output(time.monotonic() - state.stamp_s)
    why = watch.report(time.monotonic(), load_1min=os.getloadavg()[0], cores=os.cpu_count() or 1)
    if why:
        node.event("warning", why)
    if config.lockstep:
        while core.setpoint_seq != state.seq and not node.stopping:
            if not arrived.wait(config.lockstep_resend_s) and core.setpoint_seq != state.seq:
                node.log(f"lockstep: no setpoint for sample {state.seq} after {config.lockstep_resend_s} s; re-sending")
                put_state(state)


def _wait_for_services(node, names: tuple[str, ...], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    missing = list(names)
    while missing and not node.stopping:
        missing = [s for s in names if not list(node.session.liveliness().get(node.keys.alive(s), timeout=0.5))]
        if not missing:
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"lockstep: {missing} not alive after {timeout_s:.0f} s")
        node.wait(0.05)
    node.log(f"lockstep: {list(names)} alive, starting")


def natnet_refusal(config: SourceConfig) -> str:
    """Why ``--mocap-stream natnet`` cannot run with ``config`` (one line), or ""."""
    if config.lockstep or config.link == "mavlink":
        return "--mocap-stream natnet runs in real time with --link direct only"
    try:
        config.natnet.lost_windows()
    except ValueError as exc:
        return str(exc)
    rate = config.natnet.rate_hz
    if rate and not (100 <= rate <= 360 and rate == int(rate)):
        return f"--natnet-rate {rate:g}: a whole number of Hz in 100-360 (0: the world's)"
    return ""


def _run_sim_natnet(node, config: SourceConfig) -> None:
    """The world in a child process (services/natnet_world.py) streams NatNet on loopback; this process
    reads it exactly as in a lab (:func:`_run_mocap`, the motioncapture optitrack client), forwards the
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
        _run_mocap(node, replace(config, mocap=mocap), n_total=n_total)
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


def _run_mocap(node, config: SourceConfig, *, n_total: int | None = None) -> None:
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
