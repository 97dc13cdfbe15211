"""A simulated Motive PC: NatNet 4.1 on loopback, fed by the world's motion-capture samples.

The command channel (UDP ``command_port``, 1510 like Motive) answers NAT_CONNECT with NAT_SERVERINFO,
NAT_REQUEST_MODELDEF with NAT_MODELDEF (the rigid bodies by ID and name), NAT_REQUEST with an
empty NAT_RESPONSE, ignores NAT_KEEPALIVE and answers anything else with NAT_UNRECOGNIZED_REQUEST;
a datagram too short or whose header lies is dropped and counted (``malformed``).

The frame stream (``data_port``, 1511 like Motive): multicast to ``multicast_group`` on the loopback
interface (Motive's default; the only way two clients on one machine both receive it), or unicast
to every client that connected: to its command socket (what OptiTrack's sample clients read) and to
its address on ``data_port`` (what libmotioncapture 1.1 reads). Loopback only: the server binds
127.0.0.1 and multicasts through it.

:meth:`NatNetServer.submit` queues a frame to leave at a wall-clock (``time.monotonic``) instant; a
sender thread sends it then. What the world's mocap model does to the stream (latency, jitter,
dropouts, a rigid body lost) is decided by the caller (:class:`StreamModel`), not here. High-resolution
timestamps are ``time.monotonic`` in ticks of :data:`CLOCK_HZ`, like Motive's QueryPerformanceCounter.
This module does I/O (sockets, a thread); only ``services/source.py`` and tests use it.
"""
from __future__ import annotations

import heapq
import itertools
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from sim import natnet

CLOCK_HZ = 10_000_000  # Motive's high-resolution clock on Windows: 10 MHz


@dataclass(frozen=True)
class NatNetServerConfig:
    """Ports and transport; ``bodies``: ``{name: id}`` streamed, in this order; ``version``: the NatNet version it
    speaks (one of :data:`sim.natnet.SUPPORTED`)."""

    bodies: dict[str, int] = field(default_factory=lambda: {"uav1": 1})
    version: tuple[int, int] = natnet.NATNET_VERSION[:2]
    command_port: int = 1510
    data_port: int = 1511
    multicast: bool = True
    multicast_group: str = "239.255.42.99"
    address: str = "127.0.0.1"


@dataclass(frozen=True)
class StreamModel:
    """What the motion-capture system does to each sample on its way out: ``latency_s`` from mid-exposure
    to transmission (the world's mocap model, :class:`sim.mocap.MocapConfig`), ``jitter_std_s``: each frame
    leaves a further |N(0, jitter_std_s)| late (half-normal: never before its latency), ``dropout`` (probability a frame is not
    sent), ``lost``: (start_s, duration_s) windows of world time in which the rigid bodies are not
    tracked (frames still go out, with the tracking-valid flag clear). ``up_axis``: Motive's "y"
    (default) or "z"."""

    latency_s: float = 0.010
    jitter_std_s: float = 0.0
    dropout: float = 0.0
    lost: tuple[tuple[float, float], ...] = ()
    up_axis: str = "y"

    def tracked(self, t_s: float) -> bool:
        return not any(start <= t_s < start + duration for start, duration in self.lost)


class NatNetServer:
    """Start with :meth:`start` (or ``with``); :meth:`close` stops both threads and the sockets."""

    def __init__(self, config: NatNetServerConfig) -> None:
        self.config = config
        self.malformed = 0
        self.sent = 0
        self.clients: list[tuple[str, int]] = []  # command-socket addresses that sent NAT_CONNECT
        self._frame_number = itertools.count()
        self._queue: list[tuple[float, int, float, list[natnet.BodyPose]]] = []
        self._order = itertools.count()
        self._wake = threading.Condition()
        self._stopping = False
        self._t0 = time.monotonic()
        self._cmd = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._cmd.bind((config.address, config.command_port))
        self._cmd.settimeout(0.2)
        self._data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._data.bind((config.address, 0))
        if config.multicast:
            self._data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(config.address))
            self._data.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self._threads = [threading.Thread(target=self._serve_commands, name="natnet-commands", daemon=True),
                         threading.Thread(target=self._send_frames, name="natnet-frames", daemon=True)]

    @property
    def command_port(self) -> int:
        return self._cmd.getsockname()[1]

    def start(self) -> "NatNetServer":
        for t in self._threads:
            t.start()
        return self

    def close(self) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify_all()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)
        self._cmd.close()
        self._data.close()

    def __enter__(self) -> "NatNetServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def submit(self, send_at_s: float, mid_exposure_s: float, bodies: list[natnet.BodyPose]) -> None:
        """Send a frame of ``bodies`` at monotonic ``send_at_s``, exposed at monotonic ``mid_exposure_s``."""
        with self._wake:
            heapq.heappush(self._queue, (send_at_s, next(self._order), mid_exposure_s, bodies))
            self._wake.notify()

    def _serve_commands(self) -> None:
        cfg = self.config
        info = natnet.server_info(data_port=cfg.data_port, multicast=cfg.multicast, multicast_group=cfg.multicast_group,
                                  clock_hz=CLOCK_HZ, version=cfg.version)
        model = natnet.model_def({body_id: name for name, body_id in cfg.bodies.items()}, cfg.version)
        while not self._stopping:
            try:
                data, addr = self._cmd.recvfrom(65536)
                message_id, _ = natnet.split(data)
            except socket.timeout:
                continue
            except natnet.NatNetError:
                self.malformed += 1
                continue
            except OSError:
                return
            if message_id == natnet.NAT_CONNECT:
                if addr not in self.clients:
                    self.clients.append(addr)
                reply = info
            elif message_id == natnet.NAT_REQUEST_MODELDEF:
                reply = model
            elif message_id == natnet.NAT_REQUEST:
                reply = natnet.packet(natnet.NAT_RESPONSE, b"\0")
            elif message_id == natnet.NAT_KEEPALIVE:
                continue
            else:
                reply = natnet.packet(natnet.NAT_UNRECOGNIZED_REQUEST)
            self._cmd.sendto(reply, addr)

    def _destinations(self) -> list[tuple[socket.socket, tuple[str, int]]]:
        cfg = self.config
        if cfg.multicast:
            return [(self._data, (cfg.multicast_group, cfg.data_port))]
        out = []
        for host, port in list(self.clients):
            out += [(self._cmd, (host, port)), (self._data, (host, cfg.data_port))]
        return out

    def _send_frames(self) -> None:
        while True:
            with self._wake:
                while not self._stopping and (not self._queue or self._queue[0][0] > time.monotonic()):
                    self._wake.wait(None if not self._queue else max(0.0, self._queue[0][0] - time.monotonic()))
                if self._stopping:
                    return
                _, _, mid_s, bodies = heapq.heappop(self._queue)
            now = time.monotonic()
            frame = natnet.frame_of_data(next(self._frame_number), bodies, timestamp_s=mid_s - self._t0,
                                         mid_exposure_ticks=int(mid_s * CLOCK_HZ), received_ticks=int(mid_s * CLOCK_HZ),
                                         transmit_ticks=int(now * CLOCK_HZ), clock_hz=CLOCK_HZ,
                                         version=self.config.version)
            for sock, dest in self._destinations():
                try:
                    sock.sendto(frame, dest)
                except OSError:
                    pass  # a unicast client gone away; the others still get the frame
            self.sent += 1


class WorldStream:
    """The world's mocap samples → NatNet frames: each sample of rigid body ``body_id`` (ENU position and
    ZYX Euler angles, world time ``t_s``) is exposed at ``anchor_s + t_s`` (monotonic) and submitted to
    leave ``latency_s`` (+ jitter) later, unless dropped; in a ``lost`` window it goes out untracked.
    Seeded: the same seed, the same jitter and dropouts."""

    def __init__(self, server: NatNetServer, model: StreamModel, *, body_id: int, anchor_s: float, seed: int) -> None:
        self.server, self.model, self.body_id, self.anchor_s = server, model, body_id, anchor_s
        self._rng = np.random.default_rng(seed)
        self.dropped = 0

    def sample(self, t_s: float, pos_enu_m, rpy_rad) -> None:
        m = self.model
        jitter = abs(self._rng.normal(0.0, m.jitter_std_s)) if m.jitter_std_s > 0 else 0.0
        if m.dropout > 0 and self._rng.random() < m.dropout:
            self.dropped += 1
            return
        pos, quat = natnet.motive_pose(pos_enu_m, rpy_rad, m.up_axis)
        mid = self.anchor_s + t_s
        self.server.submit(mid + m.latency_s + jitter, mid, [natnet.BodyPose(self.body_id, pos, quat, m.tracked(t_s))])


class FeedStream:
    """The world's mocap samples → a shared simulated Motive (:class:`SharedMotive`, another process) over a
    loopback UDP ``feed_port``: per sample, the rigid body's ``body_id``, its exposure at ``anchor_s + t_s``
    (monotonic), its ENU position and ZYX Euler angles, whether it is tracked (``model.lost``) and the world's
    mocap latency; what Motive does to frames (latency, jitter, dropouts, the up axis) is Motive's."""

    def __init__(self, feed_port: int, model: StreamModel, *, body_id: int, anchor_s: float) -> None:
        self.model, self.body_id, self.anchor_s = model, body_id, anchor_s
        self._dest = ("127.0.0.1", feed_port)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def sample(self, t_s: float, pos_enu_m, rpy_rad) -> None:
        import msgpack

        m = self.model
        self._sock.sendto(msgpack.packb([self.body_id, self.anchor_s + t_s, [float(v) for v in pos_enu_m],
                                         [float(v) for v in rpy_rad], m.tracked(t_s), m.latency_s]), self._dest)

    def close(self) -> None:
        self._sock.close()


class SharedMotive:
    """One simulated Motive for several worlds, as a lab has one Motive PC for all its vehicles: each world
    feeds its rigid body's samples (:class:`FeedStream`) to UDP ``feed_port`` on loopback; frames leave on
    Motive's own clock at ``rate_hz``, each carrying every rigid body (``server``'s model order): the sample
    nearest the frame's exposure instant (the worlds' clocks are not Motive's: at most half a frame apart at the
    same rate), untracked with its last pose when its world has fed nothing within a frame and a half (counted:
    ``stale``). A frame leaves the largest fed latency (at least a frame) after its exposure, plus
    |N(0, ``model.jitter_std_s``)|, unless dropped (``model.dropout``). Malformed feed datagrams are counted
    (``malformed_feed``) and dropped."""

    def __init__(self, server: NatNetServer, model: StreamModel, *, rate_hz: float, feed_port: int, seed: int = 0) -> None:
        self.server, self.model, self.period_s = server, model, 1.0 / rate_hz
        self._rng = np.random.default_rng(seed)
        self._samples: dict[int, list[tuple[float, tuple, tuple, bool, float]]] = {i: [] for i in server.config.bodies.values()}
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self.malformed_feed = self.dropped = self.stale = 0
        self.latency_s = 0.0  # the largest the worlds fed (their mocap models')
        self._feed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._feed.bind(("127.0.0.1", feed_port))
        self._feed.settimeout(0.2)
        self._threads = [threading.Thread(target=self._read_feed, name="motive-feed", daemon=True),
                         threading.Thread(target=self._frames, name="motive-clock", daemon=True)]

    @property
    def feed_port(self) -> int:
        return self._feed.getsockname()[1]

    def start(self) -> "SharedMotive":
        for t in self._threads:
            t.start()
        return self

    def close(self) -> None:
        self._stopping.set()
        for t in self._threads:
            if t.is_alive():
                t.join(timeout=2.0)
        self._feed.close()

    def _read_feed(self) -> None:
        import msgpack

        while not self._stopping.is_set():
            try:
                data = self._feed.recv(4096)
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                body_id, mid_s, pos, rpy, tracked, latency_s = msgpack.unpackb(data)
                sample = (float(mid_s), tuple(map(float, pos)), tuple(map(float, rpy)), bool(tracked), float(latency_s))
                if body_id not in self._samples or len(sample[1]) != 3 or len(sample[2]) != 3 \
                        or not all(np.isfinite((sample[0], *sample[1], *sample[2], sample[4]))):
                    raise ValueError(body_id)
            except (ValueError, TypeError, msgpack.UnpackException):
                self.malformed_feed += 1
                continue
            with self._lock:
                kept = self._samples[body_id]
                kept.append(sample)
                del kept[:-16]  # the newest 16: the world runs up to a control period ahead of its samples

    def frame_bodies(self, mid_s: float) -> tuple[list[natnet.BodyPose], float]:
        """Every fed body at exposure ``mid_s`` (monotonic) and the frame's latency (s)."""
        bodies, latency = [], 0.0
        with self._lock:
            for body_id, kept in self._samples.items():
                if not kept:
                    continue
                t, pos, rpy, tracked, lat = min(kept, key=lambda s: abs(s[0] - mid_s))
                fresh = abs(t - mid_s) <= 1.5 * self.period_s
                self.stale += not fresh
                p, q = natnet.motive_pose(pos, rpy, self.model.up_axis)
                bodies.append(natnet.BodyPose(body_id, p, q, tracked and fresh))
                latency = max(latency, lat)
        return bodies, latency

    def _frames(self) -> None:
        t0 = time.monotonic()
        for k in itertools.count(1):
            mid = t0 + k * self.period_s
            # assembled when it is due to leave (the latency after its exposure, at least a frame): a world late by
            # up to that much on a busy machine has still fed its sample nearest the exposure
            if self._stopping.wait(max(0.0, mid + max(self.latency_s, self.period_s) - time.monotonic())):
                return
            bodies, self.latency_s = self.frame_bodies(mid)
            if not bodies:
                continue
            if self.model.dropout > 0 and self._rng.random() < self.model.dropout:
                self.dropped += 1
                continue
            jitter = abs(self._rng.normal(0.0, self.model.jitter_std_s)) if self.model.jitter_std_s > 0 else 0.0
            self.server.submit(mid + max(self.latency_s, self.period_s) + jitter, mid, bodies)


def free_udp_port() -> int:
    """A UDP port nobody on 127.0.0.1 holds now (for tests and benches that run servers side by side)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]

