"""Command-line options every bus-connected command shares (vehicle, endpoints, Zenoh config)."""
from __future__ import annotations

import argparse

from runtime.bus import DEFAULT_HUB, BusConfig


def add_bus_arguments(parser: argparse.ArgumentParser, *, default_mode: str = "peer") -> None:
    g = parser.add_argument_group("bus")
    g.add_argument("--vehicle", default="uav1", help="vehicle name: keys live under neso/<vehicle>/ (default uav1)")
    g.add_argument("--connect", action="append", default=None,
                   help=f"Zenoh endpoint to connect to, repeatable (default {DEFAULT_HUB})")
    g.add_argument("--listen", action="append", default=None,
                   help="Zenoh endpoint to listen on, repeatable (default tcp/127.0.0.1:0; the hub: its own endpoint)")
    g.add_argument("--mode", default=default_mode, choices=("peer", "client", "router"))
    g.add_argument("--zenoh-config", default=None, help="a Zenoh JSON5 config file, applied before the options above")
    g.add_argument("--low-latency", action="store_true", help="Zenoh lowlatency transport (every process must agree)")


def bus_from_args(args, *, role: str = "peer") -> BusConfig:
    """The BusConfig the options describe; ``role`` ``router`` makes the hub's defaults."""
    if role == "router":
        listen = tuple(args.listen or (args.connect or [DEFAULT_HUB])[:1])
        return BusConfig(connect=(), listen=listen, mode="router", config_file=args.zenoh_config,
                         low_latency=args.low_latency)
    return BusConfig(connect=tuple(args.connect or (DEFAULT_HUB,)), listen=tuple(args.listen or ("tcp/127.0.0.1:0",)),
                     mode=args.mode, config_file=args.zenoh_config, low_latency=args.low_latency)
