"""``controller`` on the bus: the thin adapter around :class:`flight.controller.ControllerCore`
(what it does, its commands and its certificate check are documented there).

State and estimate samples go to the core with their arrival time; the (setpoint, reference) pairs it
returns are published; a watchdog thread asks it every third of ``stale_timeout_s`` whether the newest
sample waited too long (the local ESO then flies), except at a wake that came over two of its periods late: the
process had no CPU, and an estimate that came meanwhile is answered first (one wake only). Gain changes take effect
at the next sample.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

from flight.controller import CONTROLLER_PARAMS, ControllerConfig, ControllerCore, gain_values, resolved
from runtime.options import add_options, config_from_options
from runtime.params import ParamSet
from runtime.schema import EstimateMsg, StateMsg


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, ControllerConfig)


def config_from_args(args) -> ControllerConfig:
    config = config_from_options(ControllerConfig, args)
    dt = config.control.dt_s
    # at high rates a few periods are shorter than one scheduling hiccup of a 2-core VM: floor 20 ms
    lockstep = getattr(args, "lockstep", False)
    stale = config.lockstep_stale_s if lockstep else max(config.stale_periods * dt, 0.02)
    return replace(config, stale_timeout_s=stale, stale_samples=0 if lockstep else max(1, round(stale / dt)))


def run(args, bus) -> int:
    from runtime.node import Node, run_node
    from runtime.stall import LateWake

    config = config_from_args(args)
    core = ControllerCore(config, clock=time.monotonic)
    params = ParamSet(CONTROLLER_PARAMS, gain_values(resolved(config).control), check=core.check_gains,
                      prepare=core.prepare_gains)
    node = Node("controller", vehicle=args.vehicle, bus=bus, config=resolved(config), params=params)
    put_setpoint, put_reference = node.publisher("setpoint"), node.publisher("reference")

    def publish(outputs, received_s: float) -> None:
        node.stats.set_counter("local_eso_fallbacks", core.fallbacks)
        for setpoint, reference in outputs:
            put_setpoint(setpoint)
            node.stats.output(time.monotonic() - received_s)
            if reference is not None:
                put_reference(reference)
        while core.events:
            node.event(*core.events.pop(0))

    def tick_boundary(seq: int) -> None:
        changed = params.take_pending()
        if changed:
            core.apply_gains(params.effective())
            node.broadcast_params(seq, f"gains {changed} from sample {seq}")

    def on_state(msg: StateMsg, received_s: float) -> None:
        tick_boundary(msg.seq)
        publish(core.on_state(msg, received_s), received_s)

    def on_estimate(msg: EstimateMsg, received_s: float) -> None:
        publish(core.on_estimate(msg, received_s), received_s)

    node.subscribe("state", on_state)
    node.subscribe("estimate", on_estimate)
    node.subscribe("network", lambda msg, _received_s: core.on_network(msg))
    node.on_command(core.command)
    node.status_hook = lambda: ("flying on the LOCAL ESO (estimate stale)" if core.using_local else
                                f"ok, {'armed' if core.armed else 'disarmed'}, segment {core.mission.segment}")

    def watchdog(node: Node) -> None:
        period = max(config.stale_timeout_s / 3.0, 0.001)
        wakes = LateWake(period, time.monotonic())
        while not node.wait(period):
            if not wakes.may_judge(time.monotonic()):
                continue
            with node.lock:
                now = time.monotonic()
                publish(core.check_stale(now), now)

    return run_node(node, watchdog)
