"""``source``: where state samples come from — the simulator or a motion-capture system.

Simulator (:class:`SimSource`): steps :class:`sim.quadrotor.QuadrotorSim` one control period
with the newest setpoint and publishes the state (and the truth). Two ways to run:

- real time: one sample every period on the wall clock, the newest setpoint acts (a setpoint
  that has not arrived by the next sample is a deadline miss: the previous one is held; misses
  are counted in health ``counters`` and explained in a warning event at most once a second:
  which process took the time, how late, and the machine's load, :mod:`services.deadline`);
- lockstep: sample k+1 is computed only once setpoint k has arrived, so a run is
  deterministic and reproduces :func:`sim.runner.fly` exactly (same seed, same network).

Command ``scenario`` (args ``{"name": <scenario>}``, simulator in real time only): the world
restarts with that scenario at the next period, without any process restarting. The new world
is a new flight: ``seq`` and the source's clock start again at 0, which is how the estimator
and the controller recognise a new flight (they re-initialise and fly its start mission).

Motion capture (:class:`MocapSource`): frames from the ``motioncapture`` library (OptiTrack,
Vicon, Qualisys, VRPN, ... as Crazyswarm2 uses it), the configured rigid body mapped into
ENU, velocity from a filtered finite difference, published at the control rate. Setpoints
then go to the vehicle (the PX4 gateway), not to the source.
"""
from __future__ import annotations

import argparse
import math
import os
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np

from neso.control import ControlConfig, PositionController
from neso.rotations import euler_zyx_from_world_from_body
from neso.types import AttitudeSetpoint
from runtime.schema import SetpointMsg, StateMsg, TruthMsg, vec
from services.deadline import DeadlineWatch

# mocap frame → ENU rotations: p_enu = M @ p_mocap
FRAMES: dict[str, tuple[tuple[float, ...], ...]] = {
    "enu": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "ned": ((0, 1, 0), (1, 0, 0), (0, 0, -1)),
    "y_up": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),  # OptiTrack/Motive default: x, y up, z towards the operator
}


@dataclass(frozen=True)
class MocapConfig:
    """``type``/``hostname``: passed to ``motioncapture.connect``. ``rigid_body``: the vehicle's
    name in the mocap software. ``frame``: a name in :data:`FRAMES` or 9 numbers (row-major M)."""

    type: str = "optitrack"
    hostname: str = "127.0.0.1"
    rigid_body: str = "uav1"
    frame: str = "y_up"
    vel_cutoff_hz: float = 15.0


@dataclass(frozen=True)
class SourceConfig:
    backend: str = "sim"  # "sim" or "mocap"
    scenario: str = "nominal_landing"
    seed: int = 1
    rate_hz: float = 50.0
    start: str = "scenario"  # "scenario": the scenario's start pose; "ground": on the floor below it
    lockstep: bool = False
    duration_s: float = 0.0  # 0: until stopped
    wait_for: tuple[str, ...] = ("estimator", "controller")
    lockstep_resend_s: float = 1.0
    mocap: MocapConfig = field(default_factory=MocapConfig)
    link: str = "direct"  # "direct": bus setpoints act; "mavlink": a MAVLink PX4 stand-in takes them (sim/mavlink_vehicle.py)
    mavlink_out: str = "udpout:127.0.0.1:14540"
    mavlink_log: str = ""


class SimSource:
    """The simulator as a pure step object: :meth:`take` a setpoint, :meth:`step` a period."""

    def __init__(self, config: SourceConfig) -> None:
        from sim.quadrotor import QuadrotorSim
        from sim.scenarios import make_scenario

        self.config = config
        self.scenario = make_scenario(config.scenario, control_period_s=1.0 / config.rate_hz)
        self.sim = QuadrotorSim(self.scenario, seed=config.seed)
        x, y, z = self.scenario.initial_pos_enu_m
        self.sim.reset(pos_enu_m=(x, y, z if config.start == "scenario" else -1.0), yaw_rad=self.scenario.initial_yaw_rad)
        on_ground = self.sim.truth.on_ground
        hover = PositionController(ControlConfig(dt_s=1.0 / config.rate_hz)).hover_output(self.scenario.initial_yaw_rad)
        self.setpoint = AttitudeSetpoint(0.0, 0.0, 0.0, 0.0, 0.0) if on_ground else hover.setpoint
        self.setpoint_seq = -1
        self.seq = -1

    def take(self, sp: SetpointMsg) -> None:
        """Hold ``sp`` from the next period on (older ones than held are ignored)."""
        if sp.seq >= self.setpoint_seq or sp.seq == self.seq:
            self.setpoint_seq = sp.seq
            self.setpoint = AttitudeSetpoint(sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm, sp.thrust_n)

    def step(self) -> tuple[StateMsg, TruthMsg]:
        meas = self.sim.step(self.setpoint)
        truth = self.sim.truth
        self.seq += 1
        now = time.monotonic()
        state = StateMsg(seq=self.seq, stamp_s=now, t_s=truth.t_s, pos_enu_m=vec(meas.pos_enu_m),
                         vel_enu_mps=vec(meas.vel_enu_mps), roll_rad=meas.roll_rad, pitch_rad=meas.pitch_rad,
                         yaw_rad=meas.yaw_rad, source="sim")
        truth_msg = TruthMsg(seq=self.seq, stamp_s=now, t_s=truth.t_s, pos_enu_m=vec(truth.pos_enu_m),
                             vel_enu_mps=vec(truth.vel_enu_mps),
                             disturbance_acc_enu_mps2=vec(np.clip(truth.disturbance_acc_enu_mps2, -1e4, 1e4)),
                             on_ground=bool(truth.on_ground), crashed=bool(self.sim.crashed or self.sim.diverged),
                             scenario=self.scenario.name)
        return state, truth_msg


def frame_matrix(frame: str) -> np.ndarray:
    if frame in FRAMES:
        return np.array(FRAMES[frame], dtype=float)
    values = [float(v) for v in frame.replace(",", " ").split()]
    m = np.array(values).reshape(3, 3) if len(values) == 9 else None
    if m is None or not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or not np.isclose(np.linalg.det(m), 1.0, atol=1e-6):
        raise ValueError(f"frame {frame!r}: a name in {sorted(FRAMES)} or 9 numbers of a rotation matrix")
    return m


class MocapSource:
    """Rigid-body frames → state samples (pure: give it poses, it gives messages)."""

    def __init__(self, config: MocapConfig, rate_hz: float) -> None:
        self.config = config
        self.enu_from_mocap = frame_matrix(config.frame)
        self.period_s = 1.0 / rate_hz
        self.seq = -1
        self._t0: float | None = None
        self._prev: tuple[float, np.ndarray] | None = None
        self._vel = np.zeros(3)
        self._next_publish_s = -math.inf

    def frame(self, t_s: float, pos_m: np.ndarray, quat_wxyz: tuple[float, float, float, float]) -> StateMsg | None:
        """One mocap frame at monotonic ``t_s``: the state to publish, or None between control ticks."""
        if self._t0 is None:
            self._t0 = t_s
        pos = self.enu_from_mocap @ np.asarray(pos_m, dtype=float)
        if self._prev is not None and t_s > self._prev[0]:
            dt = t_s - self._prev[0]
            raw = (pos - self._prev[1]) / dt
            a = math.exp(-2 * math.pi * self.config.vel_cutoff_hz * dt)
            self._vel = a * self._vel + (1 - a) * raw
        self._prev = (t_s, pos)
        if t_s < self._next_publish_s - self.period_s / 4:  # a quarter period of slack for frame jitter
            return None
        self._next_publish_s += self.period_s
        if self._next_publish_s < t_s:  # first frame, or frames stopped for a while: re-anchor the grid
            self._next_publish_s = t_s + self.period_s
        w, x, y, z = quat_wxyz
        body = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ])
        roll, pitch, yaw = euler_zyx_from_world_from_body(self.enu_from_mocap @ body @ self.enu_from_mocap.T)
        self.seq += 1
        return StateMsg(seq=self.seq, stamp_s=time.monotonic(), t_s=t_s - self._t0, pos_enu_m=vec(pos),
                        vel_enu_mps=vec(self._vel), roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, source="mocap")


# -- bus adapter ------------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from sim.scenarios import SCENARIOS

    parser.add_argument("--backend", default="sim", choices=("sim", "mocap"))
    parser.add_argument("--scenario", default="nominal_landing", choices=sorted(SCENARIOS))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--rate", type=float, default=50.0, help="control rate Hz")
    parser.add_argument("--start", default="scenario", choices=("scenario", "ground"))
    parser.add_argument("--duration", type=float, default=0.0, help="seconds of flight, 0 = until stopped")
    parser.add_argument("--wait-for", default="estimator,controller",
                        help="services whose liveliness a lockstep run waits for before the first sample")
    parser.add_argument("--mocap-type", default="optitrack", help="motioncapture backend (optitrack, vicon, qualisys, vrpn, mock...)")
    parser.add_argument("--mocap-host", default="127.0.0.1")
    parser.add_argument("--rigid-body", default="uav1", help="the vehicle's rigid-body name in the mocap software")
    parser.add_argument("--frame", default="y_up", help=f"mocap frame: {sorted(FRAMES)} or 9 numbers (ENU from mocap)")
    parser.add_argument("--link", default="direct", choices=("direct", "mavlink"),
                        help="how setpoints reach the simulated vehicle: direct (bus setpoints) or mavlink "
                             "(it presents itself as a PX4 on --mavlink-out; the px4_gateway flies it)")
    parser.add_argument("--mavlink-out", default="udpout:127.0.0.1:14540",
                        help="where the simulated PX4 sends its MAVLink (the gateway's udpin address)")
    parser.add_argument("--mavlink-log", default="", help="JSON-lines log of every MAVLink command/setpoint received")


def config_from_args(args) -> SourceConfig:
    return SourceConfig(
        backend=args.backend, scenario=args.scenario, seed=args.seed, rate_hz=args.rate, start=args.start,
        lockstep=getattr(args, "lockstep", False), duration_s=args.duration,
        wait_for=tuple(s for s in args.wait_for.split(",") if s),
        mocap=MocapConfig(type=args.mocap_type, hostname=args.mocap_host, rigid_body=args.rigid_body, frame=args.frame),
        link=args.link, mavlink_out=args.mavlink_out, mavlink_log=args.mavlink_log,
    )


def run(args, bus) -> int:
    from runtime.node import Node, run_node

    config = config_from_args(args)
    node = Node("source", vehicle=args.vehicle, bus=bus, config=config)
    if config.backend == "mocap":
        frame_matrix(config.mocap.frame)  # refuse a bad frame before joining the bus
        return run_node(node, lambda n: _run_mocap(n, config))
    if config.link == "mavlink":
        if config.lockstep:
            raise SystemExit("source: --link mavlink runs in real time only (MAVSDK streams on its own clock)")
        return run_node(node, lambda n: _run_sim_mavlink(n, config))
    return run_node(node, lambda n: _run_sim(n, config))


def _run_sim(node, config: SourceConfig) -> None:
    core = SimSource(config)
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

        if name != "scenario":
            return False, f"unknown command {name!r}; the sim source takes: scenario"
        wanted = args.get("name")
        if wanted not in SCENARIOS:
            return False, f"scenario {wanted!r} is not one of {sorted(SCENARIOS)}"
        if config.lockstep:
            return False, "a lockstep flight cannot switch scenario (restart it)"
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
                core = SimSource(replace(core.config, scenario=next_scenario.pop()))
                node.event("info", f"world restarted with scenario {core.config.scenario}")
            elif not config.lockstep and core.seq >= 0 and core.setpoint_seq != core.seq:
                misses[0] += 1
                node.stats.count("deadline_misses")
                if last_state and last_state[0].seq == core.seq:
                    watch.missed(core.seq, last_state[0].stamp_s, time.monotonic())
            state, truth = core.step()
            put_state(state)
            put_truth(truth)
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

    core = SimSource(config)
    vehicle = MavlinkVehicle(VehicleConfig(target=config.mavlink_out, log_path=config.mavlink_log,
                                           hover_thrust_norm=core.sim.config.params.hover_thrust_norm),
                             dt_s=1.0 / config.rate_hz)
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


def _run_mocap(node, config: SourceConfig) -> None:
    import motioncapture

    core = MocapSource(config.mocap, config.rate_hz)
    put_state = node.publisher("state")
    name = config.mocap.rigid_body
    node.log(f"connecting to {config.mocap.type} at {config.mocap.hostname}, rigid body {name!r}, frame {config.mocap.frame}")
    mc = motioncapture.connect(config.mocap.type, {"hostname": config.mocap.hostname})
    seen = [0]
    node.status_hook = lambda: (f"mocap {config.mocap.type}: {seen[0]} frames, sample {core.seq}" if core.seq >= 0 else
                                f"mocap {config.mocap.type}: {seen[0]} frames, rigid body {name!r} not seen yet")
    while not node.stopping:
        mc.waitForNextFrame()
        seen[0] += 1
        body = mc.rigidBodies.get(name)
        if body is None:
            continue
        q = body.rotation
        state = core.frame(time.monotonic(), np.asarray(body.position), (q.w, q.x, q.y, q.z))
        if state is not None:
            put_state(state)
            node.stats.output(time.monotonic() - state.stamp_s)
