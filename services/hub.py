"""``hub``: the Zenoh router every peer connects to on one machine (``zenohd`` in containers).

It carries no data of its own: it routes discovery and traffic until the peers have linked
up with each other directly; peers keep talking if it goes, and find it again when it is back.
"""
from __future__ import annotations

import argparse
import signal
import threading


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The hub listens on ``--listen`` (default tcp/127.0.0.1:7447); it needs nothing else."""


def run(args, bus) -> int:
    from runtime.bus import open_session

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = open_session(bus)
    try:
        print(f"[hub] Zenoh router {session.info.zid()} listening on {', '.join(bus.listen)}", flush=True)
        stop.wait()
    finally:
        session.close()
    return 0
