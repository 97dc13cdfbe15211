"""``neso run <service>``: one role of the service graph alone, against a bus that may be elsewhere.

A per-vehicle role serves one vehicle (``--vehicle``), or several from this one process (``--vehicles
a,b,c``: a thread per vehicle, each its own node and Zenoh session; a signal stops them all)."""
from __future__ import annotations

import argparse
import copy
import importlib
import threading

from cli.busargs import add_bus_arguments, bus_from_args
from runtime.graph import GRAPH


class _RoleArguments(argparse._SubParsersAction):
    """The role's own arguments added once it is chosen: a service process imports its own module only, not
    every role's (each one's imports cost every process ~0.5 s of CPU at its start)."""

    def __call__(self, parser, namespace, values, option_string=None):
        role = GRAPH.get(values[0])
        chosen = self._name_parser_map.get(values[0])
        if role is not None and chosen is not None and not getattr(chosen, "role_arguments", False):
            importlib.import_module(role.module).add_arguments(chosen)
            chosen.role_arguments = True
        super().__call__(parser, namespace, values, option_string)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("run", help="run one service (see `neso run -h` for the list)")
    roles = p.add_subparsers(dest="service", required=True, metavar="service", action=_RoleArguments)
    for role in GRAPH.values():
        rp = roles.add_parser(role.name, help=role.description, description=role.description)
        add_bus_arguments(rp)
        rp.add_argument("--lockstep", action="store_true", help="deterministic lockstep with the simulator source")
        if role.per_vehicle and role.bus_role != "router":
            rp.add_argument("--vehicles", default="",
                            help="serve these vehicles (comma-separated) from this one process instead of --vehicle")


def run(args) -> int:
    role = GRAPH[args.service]
    bus = bus_from_args(args, role=role.bus_role, identity=role.cert_name)
    module = importlib.import_module(role.module)
    vehicles = [v for v in getattr(args, "vehicles", "").split(",") if v]
    if not vehicles:
        return module.run(args, bus)
    return _run_many(module, args, bus, vehicles)


def _run_many(module, args, bus, vehicles: list[str]) -> int:
    """``module.run`` for each vehicle on a thread of its own; the worst exit code of them."""
    from runtime.node import stop_all_on_signals

    stop_all_on_signals()
    codes: dict[str, int] = {}

    def serve(vehicle: str) -> None:
        one = copy.copy(args)
        one.vehicle = vehicle
        codes[vehicle] = module.run(one, bus)
    threads = [threading.Thread(target=serve, args=(v,), name=f"{args.service}-{v}") for v in vehicles]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return max((codes.get(v, 1) for v in vehicles), default=0)
