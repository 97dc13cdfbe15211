"""``neso run <service>``: one role of the service graph alone, against a bus that may be elsewhere."""
from __future__ import annotations

import importlib

from cli.busargs import add_bus_arguments, bus_from_args
from runtime.graph import GRAPH


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("run", help="run one service (see `neso run -h` for the list)")
    roles = p.add_subparsers(dest="service", required=True, metavar="service")
    for role in GRAPH.values():
        rp = roles.add_parser(role.name, help=role.description, description=role.description)
        add_bus_arguments(rp)
        rp.add_argument("--lockstep", action="store_true", help="deterministic lockstep with the simulator source")
        importlib.import_module(role.module).add_arguments(rp)


def run(args) -> int:
    role = GRAPH[args.service]
    bus = bus_from_args(args, role=role.bus_role, identity=role.cert_name)
    return importlib.import_module(role.module).run(args, bus)
