"""The far side of the floor ping-pongs in :mod:`bench.bus_latency`: every message straight back.

``python -m bench.echo udp``: a UDP socket on 127.0.0.1 (a free port, printed first) that sends
every datagram back to its sender.
``python -m bench.echo zenoh <port>``: a Zenoh peer listening on ``tcp/127.0.0.1:<port>``
(multicast scouting off) that puts every ``bench/ping`` payload, unchanged, on ``bench/pong``
(express); prints ``ready`` once declared.
``python -m bench.echo zenoh <port> <secure dir> <variant>``: the same on a secure bus as the
``estimator``, echoing ``neso/bench/state`` on ``neso/bench/estimate`` (keys the ACL lets a
``source`` and the ``estimator`` put); :func:`secure_config` says what each variant is.

``python -m bench.echo chain <role> <hub>``: one hop of the bare chain (:mod:`bench.hotpath`), a peer of the
hub like a service: ``estimator`` puts an estimate-sized payload on ``bench/chain/estimate`` for every
``bench/chain/state``; ``controller`` (also subscribed to the state, as the controller is) puts a
setpoint-sized payload on ``bench/chain/setpoint`` for every estimate; both also take the setpoint (as the
source and estimator do). Every payload is a real message of its topic with its first 8 bytes replaced by
the state's stamp (float64), so the sizes are exactly the pipeline's. No decoding, no compute: the bus alone.

All run until their stdin closes, then close their socket or session.
"""
from __future__ import annotations

import socket
import sys
import threading

PING, PONG = "bench/ping", "bench/pong"
SECURE_PING, SECURE_PONG = "neso/bench/state", "neso/bench/estimate"


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


VARIANTS = ("acl", "tls", "routed")


def secure_config(port: int, directory: str, variant: str, *, echo: bool):
    """The BusConfig of one side of a secure ping-pong on ``port``: ``acl`` — peers linked directly,
    mutual TLS, the graph's ACL in both (the design ``--secure`` uses); ``tls`` — the same with
    the ACL off (what the ACL itself costs); ``routed`` — both sides clients of a secure hub
    listening on ``port`` (the other design: every message through the hub's ACL, two links)."""
    from runtime.bus import BusConfig
    from runtime.secure import Credentials

    credentials = Credentials(directory, "estimator" if echo else "source")
    endpoint = f"tls/127.0.0.1:{port}"
    if variant == "routed":
        return BusConfig(connect=(endpoint,), listen=(), mode="client", credentials=credentials)
    extra = {"access_control": {"enabled": False}} if variant == "tls" else {}
    if echo:
        return BusConfig(connect=(), listen=(endpoint,), credentials=credentials, extra=extra)
    return BusConfig(connect=(endpoint,), listen=(), credentials=credentials, extra=extra)


def _zenoh(port: int, secure_dir: str | None = None, variant: str = "acl") -> None:
    from runtime.bus import BusConfig, open_session

    config = BusConfig(connect=(), listen=(f"tcp/127.0.0.1:{port}",))
    ping_key, pong_key = PING, PONG
    if secure_dir:
        config = secure_config(port, secure_dir, variant, echo=True)
        ping_key, pong_key = SECURE_PING, SECURE_PONG
    with open_session(config) as session:
        pong = session.declare_publisher(pong_key, express=True)
        session.declare_subscriber(ping_key, lambda sample: pong.put(sample.payload.to_bytes()))
        print("ready", flush=True)
        sys.stdin.read()


CHAIN = "bench/chain/"


def _chain(role: str, hub: str) -> None:
    from bench.payloads import payload
    from runtime.bus import BusConfig, open_session

    out_topic, in_topic = {"estimator": ("estimate", "state"), "controller": ("setpoint", "estimate")}[role]
    body = payload(out_topic)[8:]
    with open_session(BusConfig(connect=(hub,))) as session:
        pub = session.declare_publisher(CHAIN + out_topic, express=True)
        session.declare_subscriber(CHAIN + in_topic, lambda s: pub.put(s.payload.to_bytes()[:8] + body))
        session.declare_subscriber(CHAIN + "setpoint", lambda s: None)
        if role == "controller":
            session.declare_subscriber(CHAIN + "state", lambda s: None)
        print("ready", flush=True)
        sys.stdin.read()


if __name__ == "__main__":
    if sys.argv[1] == "udp":
        _udp()
    elif sys.argv[1] == "chain":
        _chain(sys.argv[2], sys.argv[3])
    else:
        _zenoh(int(sys.argv[2]), *sys.argv[3:5])
