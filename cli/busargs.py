"""Command-line options every bus-connected command shares (vehicle, endpoints, Zenoh config, security)."""
from __future__ import annotations

import argparse

from runtime.bus import DEFAULT_HUB, SECURE_HUB, BusConfig


def add_bus_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer") -> None:
    g = parser.add_argument_group("bus")
    g.add_argument("--vehicle", default="uav1", help="vehicle name: keys live under neso/<vehicle>/ (default uav1)")
    g.add_argument("--connect", action="append", default=None,
                   help=f"Zenoh endpoint to connect to, repeatable (default {DEFAULT_HUB}; --secure: {SECURE_HUB})")
    g.add_argument("--listen", action="append", default=None,
                   help="Zenoh endpoint to listen on, repeatable (default tcp/127.0.0.1:0; the hub: its own endpoint)")
    g.add_argument("--mode", default=default_mode, choices=("peer", "client", "router"))
    g.add_argument("--zenoh-config", default=None, help="a Zenoh JSON5 config file, applied before the options above")
    g.add_argument("--low-latency", action="store_true", help="Zenoh lowlatency transport (every process must agree)")
    g.add_argument("--priorities", action="store_true",
                   help="publish the loop's streams at Zenoh's real-time priority, health and events at low priority")
    add_secure_arguments(g)


def add_secure_arguments(group) -> None:
    from runtime.secure import default_dir

    group.add_argument("--secure", action="store_true",
                       help="TLS with client certificates and the graph's access control (see `neso secure init`)")
    group.add_argument("--secure-dir", default=None,
                       help=f"where the CA and certificates are (default $NESO_SECURE_DIR or {default_dir()})")
    group.add_argument("--identity", default=None,
                       help="certificate to present (default: the service's own; the CLI: operator)")


def credentials_from_args(args, identity: str):
    """The credentials ``--secure`` asks for (None without it); exits with one line if missing."""
    if not getattr(args, "secure", False):
        return None
    from runtime.secure import Credentials, SecureSetupError, default_dir

    try:
        return Credentials(args.secure_dir or default_dir(), args.identity or identity).check()
    except SecureSetupError as exc:
        raise SystemExit(f"error: {exc}") from None


def refusal_hint(args, identity: str = "operator") -> str:
    """What to add to "no reply" on a secure bus (the ACL drops what it refuses without a word)."""
    if not getattr(args, "secure", False):
        return ""
    return f" (or the bus's access control does not let {args.identity or identity!r} send it)"


def bus_from_args(args, *, role: str = "peer", identity: str = "operator") -> BusConfig:
    """The BusConfig the options describe; ``role`` ``router`` makes the hub's defaults;
    ``identity``: the certificate a ``--secure`` session presents unless ``--identity`` says."""
    credentials = credentials_from_args(args, identity)
    hub = SECURE_HUB if credentials is not None else DEFAULT_HUB
    listen_any = "tls/127.0.0.1:0" if credentials is not None else "tcp/127.0.0.1:0"
    try:
        if role == "router":
            listen = tuple(args.listen or (args.connect or [hub])[:1])
            return BusConfig(connect=(), listen=listen, mode="router", config_file=args.zenoh_config,
                             low_latency=args.low_latency, priorities=args.priorities, credentials=credentials)
        default_listen = () if args.mode == "client" else (listen_any,)  # a client only talks through the hub
        return BusConfig(connect=tuple(args.connect or (hub,)), listen=tuple(args.listen or default_listen),
                         mode=args.mode, config_file=args.zenoh_config, low_latency=args.low_latency,
                         priorities=args.priorities, credentials=credentials)
    except ValueError as exc:
        raise SystemExit(f"error: {exc}") from None
