"""``neso params get|set`` and ``neso cmd``: talk to running services from a terminal."""
from __future__ import annotations

import json

from cli.busargs import add_bus_arguments, bus_from_args, refusal_hint


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("params", help="read or change a running service's live parameters")
    p.add_argument("op", choices=("get", "set"))
    p.add_argument("service", help="estimator, controller, ...")
    p.add_argument("values", nargs="*", metavar="name=value", help="for set: values (JSON literals or text)")
    p.add_argument("--timeout", type=float, default=2.0)
    add_bus_arguments(p)


def add_cmd_parser(subparsers) -> None:
    p = subparsers.add_parser("cmd", help="send a command to a running service (e.g. a mission to the controller)")
    p.add_argument("service")
    p.add_argument("name", help="command, e.g. takeoff, hover, landing_test, lemniscate, land")
    p.add_argument("args", nargs="*", metavar="name=value")
    p.add_argument("--timeout", type=float, default=2.0)
    add_bus_arguments(p)


def parse_assignments(items: list[str]) -> dict:
    """``["pathway=eso", "lipschitz_bound=0.5"]`` → ``{"pathway": "eso", "lipschitz_bound": 0.5}``."""
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"expected name=value, got {item!r}")
        try:
            out[name] = json.loads(text)
        except json.JSONDecodeError:
            out[name] = text
    return out


def _session(args):
    from runtime.bus import open_session
    return open_session(bus_from_args(args))


def run(args) -> int:
    from runtime.client import ServiceUnavailable, get_params, set_params
    from runtime.schema import Keys

    keys = Keys(args.vehicle)
    with _session(args) as session:
        try:
            if args.op == "get":
                reply = get_params(session, keys, args.service, args.timeout)
            else:
                reply = set_params(session, keys, args.service, parse_assignments(args.values), args.timeout)
        except ServiceUnavailable as exc:
            print(f"error: {exc}{refusal_hint(args)}")
            return 2
    print(json.dumps(reply.values, indent=2))
    if not reply.ok:
        print(f"refused: {reply.error}")
        return 1
    if args.op == "set":
        print("accepted: takes effect at the next sample")
    return 0


def run_cmd(args) -> int:
    from runtime.client import ServiceUnavailable, command
    from runtime.schema import Keys

    with _session(args) as session:
        try:
            reply = command(session, Keys(args.vehicle), args.service, args.name, parse_assignments(args.args), args.timeout)
        except ServiceUnavailable as exc:
            print(f"error: {exc}{refusal_hint(args)}")
            return 2
    print(("ok" if reply.ok else "refused") + (f": {reply.message}" if reply.message else ""))
    return 0 if reply.ok else 1
