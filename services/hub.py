"""``hub``: the Zenoh router every peer connects to on one machine (``zenohd`` in containers).

It carries no data of its own: it routes discovery and traffic until the peers have linked
up with each other directly; peers keep talking if it goes, and find it again when it is back.

On a secure bus (``--secure``) it listens on ``tls/`` with mutual TLS and runs the graph's
access-control list like every other session, and it tells what it refused: each kind of
refused message (identity, message, key) and each kind of refused TLS link, the first time and
at 10, 100, … (:mod:`runtime.refusals`).
"""
from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The hub listens on ``--listen`` (default tcp/127.0.0.1:7447); it needs nothing else."""


def run(args, bus) -> int:
    from runtime.bus import open_session
    from runtime.signals import Signalled

    signalled = Signalled().install()  # a flag, never an event set in the handler (runtime/signals.py)
    if bus.credentials is not None:
        from runtime.refusals import RefusalCounter, capture_zenoh_log

        counter = RefusalCounter()

        def on_line(line: str) -> None:
            said = counter.feed(line)
            if said:
                print(f"[hub] {said}", flush=True)
        capture_zenoh_log(on_line)
    session = open_session(bus)
    try:
        secure = (f"; mutual TLS as {bus.credentials.identity!r} (CA {bus.credentials.ca}), access control from "
                  "the service graph") if bus.credentials is not None else ""
        print(f"[hub] Zenoh router {session.info.zid()} listening on {', '.join(bus.listen)}{secure}", flush=True)
        signalled.wait()
    finally:
        session.close()
    return 0
