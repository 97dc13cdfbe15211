"""The source's step objects: where state samples come from — the simulator or a motion-capture system.

Simulator (:class:`SimSource`): steps :class:`sim.quadrotor.QuadrotorSim` one control period
with the newest setpoint and publishes the state (and the truth). Two ways to run:

- real time: one sample every period on the wall clock, the newest setpoint acts (a setpoint
  that has not arrived by the next sample is a deadline miss: the previous one is held; misses
  are counted in health ``counters`` and explained in a warning event at most once a second:
  which process took the time, how late, and the machine's load, :mod:`flight.deadline`);
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

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from neso.control import ControlConfig, PositionController
from neso.rotations import euler_zyx_from_world_from_body
from neso.types import LOOP_RATE_HZ, VEL_CUTOFF_HZ, AttitudeSetpoint
from runtime.options import comma_list, option
from runtime.schema import SetpointMsg, StateMsg, TruthMsg, vec
from sim.scenarios import SCENARIOS

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

    type: str = option("optitrack", flag="--mocap-type",
                       help="motioncapture backend (optitrack, vicon, qualisys, vrpn, mock...)")
    hostname: str = option("127.0.0.1", flag="--mocap-host", help="the mocap system's address")
    port: int = option(1510, flag="--mocap-port", help="optitrack: Motive's NatNet command port")
    interface: str = option("0.0.0.0", flag="--mocap-interface",
                            help="optitrack: this machine's address on the mocap network (joins the multicast there)")
    rigid_body: str = option("uav1", help="the vehicle's rigid-body name in the mocap software")
    frame: str = option("y_up", help=f"mocap frame: {sorted(FRAMES)} or 9 numbers (ENU from mocap, row-major)")
    stream_timeout_s: float = option(0.5, flag="--stream-timeout", unit="s",
                                     help="no frame for this long: the stream has stopped (an event)")
    vel_cutoff_hz: float = VEL_CUTOFF_HZ


@dataclass(frozen=True)
class NatNetStreamConfig:
    """The simulated Motive of ``--mocap-stream natnet``: its command port (the data port is the next one),
    up axis, and what happens to the frames on the way (:class:`sim.natnet_server.StreamModel`; the
    latency is the world's mocap model's)."""

    port: int = option(1510, flag="--natnet-port", help="the simulated Motive's command port (data: the next port)")
    up_axis: str = option("y", flag="--natnet-up-axis", choices=("y", "z"), help="Motive's up axis")
    rate_hz: float = option(0.0, flag="--natnet-rate", unit="Hz",
                            help="frame rate, 100-360 (0: the world's mocap model's, 100 Hz); the physics step shrinks to fit")
    jitter_ms: float = option(0.0, flag="--natnet-jitter", unit="ms", help="std of each frame's send time")
    dropout: float = option(0.0, flag="--natnet-dropout", help="probability a frame is not sent")
    lost: str = option("", flag="--natnet-lost",
                       help="world-time windows with the rigid body untracked: 'start:duration,...' in s")
    feed_port: int = option(0, flag="--natnet-feed",
                            help="a shared simulated Motive's feed port (sim/natnet_motive.py, several vehicles on one "
                                 "stream): the world feeds it; 0: the world runs its own Motive on --natnet-port")
    body_id: int = option(1, flag="--natnet-body-id", help="the rigid body's ID in a shared Motive (1, 2, …)")
    version: str = option("4.1", flag="--natnet-version", choices=("3.0", "3.1", "4.0", "4.1"),
                          help="the NatNet version the simulated Motive speaks (Motive 2.0, 2.1, 3.0, 3.1)")

    def version_tuple(self) -> tuple[int, int]:
        major, minor = self.version.split(".")
        return int(major), int(minor)

    def lost_windows(self) -> tuple[tuple[float, float], ...]:
        try:
            return tuple((float(a), float(b)) for a, b in (w.split(":") for w in self.lost.split(",") if w.strip()))
        except ValueError:
            raise ValueError(f"--natnet-lost {self.lost!r}: windows 'start:duration' in s, comma-separated") from None


@dataclass(frozen=True)
class SourceConfig:
    backend: str = option("sim", choices=("sim", "mocap"), help="where states come from")
    scenario: str = option("nominal_landing", choices=tuple(sorted(SCENARIOS)), help="the simulated world")
    seed: int = option(1, help="the simulated world's random seed")
    rate_hz: float = option(LOOP_RATE_HZ, flag="--rate", unit="Hz", help="control rate")
    start: str = option("scenario", choices=("scenario", "ground"),
                        help="scenario: the scenario's start pose; ground: on the floor below it")
    lockstep: bool = False
    duration_s: float = option(0.0, flag="--duration", unit="s", help="seconds of flight, 0 = until stopped")
    wait_for: tuple[str, ...] = option(("estimator", "controller"), cli=comma_list(),
                                       help="services whose liveliness the world waits for before its first sample (lockstep: "
                                            "required; real time: at most 30 s)")
    lockstep_resend_s: float = 1.0
    first_answer_wait_s: float = 2.0  # real time: the world's clock starts once sample 0 is answered, or after this
    first_answer_resend_s: float = 0.1  # ... re-sending sample 0 this often until then
    stall_report_s: float = 0.5  # real time: a loop that stood still this long is reported, with where it stood
    lockstep_pace: float = option(0.0, help="lockstep: at most this multiple of real time (0: as fast as the services "
                                            "answer; a paced flight leaves the machine's CPU to the rest)")
    mocap: MocapConfig = option(default_factory=MocapConfig, nested=True)
    link: str = option("direct", choices=("direct", "mavlink", "px4"),
                       help="how setpoints reach the simulated vehicle: direct (bus setpoints), mavlink (it presents "
                            "itself as a PX4 on --mavlink-out; the px4_gateway flies it, sim/mavlink_vehicle.py) or px4 "
                            "(it is real PX4 SITL's simulator on TCP --px4-port; PX4 flies it, sim/px4_hil.py)")
    px4_port: int = option(4560, help="--link px4: the TCP port PX4 SITL connects to (4560 + its instance)")
    mavlink_out: str = option("udpout:127.0.0.1:14540",
                              help="where the simulated PX4 sends its MAVLink (the gateway's udpin address)")
    mavlink_log: str = option("", help="JSON-lines log of every MAVLink command/setpoint received")
    mocap_stream: str = option("direct", choices=("direct", "natnet"),
                               help="how the simulated world's mocap samples become the state: direct (in this "
                                    "process) or natnet (a simulated Motive streams NatNet on loopback, read by the "
                                    "motioncapture optitrack client as in a lab; services/source.py)")
    natnet: NatNetStreamConfig = option(default_factory=NatNetStreamConfig, nested=True)


class SimSource:
    """The simulator as a pure step object: :meth:`take` a setpoint, :meth:`step` a period.
    ``mocap_rate_hz``: the world's motion capture at that rate instead of its model's (an integer in Hz;
    the physics step becomes 1/lcm(rate, 500) s so that every period stays a whole number of steps)."""

    def __init__(self, config: SourceConfig, *, clock: Callable[[], float], mocap_rate_hz: float = 0.0) -> None:
        from sim.quadrotor import QuadrotorSim
        from sim.scenarios import make_scenario

        self.config = config
        self.clock = clock
        self.scenario = make_scenario(config.scenario, control_period_s=1.0 / config.rate_hz)
        if mocap_rate_hz:
            steps_per_s = math.lcm(int(mocap_rate_hz), round(1.0 / self.scenario.dt_s))
            self.scenario = replace(self.scenario, dt_s=1.0 / steps_per_s,
                                    mocap=replace(self.scenario.mocap, rate_hz=float(int(mocap_rate_hz))))
        self.sim = QuadrotorSim(self.scenario, seed=config.seed)
        x, y, z = self.scenario.initial_pos_enu_m
        self.sim.reset(pos_enu_m=(x, y, z if config.start == "scenario" else -1.0), yaw_rad=self.scenario.initial_yaw_rad)
        on_ground = self.sim.truth.on_ground
        hover = PositionController(ControlConfig(dt_s=1.0 / config.rate_hz)).hover_output(self.scenario.initial_yaw_rad)
        self.setpoint = AttitudeSetpoint(0.0, 0.0, 0.0, 0.0, 0.0) if on_ground else hover.setpoint
        self.setpoint_seq = -1
        self.seq = -1
        self.untracked_until_t_s = -math.inf

    def lose_tracking(self, duration_s: float) -> None:
        """The world's motion capture loses the vehicle for ``duration_s`` (s) of world time from now: its
        states are not to be published (:attr:`tracked`); the world flies on."""
        self.untracked_until_t_s = self.sim.t_s + duration_s

    @property
    def tracked(self) -> bool:
        """Whether the last :meth:`step`'s state was seen by the world's motion capture."""
        return self.sim.t_s > self.untracked_until_t_s

    def take(self, sp: SetpointMsg) -> None:
        """Hold ``sp`` from the next period on (older ones than held are ignored)."""
        if sp.seq >= self.setpoint_seq or sp.seq == self.seq:
            self.setpoint_seq = sp.seq
            self.setpoint = AttitudeSetpoint(sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm, sp.thrust_n)

    def step(self) -> tuple[StateMsg, TruthMsg]:
        meas = self.sim.step(self.setpoint)
        truth = self.sim.truth
        self.seq += 1
        now = self.clock()
        state = StateMsg(seq=self.seq, stamp_s=now, t_s=truth.t_s, pos_enu_m=vec(meas.pos_enu_m),
                         vel_enu_mps=vec(meas.vel_enu_mps), roll_rad=meas.roll_rad, pitch_rad=meas.pitch_rad,
                         yaw_rad=meas.yaw_rad, source="sim",
                         capture_stamp_s=max(0.0, now - (truth.t_s - meas.t_s)))  # the world's mocap exposure
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

    def __init__(self, config: MocapConfig, rate_hz: float, *, clock: Callable[[], float]) -> None:
        self.config = config
        self.clock = clock
        self.enu_from_mocap = frame_matrix(config.frame)
        self.period_s = 1.0 / rate_hz
        self.seq = -1
        self._t0: float | None = None
        self._prev: tuple[float, np.ndarray] | None = None
        self._vel = np.zeros(3)
        self._next_publish_s = -math.inf

    def frame(self, t_s: float, pos_m: np.ndarray, quat_wxyz: tuple[float, float, float, float],
              capture_stamp_s: float | None = None) -> StateMsg | None:
        """One mocap frame taken at ``t_s`` on the stream's own clock (Motive's camera mid-exposure, s; the arrival
        on this machine's monotonic clock for a system that gives no time): the state to publish, or None between
        control ticks. ``capture_stamp_s``: that instant on this machine's monotonic clock
        (:class:`flight.mocap_time.CaptureClock`; default ``t_s``). The state's ``t_s`` counts from the first
        frame on the stream's clock, so its steps are whole frame intervals; a frame not newer than the last one
        must not be given (:meth:`flight.mocap_time.StreamStats.add` tells)."""
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
        return StateMsg(seq=self.seq, stamp_s=self.clock(), t_s=t_s - self._t0, pos_enu_m=vec(pos),
                        vel_enu_mps=vec(self._vel), roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, source="mocap",
                        capture_stamp_s=t_s if capture_stamp_s is None else capture_stamp_s)
