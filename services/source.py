"""``source`` on the bus: the thin adapter around :class:`flight.source.SimSource` and
:class:`flight.source.MocapSource` (what each does is documented in :mod:`flight.source`); the motion-capture
paths are in :mod:`services.mocap_source`.

Real time: one sample every period on the wall clock, the newest setpoint acts; the clock starts once the
controller has answered sample 0 (re-sent every ``first_answer_resend_s``, at most ``first_answer_wait_s``); lockstep:
sample k+1 once setpoint k has arrived (``lockstep_pace``: and not sooner than period / pace after sample k). Command
``scenario`` restarts the world as a new flight (lockstep too: its sample 0 waits for its setpoint like any other).
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from dataclasses import replace

from flight.deadline import DeadlineWatch
from flight.source import SimSource, SourceConfig, frame_matrix
from runtime.options import add_options, config_from_options
from runtime.pacing import next_wait
from runtime.schema import SetpointMsg, StateMsg
from runtime.stall import StallWatch


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, SourceConfig)


def config_from_args(args) -> SourceConfig:
    return config_from_options(SourceConfig, args, lockstep=getattr(args, "lockstep", False))


def run(args, bus) -> int:
    from runtime.node import Node, run_node

    config = config_from_args(args)
    if config.lockstep_pace < 0:
        raise SystemExit(f"source: --lockstep-pace {config.lockstep_pace:g}: a multiple of real time ≥ 0")

    def node(description: dict[str, str]):
        return Node("source", vehicle=args.vehicle, bus=bus, config=config, params=description_params(description))

    if config.backend == "mocap":
        from services.mocap_source import natnet_description, natnet_offer, run_mocap

        frame_matrix(config.mocap.frame)  # refused before joining the bus, as are a server that does not answer
        offer = natnet_offer(config.mocap) if config.mocap.type == "optitrack" else None  # and a wrong rigid body
        description = (natnet_description(offer, config.mocap.rigid_body) if offer is not None else
                       {"kind": config.mocap.type, "server": config.mocap.hostname, "rigid_body": config.mocap.rigid_body})
        return run_node(node(description), lambda n: run_mocap(n, config, offer=offer))
    if config.mocap_stream == "natnet":
        problem = natnet_refusal(config)  # refused before joining the bus: one line, exit 2
        if problem:
            print(f"source: {problem}", file=sys.stderr, flush=True)
            raise SystemExit(2)
        from services.mocap_source import natnet_description, natnet_offer, run_sim_natnet, start_world, world_mocap

        world = start_world(config)
        offer = natnet_offer(world_mocap(config, world[2]))
        description = natnet_description(offer, config.mocap.rigid_body, scenario=config.scenario, link=config.link,
                                         world="simulated (sim/natnet_server.py)")
        return run_node(node(description), lambda n: run_sim_natnet(n, config, world, offer))
    description = {"kind": "sim", "scenario": config.scenario, "link": config.link}
    if config.link == "mavlink":
        if config.lockstep:
            raise SystemExit("source: --link mavlink runs in real time only (MAVSDK streams on its own clock)")
        return run_node(node(description), lambda n: _run_sim_mavlink(n, config))
    if config.link == "px4":
        if config.lockstep:
            raise SystemExit("source: --link px4 runs in real time only (PX4 and MAVSDK keep wall-clock timeouts)")
        from services.px4_world import px4_in_the_loop

        return run_node(node(description),
                        lambda n: _run_sim(n, config, world=lambda sim: px4_in_the_loop(n, config, sim)))
    return run_node(node(description), lambda n: _run_sim(n, config))


def description_params(description: dict[str, str]):
    """Where the states come from, as the source's read-only parameters (``neso params get source``; the recorder
    keeps them with every flight): each a text parameter whose only allowed value is its own."""
    from runtime.params import Param, ParamSet

    specs = tuple(Param(k, str(v), str, "where the states come from (read only)", choices=(str(v),))
                  for k, v in description.items())
    return ParamSet(specs, check=lambda _: "the source's description is read only")


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
        if world is not None:
            return False, "a PX4 flight cannot switch scenario (PX4 would not follow the world's restart; restart it)"
        next_scenario[:] = [wanted]
        return True, f"world restarts with {wanted} at the next period (a new flight from sample 0)"

    node.on_command(on_command)
    loop_alive = wait_for_loop(node, config.wait_for, required=config.lockstep)
    # a PX4 world runs on PX4's clock; a loop without a controller sends no setpoint to wait for
    first_answer = not config.lockstep and world is None and loop_alive and "controller" in config.wait_for
    n_total = int(round(config.duration_s * config.rate_hz)) if config.duration_s > 0 else None
    period = 1.0 / config.rate_hz
    if config.lockstep:  # a paced lockstep flight steps at most every period / pace of the wall clock
        period = period / config.lockstep_pace if config.lockstep_pace > 0 else 0.0
    next_tick = time.monotonic()
    stall = None if config.lockstep else StallWatch(config.stall_report_s)
    while not node.stopping and (n_total is None or core.seq + 1 < n_total):
        stood = stall.beat() if stall is not None else None
        if stood is not None:
            node.event("warning", f"the world stood still {stood[0]:.2f} s before sample {core.seq + 1} "
                                  f"(t={core.sim.t_s:.2f} s, load {os.getloadavg()[0]:.2f} on {os.cpu_count()} "
                                  f"cores): its loop was in {stood[1]}")
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
                if first_answer and state.seq == 0:
                    _await_first_answer(node, config, state, put_state, arrived, core)
                    next_tick = time.monotonic()  # the world's clock starts at the answer
                    if stall is not None:
                        stall.beat()  # that wait is not a stall
            else:  # the world's motion capture does not see it (command lose_tracking): no state
                node.stats.count("untracked_samples")
                if last_state and last_state[0].seq == state.seq - 1:
                    node.event("warning", f"the world's motion capture lost the vehicle at t={truth.t_s:.2f} s: "
                                          "no state until it is back")
        if period > 0:
            # lockstep: from this sample's stamp, so a late sample is never followed by one sooner than period (a
            # fixed grid would catch up, faster than the pace); real time: on the grid, catching up a late one
            next_tick = state.stamp_s + period if config.lockstep else next_tick + period
            delay, next_tick = next_wait(next_tick, period, time.monotonic())
            if delay > 0:
                node.wait(delay)
    if stall is not None:
        stall.close()
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
            delay, next_tick = next_wait(next_tick + period, period, time.monotonic())
            if delay > 0:
                node.wait(delay)
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


def _await_first_answer(node, config: SourceConfig, state: StateMsg, put_state, arrived: threading.Condition,
                        core: SimSource) -> None:
    """Real time, under the node lock: until sample 0's setpoint has come, re-sending it, at most
    ``first_answer_wait_s``. Without it, a first state the loop got late or not at all (a new route on the bus, a busy
    machine) went unanswered, and a controller whose first state was sample 1 took the flight as one it joined."""
    deadline = time.monotonic() + config.first_answer_wait_s
    sent = 1
    while core.setpoint_seq != state.seq and not node.stopping:
        left = deadline - time.monotonic()
        if left <= 0:
            node.event("warning", f"no setpoint for sample 0 within {config.first_answer_wait_s:g} s (sent {sent} "
                                  "times): the world's clock starts anyway")
            return
        if not arrived.wait(min(config.first_answer_resend_s, left)) and core.setpoint_seq != state.seq \
                and time.monotonic() < deadline:
            put_state(state)
            sent += 1
    if sent > 1:
        node.log(f"sample 0 answered after it was sent {sent} times")


def wait_for_loop(node, names: tuple[str, ...], *, required: bool, timeout_s: float | None = None) -> bool:
    """Until every service in ``names`` is alive on the bus, before the world's first sample: a world that started
    before its loop flew unanswered until the controller came up, which then took the flight as one it joined and held
    the vehicle where it had fallen to (6 cm below its hover, once the source started faster than the controller).
    ``required`` (lockstep): one still missing after ``timeout_s`` (default 60 s) is an error; in real time the world
    starts anyway after it (default 30 s), saying which are missing. True: every one is alive."""
    timeout_s = timeout_s if timeout_s is not None else 60.0 if required else 30.0
    deadline = time.monotonic() + timeout_s
    missing = list(names)
    while missing and not node.stopping:
        missing = [s for s in names if not list(node.session.liveliness().get(node.keys.alive(s), timeout=0.5))]
        if not missing:
            break
        if time.monotonic() > deadline:
            if required:
                raise TimeoutError(f"lockstep: {missing} not alive after {timeout_s:.0f} s")
            node.event("warning", f"{missing} not alive after {timeout_s:.0f} s: the world starts without them")
            return False
        node.wait(0.05)
    node.log(f"{'lockstep' if required else 'real time'}: {list(names)} alive, starting")
    return not missing


def natnet_refusal(config: SourceConfig) -> str:
    """Why ``--mocap-stream natnet`` cannot run with ``config`` (one line), or ""."""
    if config.lockstep or config.link == "px4":
        return "--mocap-stream natnet runs in real time with --link direct or mavlink only"
    try:
        config.natnet.lost_windows()
    except ValueError as exc:
        return str(exc)
    rate = config.natnet.rate_hz
    if rate and not (100 <= rate <= 360 and rate == int(rate)):
        return f"--natnet-rate {rate:g}: a whole number of Hz in 100-360 (0: the world's)"
    return ""
