"""The far side of the floor ping-pongs in :mod:`bench.bus_latency`: every message straight back.

``python -m bench.echo udp``: a UDP socket on 127.0.0.1 (a free port, printed first) that sends
every datagram back to its sender.
``python -m bench.echo zenoh <port>``: a Zenoh peer listening on ``tcp/127.0.0.1:<port>``
(multicast scouting off) that puts every ``bench/ping`` payload, unchanged, on ``bench/pong``
(express); prints ``ready`` once declared.

Both run until their stdin closes, then close their socket or session.
"""
from __future__ import annotations

import socket
import sys
import threading

PING, PONG = "bench/ping", "bench/pong"


def _udp() -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    print(sock.getsockname()[1], flush=True)

    def echo() -> None:
        while True:
            data, sender = sock.recvfrom(65536)
            sock.sendto(data, sender)

    threading.Thread(target=echo, daemon=True).start()
    sys.stdin.read()
    sock.close()


def _zenoh(port: int) -> None:
    from runtime.bus import BusConfig, open_session

    with open_session(BusConfig(connect=(), listen=(f"tcp/127.0.0.1:{port}",))) as session:
        pong = session.declare_publisher(PONG, express=True)
        session.declare_subscriber(PING, lambda sample: pong.put(sample.payload.to_bytes()))
        print("ready", flush=True)
        sys.stdin.read()


if __name__ == "__main__":
    _udp() if sys.argv[1] == "udp" else _zenoh(int(sys.argv[2]))
