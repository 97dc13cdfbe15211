"""``neso experiment paper --world px4``: the paper's experiments flown by real PX4 v1.16.0 SITL.

Each flight is one fresh PX4 SITL boot (its own instance's ports, its own working folder) with the world of the
experiment's scenario as its simulator (``sim.px4_hil``: lockstep, PX4's EKF2, attitude and rate control and
control allocation drive the rotors), driven from this process at the wall clock's 50 Hz (MAVSDK offboard needs
real time): the world's motion capture goes to EKF2 as external vision and each of the controller's setpoints
to PX4's offboard attitude exactly as the px4_gateway does it (its :class:`GatewayCore` and ODOMETRY form),
real MAVSDK over UDP. A flight: boot, offboard, arm (PX4's own checks), the controller's take-off (PD+ESO) to
the trajectory's start, ``hover_before_s`` of hover, then :func:`sim.runner.fly` with the method's estimator and
the networks the built-in pipeline trained (the same recipe), scored by the same metrics
(:mod:`sim.experiments`). TDR retrains on a neural_eso lemniscate flown in this world, as the built-in world's
TDR does in its own. A method with the suffix ``_tuned`` flies at the z gains and observer bandwidth the built-in
world's search found for its kind of flight (:mod:`sim.tuning`; x and y as the gain set flown), with the networks the
built-in pipeline trained for them; ``neural_eso_tdr_tuned`` retrains on a lemniscate flown here at those gains.
The gains are tuned in the built-in world, not in PX4's (a PX4 flight takes a minute of wall clock).

Measured besides: rotor saturation (airborne sensor periods with a PX4 motor output within 1 % of 0 or 1,
:class:`sim.px4_hil.AutopilotInTheLoop`) during each experiment flight, and per flight the time to arm and the
hover thrust the gateway learnt.
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, replace

from neso.control import GAIN_SETS, ControlConfig, PositionController
from neso.methods import build_estimator
from neso.metrics import summarise
from neso.types import AttitudeSetpoint

PX4_EXPERIMENTS = ("nominal_landing", "ood_slope", "lemniscate_near_ground")


@dataclass(frozen=True)
class Px4PaperConfig:
    """What the PX4 world flies. ``methods``: None for every method of each experiment (as the built-in world),
    else only those; ``gains``: the :data:`GAIN_SETS` flown side by side, the first reported at the top level."""

    trials: int = 1
    experiments: tuple[str, ...] = PX4_EXPERIMENTS
    methods: tuple[str, ...] | None = None
    gains: tuple[str, ...] = ("paper",)
    hover_before_s: float = 3.0
    arm_timeout_s: float = 120.0


class Px4FlightError(RuntimeError):
    """A PX4 flight that could not start (PX4 never armed, never connected)."""


_CLAIMED: dict[int, object] = {}  # instance → its lock file, open (and locked) while this process flies it


def free_px4_instance() -> int:
    """A PX4 SITL instance (0–9) for this process: one whose lock file (``neso-px4-instance-<i>.lock`` in the temporary
    folder) no other process holds and whose ports are free here. This process holds the lock until
    :func:`release_px4_instance` or its end: between choosing an instance and PX4 binding its ports, another flight
    on this machine (a parallel test, a benchmark) would otherwise take the same one."""
    import fcntl

    for instance in range(10):
        if instance in _CLAIMED:
            continue
        lock = open(os.path.join(tempfile.gettempdir(), f"neso-px4-instance-{instance}.lock"), "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
                tcp.bind(("127.0.0.1", 4560 + instance))
            for port in (14540, 14580, 18570):
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                    udp.bind(("127.0.0.1", port + instance))
        except OSError:  # held by another process (BlockingIOError), or a port taken
            lock.close()
            continue
        _CLAIMED[instance] = lock
        return instance
    raise Px4FlightError("no free PX4 SITL instance (ports 4560/14540/14580/18570 + 0–9 all taken)")


def release_px4_instance(instance: int) -> None:
    """Let another process fly ``instance`` (its PX4 has stopped)."""
    lock = _CLAIMED.pop(instance, None)
    if lock is not None:
        lock.close()


def _die_with_parent() -> None:
    """In the PX4 child before exec: SIGTERM when this process ends, however it ends (Linux prctl
    PR_SET_PDEATHSIG), so no PX4 outlives an interrupted experiment."""
    import ctypes

    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)


class Px4Vehicle:
    """One PX4 SITL boot flying one world, as a plant for :func:`sim.runner.fly`: ``reset`` (after
    :meth:`prepare` has taken off and hovers at the trajectory's start) starts the experiment's clock and
    counters, ``step`` sends the setpoint to PX4, waits for the period's wall-clock end, steps the world (PX4 in
    lockstep) and forwards the motion capture. ``truth`` and the measurement carry the experiment's time."""

    def __init__(self, sim_config, *, seed: int) -> None:
        from services.px4_gateway import GatewayConfig, Px4Link
        from sim.px4_hil import AutopilotInTheLoop, HilSensors
        from sim.px4_link import Px4SimLink
        from sim.px4_sitl import OFFBOARD_UDP_PORT, SIM_TCP_PORT, sitl_command
        from sim.quadrotor import QuadrotorSim

        self.instance = free_px4_instance()
        try:
            self.link = Px4SimLink(SIM_TCP_PORT + self.instance)
        except OSError as exc:  # taken between the probe and here (another flight on this machine)
            raise Px4FlightError(f"PX4 instance {self.instance}'s simulator port: {exc}") from None
        self.workdir = tempfile.mkdtemp(prefix=f"neso-px4-paper-{self.instance}-")
        self.world = AutopilotInTheLoop(QuadrotorSim(sim_config, seed=seed), self.link.exchange, HilSensors(seed=seed))
        argv, env = sitl_command(self.instance)
        self._px4_out = open(os.path.join(self.workdir, "px4.log"), "wb")
        self.proc = subprocess.Popen(argv, cwd=self.workdir, env=env, stdout=self._px4_out, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True, preexec_fn=_die_with_parent)
        # the gateway's own mapping (hover thrust learnt online) and external-vision form, without its bus
        self.gateway = Px4Link(None, GatewayConfig(mavlink=f"udpin://0.0.0.0:{OFFBOARD_UDP_PORT + self.instance}",
                                                   forward_sources=()))
        self.texts: list[str] = []
        self.mode = "UNKNOWN"
        self.armed = False
        self.problem = ""  # the bring-up failed (ends the flight)
        self.refused = ""  # PX4's newest refusal of offboard or arm (retried)
        self.autopilot = ""  # the firmware's version as PX4 reports it once armed ("PX4 v1.16.0 6ea3539")
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._next_s = time.monotonic()
        self.t0_s = 0.0
        self.late_periods = 0  # periods that started more than a period late (the clock restarted)
        self.not_offboard_periods = 0  # experiment periods PX4 spent armed in a mode other than offboard
        self._mavsdk = None
        self._bringup = threading.Thread(target=self._bring_up, name="px4-bring-up", daemon=True)
        self._bringup.start()

    # -- the plant interface of sim.runner.fly ------------------------------------------------
    def __getattr__(self, name: str):
        return getattr(self.world, name)

    @property
    def truth(self):
        return replace(self.world.truth, t_s=self.world.truth.t_s - self.t0_s)

    def reset(self, *, pos_enu_m, yaw_rad: float = 0.0):
        """The experiment starts here (the vehicle already hovers at ``pos_enu_m``): time 0, counters 0."""
        self.t0_s = self.world.sim.t_s
        self.world.airborne = self.world.saturated = 0
        self.late_periods = self.not_offboard_periods = 0
        return None

    def step(self, setpoint: AttitudeSetpoint):
        meas = self._advance(setpoint)
        self.not_offboard_periods += self.mode != "OFFBOARD"
        return replace(meas, t_s=meas.t_s - self.t0_s)

    # -- before the experiment ------------------------------------------------------------------
    def prepare(self, ref0, control: ControlConfig, estimator_config, hover_before_s: float,
                arm_timeout_s: float) -> dict:
        """Boot, offboard, arm, take off with PD+ESO to ``ref0`` (the trajectory's start) and hover there
        ``hover_before_s``. Figures of the bring-up back; :class:`Px4FlightError` when PX4 never arms."""
        from flight.mission import Mission, MissionConfig

        x0, y0, z0 = (float(v) for v in ref0.pos_enu_m)
        self.world.sim.reset(pos_enu_m=(x0, y0, -1.0), yaw_rad=ref0.yaw_rad)  # on the ground
        started = time.monotonic()
        idle = AttitudeSetpoint(0.0, 0.0, ref0.yaw_rad, 0.0, 0.0)
        sp = idle
        while not self.armed:
            if self.problem or time.monotonic() - started > arm_timeout_s:
                raise Px4FlightError(f"PX4 did not arm within {arm_timeout_s:.0f} s: {self.problem or 'timeout'}; "
                                     f"last refusal {self.refused!r}; PX4 said {self.texts[-3:]}")
            self._advance(sp)
        armed_after_s = time.monotonic() - started
        mission = Mission(MissionConfig(origin_xy_m=(x0, y0), takeoff_height_m=z0))
        controller = PositionController(control)
        estimator = build_estimator("pd_eso", estimator_config, {})
        meas = self._advance(idle)
        mission.start("takeoff", meas.t_s, meas.pos_enu_m, from_position=True)
        estimator.reset(meas, 0.0)
        out = controller.hover_output(ref0.yaw_rad)
        hover_since = None
        while hover_since is None or meas.t_s - hover_since < hover_before_s:
            ref = mission.reference(meas.t_s)
            if mission.segment == "hover" and hover_since is None:
                hover_since = meas.t_s
            est = estimator.update(meas, out.applied)
            out = controller.step(meas, replace(ref, yaw_rad=ref0.yaw_rad), est.f_hat)
            meas = self._advance(out.setpoint)
            if self.world.sim.crashed or self.world.sim.diverged or self.mode not in ("OFFBOARD", "UNKNOWN"):
                raise Px4FlightError(f"take-off failed (crashed {self.world.sim.crashed}, PX4 mode {self.mode}); "
                                     f"PX4 said {self.texts[-3:]}")
        return {"armed_after_s": round(armed_after_s, 2), "airborne_at_start_s": round(self.world.sim.t_s, 2)}

    def close(self) -> dict:
        """Stop PX4 and the link; what PX4 said and the link's counts back."""
        self._stop.set()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5.0)
        self._bringup.join(5.0)
        with self._lock:
            self.gateway.offboard = self.gateway.direct = None
        if self._mavsdk is not None:
            self._mavsdk.destroy()
        self.link.close()
        self._px4_out.close()
        shutil.rmtree(self.workdir, ignore_errors=True)
        release_px4_instance(self.instance)
        return {"instance": self.instance, "exchanges": self.world.exchanges, "unanswered": self.world.unanswered,
                "link_dropped": self.link.dropped, "link_stalls": self.link.stalls,
                "hover_thrust_learnt": round(self.gateway.core.hover_thrust_norm, 4), "late_periods": self.late_periods,
                "not_offboard_periods": self.not_offboard_periods, "px4_said": self.texts[-5:],
                "autopilot": self.autopilot}

    # -- internals ------------------------------------------------------------------------------
    def _advance(self, setpoint: AttitudeSetpoint):
        """One control period on the wall clock: the setpoint to PX4 now, the world stepped at the period's end
        (PX4 runs its period in lockstep), the motion capture to EKF2."""
        with self._lock:
            now = time.monotonic()
            att = self.gateway.core.on_setpoint(setpoint, now)
            if att is not None and self.gateway.offboard is not None:
                from mavsdk.plugins.offboard import Attitude

                self.gateway.last_attitude = Attitude(att.roll_deg, att.pitch_deg, att.yaw_deg, att.thrust_norm)
                self.gateway.offboard.set_attitude(self.gateway.last_attitude)
        period = self.world.sim.config.control_period_s
        self._next_s += period
        wait = self._next_s - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        elif wait < -period:  # more than a period late: start the clock again from now
            self.late_periods += 1
            self._next_s = time.monotonic()
        meas = self.world.step(setpoint)
        with self._lock:
            now = time.monotonic()
            self.gateway.core.on_state(meas, now, offboard=self.mode == "OFFBOARD")
            if self.gateway.direct is not None:  # the world's measurement, captured as it is handed over
                self.gateway._forward_pose(meas, now)
        return meas

    def _bring_up(self) -> None:
        """Blocking MAVSDK calls, off the world's loop (PX4 in lockstep answers only while the world steps):
        connect, then offboard and arm, retried every second until PX4 accepts (it refuses until EKF2 has
        settled on the motion capture)."""
        from mavsdk import ComponentType, Configuration, Mavsdk, log_subscribe
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry

        log_subscribe(lambda level, message, file, line: level < 2)  # MAVSDK's debug and info lines: not printed
        try:
            self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
            self._mavsdk.add_any_connection(self.gateway.config.mavlink)
            system = None
            while system is None and not self._stop.is_set():
                system = self._mavsdk.first_autopilot(timeout_s=0.5)
            if system is None:
                return
            tele = Telemetry(system)
            tele.subscribe_flight_mode(lambda v, _: setattr(self, "mode", v.name))
            tele.subscribe_status_text(lambda v, _: self.texts.append(f"{v.type.name}: {v.text.strip()}"))
            action, offboard = Action(system), Offboard(system)
            with self._lock:
                self.gateway.direct, self.gateway.offboard = MavlinkDirect(system), offboard
                self.gateway.system_id = system.get_system_id()
            for what in ("offboard", "arm"):
                while not self._stop.is_set():
                    try:
                        if what == "offboard":
                            with self._lock:
                                if self.gateway.last_attitude is not None:
                                    offboard.set_attitude(self.gateway.last_attitude)
                            offboard.start()
                        else:
                            action.arm()
                        break
                    except Exception as exc:  # MAVSDK's OffboardError/ActionError: PX4 refused; it is retried
                        self.refused = f"{what}: {exc}"
                        self._stop.wait(1.0)
            if not self._stop.is_set():
                from services.px4_gateway import autopilot_version

                self.autopilot = autopilot_version(system)[0] or "unknown"
            self.armed = not self._stop.is_set()
        except Exception as exc:  # the bring-up thread's failure ends the flight with its reason
            self.problem = f"{type(exc).__name__}: {exc}"


# -- the experiments ---------------------------------------------------------------------------------
@dataclass
class Px4Flight:
    log: object  # sim.runner.FlightLog or None (PX4 never flew it)
    info: dict


def fly_px4(scenario: str, method: str, networks: dict, trajectory, seed: int, paper, control: ControlConfig,
            px4: Px4PaperConfig, log=print, tuned=None) -> Px4Flight:
    """One experiment flight in the PX4 world (a fresh PX4 boot); the bring-up's failure is reported, not raised.
    ``control``: the gain set flown (x, y); the z gains and ω_o are the method's (:func:`sim.experiments.method_gains`,
    ``tuned`` the built-in world's :class:`sim.tuning.TuningResult`)."""
    from sim.experiments import disturbance_z_std_mps2, method_gains
    from sim.runner import fly
    from sim.scenarios import make_scenario

    name, gains = method_gains(method, scenario, paper, tuned)
    control, estimator_config = gains.control(control), gains.estimator(control.dt_s)

    started = time.monotonic()
    vehicle = Px4Vehicle(make_scenario(scenario, **dict(paper.sim_overrides)), seed=seed)
    info: dict = {"scenario": scenario, "method": method, "seed": seed}
    flight = None
    try:
        info.update(vehicle.prepare(trajectory.sample(0.0), control, estimator_config, px4.hover_before_s,
                                    px4.arm_timeout_s))
        info["gains"] = gains.to_dict()
        estimator = build_estimator(name, estimator_config, networks)
        flight = fly(plant=vehicle, estimator=estimator, trajectory=trajectory, seed=seed, control=control)
        airborne, saturated = vehicle.world.airborne, vehicle.world.saturated
        info.update(disturbance_z_std_mps2=disturbance_z_std_mps2(flight, paper, scenario),
                    airborne_exchanges=airborne, saturated_exchanges=saturated,
                    saturated_percent=round(100.0 * saturated / airborne, 2) if airborne else None,
                    diverged=flight.diverged, reason=flight.reason)
    except Px4FlightError as exc:
        info["failed"] = str(exc)
    finally:
        info.update(vehicle.close())
        info["wall_s"] = round(time.monotonic() - started, 1)
    what = info.get("failed") or (f"sat {info['saturated_percent']} %" + (f", {flight.reason}" if flight.diverged else ""))
    log(f"  PX4 {scenario} {method} seed {seed}: {what} ({info['wall_s']} s)")
    return Px4Flight(flight, info)


def run_px4_paper(builtin_run, paper, px4: Px4PaperConfig, *, log=print) -> dict:
    """Every experiment of :data:`PX4_EXPERIMENTS` (or ``px4.experiments``) for every method, per gain set, with
    the first recipe's networks of ``builtin_run`` (a :class:`sim.experiments.PaperRun`); TDR retrains on a
    lemniscate flown here. Per gain set: the documented shape (``experiments``), ``saturation_percent`` and
    ``disturbance_z_std_mps2`` (experiment → method → summary over trials) and ``flights`` (every flight's
    bring-up and link figures)."""
    from neso.learning import RECIPES
    from sim.experiments import LANDING_METHODS, LEMNISCATE_METHODS, tdr_network
    from sim.flights import landing_metrics, lemniscate_rmse_cm
    from sim.tuning import SCENARIO_KIND, TUNED

    recipe_name = next(iter(builtin_run.by_recipe))
    flown = builtin_run.by_recipe[recipe_name]["flown"]
    base = {"base": flown["base"], "acceleration": flown["acceleration"]}
    flown_tuned = builtin_run.by_recipe[recipe_name]["flown_tuned"]
    tuned = builtin_run.tuned
    lag = builtin_run.lag
    seeds = [paper.seed * 1000 + 1 + i for i in range(px4.trials)]
    variants = {}
    for gains in px4.gains:
        kp, kd = GAIN_SETS[gains]
        control = replace(paper.control, kp=kp, kd=kd)
        log(f"PX4 world, gains {gains} (kp {kp}, kd {kd}), recipe {recipe_name}, {px4.trials} trial(s)")
        results, saturation, disturbance, flights = {}, {}, {}, []

        def run(scenario, methods, trajectory, networks):
            per = {}
            for m in methods:
                nets = networks[TUNED] if m.endswith(TUNED) else networks[""]
                per[m] = [fly_px4(scenario, m, nets, trajectory, s, paper, control, px4, log, tuned) for s in seeds]
                flights.extend(f.info for f in per[m])
            saturation[scenario] = {m: summarise([f.info.get("saturated_percent") for f in fl]) for m, fl in per.items()}
            disturbance[scenario] = {m: summarise([f.info.get("disturbance_z_std_mps2") for f in fl])
                                     for m, fl in per.items()}
            return per

        wanted = (lambda ms: tuple(m for m in ms if px4.methods is None or m in px4.methods))
        for scenario in px4.experiments:
            if scenario in ("nominal_landing", "ood_slope"):
                per = run(scenario, wanted(LANDING_METHODS), paper.landing, {"": base, TUNED: flown_tuned["landing"]})
                results[scenario] = {"metric": "steady_state_abs_z_error_cm", "methods": {
                    m: summarise([landing_metrics(f.log, paper)[0] if f.log is not None else None for f in fl])
                    for m, fl in per.items()}}
                continue
            methods = wanted(LEMNISCATE_METHODS)
            networks = {"": dict(base), TUNED: {"base": flown_tuned["lemniscate"]["base"]}}
            for suffix in ("", TUNED):
                if f"neural_eso_tdr{suffix}" not in methods:
                    continue
                tdr_traj = replace(paper.lemniscate, cycles=paper.tdr_cycles)
                start = networks[suffix]
                data = fly_px4(scenario, f"neural_eso{suffix}", start, tdr_traj, paper.seed * 1000 + 900, paper,
                               control, px4, log, tuned)
                flights.append(dict(data.info, purpose=f"tdr_data{suffix}"))
                if data.log is None or data.log.diverged:
                    raise Px4FlightError(f"the TDR data flight in the PX4 world failed: {data.info}")
                bound = paper.base_bound(RECIPES[recipe_name], tuned.gains[SCENARIO_KIND[scenario]]) if suffix else None
                networks[suffix]["tdr"] = tdr_network(data.log, RECIPES[recipe_name], paper, start, lag, tdr_traj,
                                                      bound=bound).network
            per = run(scenario, methods, paper.lemniscate, networks)
            results[scenario] = {"metric": "z_rmse_cm", "methods": {
                m: summarise([lemniscate_rmse_cm(f.log, paper) if f.log is not None else None for f in fl])
                for m, fl in per.items()}}
        variants[gains] = {"kp": list(kp), "kd": list(kd), "experiments": results, "saturation_percent": saturation,
                           "disturbance_z_std_mps2": disturbance, "flights": flights}
    return variants
