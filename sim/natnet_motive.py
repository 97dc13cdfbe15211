"""``python -m sim.natnet_motive``: one simulated Motive PC for several simulated vehicles
(``neso up --mocap natnet`` with more than one ``--name``): NatNet (4.1 unless ``--natnet-version``) on loopback streaming every vehicle's
rigid body in one frame stream (:class:`sim.natnet_server.SharedMotive`), fed by each vehicle's world over a
loopback UDP port. Runs until SIGINT or SIGTERM."""
from __future__ import annotations

import argparse
import signal
import sys
import time

from sim.natnet_server import NatNetServer, NatNetServerConfig, SharedMotive, StreamModel


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sim.natnet_motive", description=__doc__)
    p.add_argument("--port", type=int, required=True, help="command port (data: the next one)")
    p.add_argument("--feed-port", type=int, required=True, help="loopback UDP port the worlds feed their samples to")
    p.add_argument("--bodies", required=True, help="rigid-body names, comma-separated; IDs 1, 2, … in this order")
    p.add_argument("--rate", type=float, required=True, help="frame rate, Hz (the worlds' mocap rate)")
    p.add_argument("--up-axis", default="y", choices=("y", "z"))
    p.add_argument("--jitter-ms", type=float, default=0.0)
    p.add_argument("--dropout", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--natnet-version", default="4.1", choices=("3.0", "3.1", "4.0", "4.1"))
    args = p.parse_args(argv)
    names = [n for n in args.bodies.split(",") if n]
    if not names or len(set(names)) != len(names):
        print(f"natnet_motive: --bodies {args.bodies!r}: distinct names, comma-separated", file=sys.stderr)
        return 2
    try:
        server = NatNetServer(NatNetServerConfig(bodies={n: i + 1 for i, n in enumerate(names)},
                                                 command_port=args.port, data_port=args.port + 1,
                                                 version=tuple(int(v) for v in args.natnet_version.split("."))))
        server.start()
        motive = SharedMotive(server, StreamModel(jitter_std_s=args.jitter_ms / 1e3, dropout=args.dropout,
                                                  up_axis=args.up_axis),
                              rate_hz=args.rate, feed_port=args.feed_port, seed=args.seed).start()
    except OSError as exc:
        print(f"natnet_motive: cannot listen on 127.0.0.1:{args.port}/{args.feed_port}: {exc}", file=sys.stderr)
        return 1
    caught: list[int] = []  # the handler only appends (no lock: one that waited on what it interrupted could hang)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: caught.append(signum))
    print(f"simulated Motive: NatNet {args.natnet_version} on 127.0.0.1:{args.port} (data {args.port + 1}), {args.up_axis}-up, "
          f"{args.rate:g} Hz, rigid bodies {dict(server.config.bodies)}; fed on UDP {args.feed_port}", flush=True)
    while not caught:
        time.sleep(0.1)
    motive.close()
    server.close()
    print(f"simulated Motive: {server.sent} frames sent, {motive.dropped} dropped, {motive.stale} rigid bodies "
          f"untracked for want of a fed sample near the exposure, {motive.malformed_feed} malformed feed datagrams",
          flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
