"""``estimator`` on the bus: the thin adapter around :class:`flight.estimator.EstimatorCore`
(Neural-ESO with live pathway and Lipschitz bound, the certificate check and network hot swap are
documented there).

State, setpoint and reference samples go to the core; the estimates it returns are published.
``NetworkMsg`` on ``neso/<v>/network``: once a second and on every change. Commands on
``neso/<v>/cmd/estimator`` (``offer``, ``promote``, ``rollback``, ``reject``) each reply ok=False with
the reason when refused, and a refusal leaves the active network flying. A retried command is done
once: ``runtime.client.command`` sends a request id and the node answers a repeat with the first
answer (:class:`runtime.node.AnsweredOnce`), so a second rollback never undoes the first.
"""
from __future__ import annotations

import argparse
import sys
import time

from flight.estimator import (EstimatorConfig, EstimatorCore, NetworkChoice, bound_phys, estimator_params,
                              load_flown_network, startup_network)
from neso.control import ControlConfig
from runtime.options import add_options, config_from_options
from runtime.schema import EstimateMsg, ReferenceMsg, SetpointMsg, StateMsg


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, EstimatorConfig)


def config_from_args(args) -> EstimatorConfig:
    return config_from_options(EstimatorConfig, args, lockstep=getattr(args, "lockstep", False))


def run(args, bus) -> int:
    from runtime.launcher import EXIT_CONFIG
    from runtime.node import Node, run_node
    from runtime.params import ParamSet
    from neso.certificate import LoopPlant, NetworkSlopes
    from neso.types import VehicleModel
    from services.certificate_cache import warm_flight

    config = config_from_args(args)
    try:
        loaded, source = load_flown_network(config.network)
    except (OSError, ValueError) as exc:  # a missing or refused file is the user's to fix: one line, no traceback
        print(f"[estimator] error: network {config.network!r}: {exc} (paths are relative to where neso runs; "
              "--network FILE, or '' for none)", file=sys.stderr, flush=True)
        return EXIT_CONFIG
    default_gains = (ControlConfig().kp[2], ControlConfig().kd[2])
    if loaded is not None:  # before the network's verdict: no SDP when known before
        warm_flight(NetworkSlopes.of(loaded), *default_gains, config.omega_o_rps,
                    LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=config.mass_kg))))
    network, startup_event = startup_network(config, loaded, default_gains)
    choice = NetworkChoice(network, source if network is not None else "none", config.network_dir)
    core = EstimatorCore(config, network, choice, vehicle=args.vehicle, clock=time.monotonic)
    bound = bound_phys(network) if network is not None else 1.0
    params = ParamSet(estimator_params(config, bound), check=core.check, prepare=core.prepare)
    node = Node("estimator", vehicle=args.vehicle, bus=bus, config=config, params=params)
    if network is not None:
        node.log(f"network {source}: id {core.network_id}, inputs {network.feature_set.key}, L_N "
                 f"{network.certified_lipschitz_physical():.4g} physical ({network.certified_lipschitz_normalised():.4g} "
                 f"normalised); networks for L_N {[round(b, 4) for b in sorted(choice.trained)]} on disk")
    for skipped in choice.skipped:
        node.log(f"skipped {skipped}")
    put = node.publisher("estimate")

    def flush_events() -> None:
        while core.events:
            node.event(*core.events.pop(0))

    def publish(estimates: list[EstimateMsg], received_s: float) -> None:
        for est in estimates:
            put(est)
            node.stats.output(time.monotonic() - received_s)

    def on_state(msg: StateMsg, received_s: float) -> None:
        changed = params.take_pending()
        if changed:
            note = core.apply(changed)
            node.broadcast_params(msg.seq, note)
            node.event("info", f"from sample {msg.seq}: {note}")
        publish(core.on_state(msg, received_s), received_s)

    def on_setpoint(msg: SetpointMsg, received_s: float) -> None:
        publish(core.on_setpoint(msg, received_s), received_s)

    def on_reference(msg: ReferenceMsg, _received_s: float) -> None:
        core.on_reference(msg)
        flush_events()

    def on_controller_params(values: dict) -> None:
        kp, kd, mass = values.get("kp_z"), values.get("kd_z"), values.get("mass_kg")
        mass = float(mass) if isinstance(mass, (int, float)) and mass > 0 else core.plant.mass_kg
        if isinstance(kp, (int, float)) and isinstance(kd, (int, float)) and \
                ((kp, kd) != core.gains_z or mass != core.plant.mass_kg):
            note = core.set_gains(kp, kd, mass)
            if note:
                node.event("warning", note)

    put_network = node.publisher("network")
    published_changes = [-1]

    def publish_network() -> None:  # call under the node lock
        put_network(core.network_msg())
        published_changes[0] = core.changes

    def swap_command(name: str, cmd_args: dict) -> tuple[bool, str]:
        if name == "offer":
            path = cmd_args.get("path")
            if not isinstance(path, str) or not path:
                return False, "offer needs args {path: network file}"
            predicted = cmd_args.get("predicted")
            verdict = core.check_offer(path)  # outside the lock: reads a file
            if verdict.passed:
                core.prepare({})
            with node.lock:
                if not verdict.passed:
                    node.event("warning", f"candidate {path} refused: {verdict.reason}; active {core.network_id} "
                                          "keeps flying")
                    return False, verdict.reason
                message = core.accept(verdict, path, predicted if isinstance(predicted, dict) else None)
                publish_network()
            node.event("info", message)
            return True, message
        actions = {"promote": lambda: core.promote(force=cmd_args.get("force") is True),
                   "rollback": core.rollback, "reject": core.reject}
        if name not in actions:
            return False, f"unknown command {name!r}; estimator takes offer, promote, rollback, reject"
        with node.lock:
            ok, message = actions[name]()
            if ok:
                publish_network()
        node.event("info" if ok else "warning", message)
        return ok, message

    def network_loop(n: Node) -> None:
        if startup_event is not None:
            n.event(*startup_event)
        next_s = time.monotonic()
        while not n.wait(0.05):
            with n.lock:
                flush_events()
                if core.changes != published_changes[0] or time.monotonic() >= next_s:
                    publish_network()
                    next_s = time.monotonic() + 1.0

    core.prepare({})
    node.subscribe("state", on_state)
    node.subscribe("setpoint", on_setpoint)
    node.subscribe("reference", on_reference)
    node.subscribe_params("controller", on_controller_params)
    node.on_command(swap_command, unlocked=("offer", "promote", "rollback", "reject"))
    node.status_hook = lambda: f"ok, pathway {core.estimator.pathway}, network {core.network_id}"
    return run_node(node, network_loop)
