"""A NatNet client (OptiTrack Motive's streaming protocol) for the motion-capture source: asks the server what it
streams, with retries, and reads its frames with Motive's own timestamps.

Why not libmotioncapture's optitrack client (which this source flew before): its Python binding (1.1) exposes
only ``rigidBodies`` and ``waitForNextFrame`` — not the frame's timestamp nor Motive's latency fields, so states
could only be stamped on UDP receipt (network jitter became velocity noise); its ``connect`` waits for the
server's answer without a timeout while holding Python's GIL; and a stopped stream left its reader blocked.
The packets are read by :mod:`sim.natnet` (every version in :data:`sim.natnet.SUPPORTED`), checked against the
independent ``natnet`` package and against libmotioncapture on the same stream (tests/process/test_natnet.py).

Transport as libmotioncapture does it: a socket bound to the server's data port (address reuse, so several
clients on one machine share a multicast stream), joined to its multicast group on ``interface`` when the server
multicasts; with unicast the server sends to the address that asked (the simulated Motive does both).
"""
from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from sim import natnet


class NatNetUnavailable(RuntimeError):
    """Nobody answered, or the answer is not NatNet this client reads: one line for the operator."""


@dataclass(frozen=True)
class ServerOffer:
    """What the server at ``host:port`` said it streams: its info (version, clock, data port, multicast) and its
    rigid bodies ``{id: name}``; ``tries``: the queries it took (the first answered is 1)."""

    host: str
    port: int
    info: natnet.ServerInfo
    bodies: dict[int, str]
    tries: int

    @property
    def version(self) -> str:
        """The NatNet version as Motive states it (``4.1``; its build and revision in :attr:`info`)."""
        return ".".join(map(str, self.info.natnet_version[:2]))


def _ask(sock: socket.socket, address: tuple[str, int], message_id: int, answer_id: int, tries: int,
         timeout_s: float) -> tuple[bytes, int]:
    """Send ``message_id`` until an ``answer_id`` comes (``tries`` times, ``timeout_s`` each; datagrams of another
    kind, e.g. frames a unicast server sends to this socket, are skipped): (payload, the try it took)."""
    for attempt in range(1, tries + 1):
        deadline = time.monotonic() + timeout_s
        try:
            sock.sendto(natnet.packet(message_id), address)
        except OSError:  # no route yet (the network coming up): the next try may pass
            time.sleep(timeout_s)
            continue
        while (left := deadline - time.monotonic()) > 0:
            sock.settimeout(left)
            try:
                got, answer = natnet.split(sock.recv(65536))
            except (socket.timeout, ConnectionRefusedError):  # refused: nobody listens on that port yet
                time.sleep(max(0.0, deadline - time.monotonic()))
                break
            except natnet.NatNetError:
                continue
            if got == answer_id:
                return answer, attempt
    raise NatNetUnavailable(f"no answer to {'NAT_CONNECT' if message_id == natnet.NAT_CONNECT else 'NAT_REQUEST_MODELDEF'}"
                            f" after {tries} tries of {timeout_s:g} s")


def query_server(host: str, port: int, *, tries: int = 5, timeout_s: float = 0.5) -> ServerOffer:
    """Ask the NatNet server at ``host:port`` (its command port) as its clients do: NAT_CONNECT, then
    NAT_REQUEST_MODELDEF, each retried (UDP may drop a datagram; a server busy starting answers late).
    :class:`NatNetUnavailable` with one line when nobody answers or it speaks a version not read here."""
    address = (host, port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            payload, first = _ask(s, address, natnet.NAT_CONNECT, natnet.NAT_SERVERINFO, tries, timeout_s)
            info = natnet.parse_server_info(payload)
            if not natnet.supported(info.natnet_version):
                raise NatNetUnavailable(
                    f"{info.app_name} {'.'.join(map(str, info.app_version))} at {host}:{port} speaks NatNet "
                    f"{'.'.join(map(str, info.natnet_version))}; this client reads NatNet 3.0-4.1 (Motive 2.0 and "
                    "later), whose frames carry the cameras' exposure time")
            payload, second = _ask(s, address, natnet.NAT_REQUEST_MODELDEF, natnet.NAT_MODELDEF, tries, timeout_s)
            bodies = natnet.parse_rigid_body_names(payload, info.natnet_version)
        except (OSError, natnet.NatNetError) as exc:
            raise NatNetUnavailable(f"{type(exc).__name__}: {exc}") from None
    return ServerOffer(host, port, info, bodies, max(first, second))


class FrameStream:
    """The server's frames: :meth:`read` returns the next (frame, arrival monotonic s), or None after
    ``timeout_s`` without one. Frames that do not parse are counted (``malformed``) and skipped."""

    def __init__(self, offer: ServerOffer, interface: str = "0.0.0.0") -> None:
        self.offer = offer
        self.malformed = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("0.0.0.0", offer.info.data_port))
        if offer.info.multicast:
            membership = socket.inet_aton(offer.info.multicast_group) + socket.inet_aton(interface)
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)

    def read(self, timeout_s: float) -> tuple[natnet.Frame, float] | None:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            self._sock.settimeout(left)
            try:
                data = self._sock.recv(65536)
            except socket.timeout:
                return None
            arrival_s = time.monotonic()
            try:
                message_id, payload = natnet.split(data)
                if message_id != natnet.NAT_FRAMEOFDATA:
                    continue
                return natnet.parse_frame(payload, self.offer.info.natnet_version), arrival_s
            except natnet.NatNetError:
                self.malformed += 1
        return None

    def close(self) -> None:
        self._sock.close()
