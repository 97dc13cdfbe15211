"""The controller's step object: mission + state + f̂ → attitude setpoint, with a local ESO when f̂ goes stale.

Commands: the missions of :mod:`flight.mission` plus ``arm`` (allow a take-off: a controller
started with ``--mission idle`` is disarmed, one started flying is armed), ``disarm`` (only
on the ground), ``hold`` (stop where the vehicle is: the reference freezes at the measured
position and the PD brakes the vehicle to it) and ``abort`` (land now from where it is).

The step object (:class:`ControllerCore`) pairs each state sample with the estimate for the
same ``seq`` and runs the position controller on them (the tick order of
:func:`sim.runner.fly`). It also runs its own plain ESO on every sample (a few µs): if the
estimate for the newest sample has not come within ``stale_timeout_s``, it flies on that
local f̂ instead, says so on the bus, and keeps doing so until the estimator's estimates are
back and warm. It never flies on a stale estimate. Mission commands and gain changes take
effect at the next sample.

Gain changes are checked against the stability certificate here, where they are applied: the
estimator reports the physical Lipschitz constant of the network it flies and its ω_o
(``NetworkMsg.certificate``), and a change of the z gains whose certificate then fails is
refused with the margin in the reason unless the request carries ``override: true`` (applied,
and an event says so). Until the estimator has reported, the check uses nothing it does not know:
a gain change is refused as "certificate unknown" (also overridable).
"""
from __future__ import annotations

from typing import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from flight import forget_older
from flight.mission import COMMANDS, Mission, MissionConfig
from flight.ratecheck import RateCheck
from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
from neso.control import GAIN_SETS, ControlConfig, PositionController
from neso.eso import EsoConfig
from neso.estimator import AppliedControl, NeuralESO, NeuralEsoConfig
from neso.types import OMEGA_O_RPS, AttitudeSetpoint, StateMeasurement, VehicleModel
from runtime.options import option
from runtime.params import Param, Refusal
from runtime.schema import EstimateMsg, NetworkMsg, ReferenceMsg, SetpointMsg, StateMsg, state_measurement, vec

EXTRA_COMMANDS = ("arm", "disarm", "hold", "abort")
ALL_COMMANDS = COMMANDS + EXTRA_COMMANDS
_NEEDS_ARMING = ("takeoff", "hover", "landing_test", "lemniscate")
MAX_LEMNISCATE_CYCLES = 20  # the ``cycles`` a lemniscate command may ask (6 s each: 2 min at most)


@dataclass(frozen=True)
class ControllerConfig:
    """``mission``: command started at the first sample of a flight (``idle``: wait for one).
    ``stale_timeout_s``: how long the newest sample may wait for its estimate before the local
    ESO takes over (default 3 periods); ``stale_samples``: it also takes over at the arrival of a
    sample when this many before it went unanswered (0: by time only). The count acts on the
    sample itself, where the time check waits for the watchdog thread, which a loaded machine
    may wake late. ``lockstep_stale_s``: the same wait in lockstep, where no deadline is flown and
    the wait only tells a dead estimator from a slow one. A longer one cured nothing: the lockstep TDR
    loop's pairs of silent samples (CI with 2 s, loaded run 45 with 5 s) were one setpoint lost on its
    way to the estimator: its state waited for it, and it and the next flew the local ESO. It is now
    sent again with the source's re-send after 1 s (:meth:`ControllerCore.on_state`).
    ``warmup_ticks``: samples a (re)started estimator must have run before its estimates are used again."""

    control: ControlConfig = option(default_factory=ControlConfig, flag="--rate", unit="Hz",
                                    cli=(lambda c: 1.0 / c.dt_s, lambda hz: replace(ControlConfig(), dt_s=1.0 / hz)),
                                    help="control rate (must match the source's)")
    mission: str = option("hover", choices=("idle",) + COMMANDS, help="mission started with the flight")
    missions: MissionConfig = field(default_factory=MissionConfig)
    omega_o_rps: float = option(OMEGA_O_RPS, flag="--omega-o", unit="rad/s", help="the local ESO's bandwidth")
    stale_periods: float = option(3.0, unit="periods", help="periods without an answered sample before the local "
                                                            "ESO flies (at least 20 ms; lockstep: --lockstep-stale)")
    lockstep_stale_s: float = option(2.0, flag="--lockstep-stale", unit="s",
                                     help="in lockstep, the wall-clock wait for an estimate before the local ESO "
                                          "flies (a dead estimator, not a deadline)")
    stale_timeout_s: float = 0.06  # stale_periods at the rate, as config_from_args derives it
    stale_samples: int = 3
    warmup_ticks: int = 25
    gains: str = option("paper", choices=tuple(GAIN_SETS), help="start-up gains (live parameters after): paper "
                        "(the paper's) or px4 (xy softer for PX4's slower attitude loop; neso.control.GAIN_SETS)")
    mass_kg: float = option(VehicleModel().mass_kg, unit="kg", help="the vehicle's mass: thrust in newtons is for it "
                            "(also a live parameter; recorded with every flight, so its labels are in m/s²)")


def gain_values(control: ControlConfig) -> dict[str, float]:
    """``control``'s gains and the vehicle's mass as the controller's live parameters (x and y share their
    gains)."""
    return {"kp_xy": control.kp[0], "kd_xy": control.kd[0], "kp_z": control.kp[2], "kd_z": control.kd[2],
            "mass_kg": control.vehicle.mass_kg}


def resolved(config: ControllerConfig) -> ControllerConfig:
    """``config`` as the controller flies it: its control law's gains are the set ``config.gains`` names (its
    ``control``'s own kp, kd are not read) and its vehicle model is at ``config.mass_kg``."""
    control = config.control
    kp, kd = GAIN_SETS[config.gains]
    return replace(config, control=replace(control, kp=kp, kd=kd,
                                           vehicle=replace(control.vehicle, mass_kg=config.mass_kg)))


_GAINS = gain_values(ControlConfig())
CONTROLLER_GAINS = (
    Param("kp_xy", _GAINS["kp_xy"], float, "horizontal position gain", "1/s²", lo=0.1, hi=50.0),
    Param("kd_xy", _GAINS["kd_xy"], float, "horizontal velocity gain", "1/s", lo=0.1, hi=30.0),
    Param("kp_z", _GAINS["kp_z"], float, "altitude position gain", "1/s²", lo=0.1, hi=50.0),
    Param("kd_z", _GAINS["kd_z"], float, "altitude velocity gain", "1/s", lo=0.1, hi=30.0),
)
CONTROLLER_PARAMS = CONTROLLER_GAINS + (
    Param("mass_kg", _GAINS["mass_kg"], float, "vehicle mass (thrust in newtons is for it)", "kg", lo=0.05, hi=100.0),
)


@dataclass
class _Pending:
    """The newest sample not answered yet; ``waiting_since_s``: arrival of the oldest unanswered one."""

    state: StateMsg
    meas: StateMeasurement
    waiting_since_s: float


class ControllerCore:
    """The pure step object. Feed :meth:`on_state`, :meth:`on_estimate` and :meth:`check_stale`;
    each returns the (setpoint, reference) pairs to publish (zero or one) plus events."""

    def __init__(self, config: ControllerConfig, *, clock: Callable[[], float]) -> None:
        config = resolved(config)
        self.config = config
        self.clock = clock
        self.position = PositionController(config.control)
        self.mission = Mission(config.missions)
        self.local = NeuralESO(NeuralEsoConfig(eso=EsoConfig(omega_o_rps=config.omega_o_rps, dt_s=config.control.dt_s),
                                               pathway="eso"))
        self.using_local = False
        self.events: list[tuple[str, str]] = []
        self._estimates: dict[int, EstimateMsg] = {}
        self._pending: _Pending | None = None
        self._last_seq = -1
        self._last_stepped = -1
        self._applied = self.position.hover_output().applied
        self._pending_command: tuple[str, dict] | None = None
        self._pending_local = np.zeros(3)
        self._last_output: list = []
        self.armed = config.mission != "idle"
        self.network_certificate: dict = {}  # the estimator's latest NetworkMsg.certificate
        self.fallbacks = 0  # times the local ESO took over
        self.rate_check = RateCheck("controller", config.control.dt_s)
        self._newest_estimate: tuple[int, float] | None = None  # (seq, arrival) of the newest estimate

    # -- the certificate ------------------------------------------------------------------
    def on_network(self, msg: NetworkMsg) -> None:
        self.network_certificate = dict(msg.certificate)

    def _certificate_inputs(self) -> tuple[NetworkSlopes, float] | None:
        """(the flown network's slopes, ω_o) from the estimator's latest report, or None."""
        c = self.network_certificate
        omega = c.get("omega_o")
        try:
            slopes = NetworkSlopes.from_dict(c["slopes"])
        except (KeyError, TypeError, ValueError):
            return None
        return (slopes, float(omega)) if isinstance(omega, (int, float)) and omega > 0 else None

    def _gain_certificate(self, values: dict):
        inputs = self._certificate_inputs()
        if inputs is None:
            return None
        control = replace(self.config.control, vehicle=replace(self.config.control.vehicle,
                                                               mass_kg=float(values.get("mass_kg", self.config.mass_kg))))
        return flight_certificate(inputs[0], kp=float(values["kp_z"]), kd=float(values["kd_z"]), omega_o=inputs[1],
                                  plant=LoopPlant.of(control))

    def prepare_gains(self, values: dict) -> None:
        """Compute (and cache) the certificate for the proposed z gains and mass, outside any lock."""
        self._gain_certificate(values)

    def check_gains(self, values: dict) -> Refusal | None:
        """Refuse (overridably) z gains or a vehicle mass under which the network flown is not certified."""
        kp, kd = float(values["kp_z"]), float(values["kd_z"])
        mass = float(values.get("mass_kg", self.config.mass_kg))
        if (kp, kd, mass) == (self.config.control.kp[2], self.config.control.kd[2], self.config.mass_kg):
            return None
        cert = self._gain_certificate(values)
        if cert is None:
            return Refusal("certificate unknown (no network report from the estimator yet)", overridable=True)
        return None if cert.holds else Refusal(cert.text(), overridable=True)

    # -- operator inputs (applied at the next sample) ---------------------------------------
    def command(self, name: str, args: dict) -> tuple[bool, str]:
        if name not in ALL_COMMANDS:
            return False, f"unknown mission command {name!r}; choose one of {list(ALL_COMMANDS)}"
        if name == "arm":
            self.armed = True
            return True, "armed: take-off allowed"
        if name == "disarm":
            if not self.mission.idle:
                return False, f"disarm only on the ground (segment {self.mission.segment})"
            self.armed = False
            return True, "disarmed"
        if name in ("hold", "abort") and self.mission.idle:
            return False, f"on the ground (idle), nothing to {name}"
        if name in _NEEDS_ARMING and not self.armed:
            return False, f"{name} needs the vehicle armed (send arm first)"
        at_t_s = args.get("at_t_s")
        if at_t_s is not None and not isinstance(at_t_s, (int, float)):
            return False, f"at_t_s must be the world time in s at which {name} starts, not {at_t_s!r}"
        cycles = args.get("cycles")
        if cycles is not None and (name != "lemniscate" or not isinstance(cycles, int) or isinstance(cycles, bool)
                                   or not 1 <= cycles <= MAX_LEMNISCATE_CYCLES):
            return False, f"cycles is the lemniscate's, a whole number 1-{MAX_LEMNISCATE_CYCLES}, not {cycles!r} for {name}"
        self._pending_command = (name, dict(args))
        if at_t_s is not None:  # a start on the world's clock, whatever the command's latency (paired runs)
            return True, f"{name} starts at the first sample at or after world t = {at_t_s:.2f} s"
        return True, f"{name} starts at the next sample"

    def apply_gains(self, values: dict) -> None:
        control = replace(self.config.control, kp=(values["kp_xy"], values["kp_xy"], values["kp_z"]),
                          kd=(values["kd_xy"], values["kd_xy"], values["kd_z"]),
                          vehicle=replace(self.config.control.vehicle,
                                          mass_kg=values.get("mass_kg", self.config.mass_kg)))
        force = self.position.force_prev_enu_n.copy()
        self.config = replace(self.config, control=control, mass_kg=control.vehicle.mass_kg)
        self.position = PositionController(control)
        self.position.reset(force)  # keep the rate limiter's memory: no step at the change

    # -- samples ------------------------------------------------------------------------
    def on_state(self, state: StateMsg, now_s: float) -> list[tuple[SetpointMsg, ReferenceMsg | None]]:
        if state.seq == self._last_seq:  # a re-sent sample (lockstep: the world had no setpoint for it in time)
            # answered: answer again. Still waiting for its estimate: send the setpoint before it again, which a
            # lockstep estimator waits for and may have lost (the source's re-send heals a loss on every edge)
            return self._last_output if self._last_stepped in (state.seq, state.seq - 1) else []
        if 0 < state.seq < self._last_seq:
            return []  # late
        meas = state_measurement(state)
        if self._last_seq < 0 or state.seq < self._last_seq:
            self._begin_flight(state, meas)
        self._last_seq = state.seq
        wrong_rate = self.rate_check.observe(state.seq, state.t_s)
        if wrong_rate:
            self.events.append(wrong_rate)
        local = self.local.update(meas, self._applied)
        waiting_since = self._pending.waiting_since_s if self._pending is not None else now_s
        self._pending = _Pending(state, meas, waiting_since)
        self._pending_local = local.f_hat
        if self.using_local:
            return self._step(local_f_hat=True, now_s=now_s)
        if state.seq in self._estimates:
            return self._step(local_f_hat=False, now_s=now_s)
        if 0 < self.config.stale_samples < state.seq - self._last_stepped and self._last_stepped >= 0:
            return self.check_stale(now_s, unanswered=state.seq - self._last_stepped - 1)
        return []


    def on_estimate(self, est: EstimateMsg, now_s: float) -> list[tuple[SetpointMsg, ReferenceMsg | None]]:
        if self._newest_estimate is None or est.seq >= self._newest_estimate[0]:
            self._newest_estimate = (est.seq, now_s)
        if est.seq < self._last_stepped:
            return []
        self._estimates[est.seq] = est
        forget_older(self._estimates, est.seq)
        if self.using_local and est.warm_ticks >= self.config.warmup_ticks:
            self.using_local = False
            self.events.append(("info", f"estimator back (warm for {est.warm_ticks} samples): flying on its f̂ again"))
            return []
        p = self._pending
        if not self.using_local and p is not None and p.state.seq == est.seq:
            return self._step(local_f_hat=False, now_s=now_s)
        return []

    def check_stale(self, now_s: float, unanswered: int = 0) -> list[tuple[SetpointMsg, ReferenceMsg | None]]:
        """Watchdog: no sample answered for ``stale_timeout_s`` (or ``unanswered`` samples before
        the newest, see ``stale_samples``) → the local ESO flies the newest."""
        p = self._pending
        if self.using_local or p is None or (not unanswered and now_s - p.waiting_since_s < self.config.stale_timeout_s):
            return []
        self.using_local = True
        self.fallbacks += 1
        why = f"{unanswered} samples" if unanswered else f"{self.config.stale_timeout_s * 1e3:.0f} ms"
        newest = (f"the estimator's newest answer was for sample {self._newest_estimate[0]}, "
                  f"{(now_s - self._newest_estimate[1]) * 1e3:.0f} ms ago" if self._newest_estimate else
                  "no estimate arrived yet")
        self.events.append(("warning", f"no estimate for sample {p.state.seq} and the ones before it within "
                                       f"{why}: flying on the local ESO ({newest})"))
        return self._step(local_f_hat=True, now_s=now_s)

    # -- internals ----------------------------------------------------------------------
    def _begin_flight(self, state: StateMsg, meas: StateMeasurement) -> None:
        self.position = PositionController(self.config.control)
        self._applied = self.position.hover_output(meas.yaw_rad).applied
        self.local.reset(meas, self._applied.thrust_n)
        self._estimates.clear()
        self._last_stepped = -1
        self._last_output = []  # a re-sent sample of this flight is never answered with the last one's setpoint
        self._newest_estimate = None  # a new flight's samples count from 0 again
        self.mission = Mission(self.config.missions)
        name = self.config.mission
        if name != "idle":
            if state.seq == 0:
                self.mission.start(name, 0.0, meas.pos_enu_m)  # a flight starts at the source's t = 0
            else:
                self.mission.start("hover", state.t_s, meas.pos_enu_m)
                self.events.append(("info", f"joined a flight at sample {state.seq}: holding position"))

    def _step(self, *, local_f_hat: bool, now_s: float) -> list[tuple[SetpointMsg, ReferenceMsg | None]]:
        p = self._pending
        self._pending = None
        if p.state.seq <= self._last_stepped:
            return []
        at_t_s = self._pending_command[1].get("at_t_s") if self._pending_command is not None else None
        if self._pending_command is not None and (at_t_s is None or p.state.t_s >= at_t_s - 1e-9):
            name, args = self._pending_command
            self._pending_command = None
            if name == "hold":
                self.mission.hold(p.state.t_s, p.meas.pos_enu_m)
            elif name == "abort":
                if self.mission.abort(p.state.t_s, p.meas.pos_enu_m):
                    self.events.append(("warning", "abort: landing now"))
            else:
                self.mission.start(name, p.state.t_s, p.meas.pos_enu_m, cycles=args.get("cycles"))
        used = None if local_f_hat else self._estimates[p.state.seq]
        f_hat = self._pending_local if used is None else used.f_hat_mps2  # the step takes any 3 floats
        ref = self.mission.reference(p.state.t_s)
        if ref is not None and self.mission.landed(p.meas.pos_enu_m[2], p.state.t_s):
            ref = None
            self.events.append(("info", "landed: motors idle"))
        if ref is None:
            setpoint = AttitudeSetpoint(0.0, 0.0, p.meas.yaw_rad, 0.0, 0.0)
            self.position.reset(np.zeros(3))
            self._applied = AppliedControl(acc_cmd_enu_mps2=np.array([0.0, 0.0, -self.config.control.vehicle.gravity_mps2]),
                                           thrust_n=0.0)
            reference = None
        else:
            out = self.position.step(p.meas, ref, f_hat)
            setpoint, self._applied = out.setpoint, out.applied
            reference = ReferenceMsg(seq=p.state.seq, stamp_s=now_s, t_s=p.state.t_s, pos_enu_m=vec(ref.pos_enu_m),
                                     vel_enu_mps=vec(ref.vel_enu_mps), acc_enu_mps2=vec(ref.acc_enu_mps2),
                                     yaw_rad=ref.yaw_rad, segment=self.mission.segment)
        self._last_stepped = p.state.seq
        msg = SetpointMsg(seq=p.state.seq, stamp_s=self.clock(), state_stamp_s=p.state.stamp_s, t_s=p.state.t_s,
                          roll_rad=setpoint.roll_rad, pitch_rad=setpoint.pitch_rad, yaw_rad=setpoint.yaw_rad,
                          thrust_norm=setpoint.thrust_norm, thrust_n=setpoint.thrust_n,
                          acc_cmd_enu_mps2=vec(self._applied.acc_cmd_enu_mps2),
                          estimate_source="local_eso" if local_f_hat else "estimator",
                          estimate_stamp_s=0.0 if used is None else used.stamp_s)
        self._last_output = [(msg, reference)]
        return self._last_output
