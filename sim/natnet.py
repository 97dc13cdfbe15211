"""NatNet, OptiTrack Motive's streaming protocol, as packets: built for the simulated Motive
(:mod:`sim.natnet_server`) and read where a client must check what a server offers.

Pure: bytes in, bytes out; no sockets. Layouts follow OptiTrack's published parsers (NatNet SDK
4.1 ``PacketClient.cpp``/``NatNetClient.py``, the ``natnetsdk`` package) and the reader we fly,
libmotioncapture 1.1's ``src/optitrack.cpp``. Every packet is ``uint16 message id, uint16 payload
bytes, payload``, little-endian. NatNet versions :data:`SUPPORTED` (3.0 Motive 2.0 … 4.1 Motive 3.1; a later 4.x
is read as 4.1): from 3.0 every frame carries Motive's high-resolution timestamps (camera mid-exposure, data
received, transmit), which the source stamps its states with; from 4.1 counts of the frame's data sets and of
each model description are followed by their size in bytes (earlier versions are walked field by field).

Motive's frames: **y-up** by default (x, y up, z; right-handed; ``FRAMES['y_up']`` of
:mod:`flight.source` maps it to ENU), **z-up** when the streaming pane's Up Axis says Z (then x, y,
z up, taken here as ENU). Positions in metres, orientations as quaternions (x, y, z, w) of the
body in that frame.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

NATNET_VERSION = (4, 1, 0, 0)
SUPPORTED = ((3, 0), (3, 1), (4, 0), (4, 1))  # NatNet (major, minor) read here; the simulated Motive speaks each
MOTIVE_OF = {(3, 0): (2, 0, 0, 0), (3, 1): (2, 1, 0, 0), (4, 0): (3, 0, 0, 0), (4, 1): (3, 1, 0, 0)}
MOTIVE_VERSION = MOTIVE_OF[(4, 1)]  # the application version a NatNet 4.1 server reports
DATASET_RIGID_BODY = 1
TRACKING_VALID = 0x01  # rigid body params bit: tracked in this frame
MAX_PACKET_BYTES = 65503

_HEADER = struct.Struct("<HH")
_SERVER_INFO = struct.Struct("<256s4B4BQHB4B")
_RIGID_BODY = struct.Struct("<i3f4ffh")  # id, x y z, qx qy qz qw, mean marker error, params

# Motive frame from ENU: p_motive = MOTIVE_FROM_ENU[up] @ p_enu (y-up: x east, y up, z south)
MOTIVE_FROM_ENU: dict[str, np.ndarray] = {
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
    "z": np.eye(3),
}


class NatNetError(ValueError):
    """A packet that is not what NatNet says it should be."""


@dataclass(frozen=True, slots=True)
class BodyPose:
    """One rigid body in one frame, in Motive's frame: ``pos_m`` (3,), ``quat_xyzw`` (4,)."""

    id: int
    pos_m: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    tracked: bool = True
    mean_error_m: float = 0.0


@dataclass(frozen=True, slots=True)
class ServerInfo:
    app_name: str
    app_version: tuple[int, ...]
    natnet_version: tuple[int, ...]
    clock_hz: int
    data_port: int
    multicast: bool
    multicast_group: str


def packet(message_id: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PACKET_BYTES:
        raise NatNetError(f"payload of {len(payload)} bytes exceeds NatNet's {MAX_PACKET_BYTES}")
    return _HEADER.pack(message_id, len(payload)) + payload


def split(data: bytes) -> tuple[int, bytes]:
    """(message id, payload) of one datagram; :class:`NatNetError` if the header lies about the size."""
    if len(data) < _HEADER.size:
        raise NatNetError(f"{len(data)} bytes: shorter than a NatNet header")
    message_id, size = _HEADER.unpack_from(data)
    if size > len(data) - _HEADER.size:
        raise NatNetError(f"message {message_id}: header says {size} payload bytes, {len(data) - 4} came")
    return message_id, bytes(data[_HEADER.size:_HEADER.size + size])


def supported(version: tuple[int, ...]) -> bool:
    """Whether frames of NatNet ``version`` are read here (3.0 and later; a 4.x above 4.1 as 4.1)."""
    return tuple(version[:2]) >= (3, 0) and version[0] <= 4


def _sized(version: tuple[int, ...]) -> bool:
    """From NatNet 4.1 each data set's count (and each model description) is followed by its size in bytes."""
    return tuple(version[:2]) >= (4, 1)


def server_info(*, data_port: int, multicast: bool, multicast_group: str, clock_hz: int,
                app_name: str = "Motive", version: tuple[int, ...] = NATNET_VERSION) -> bytes:
    """NAT_SERVERINFO (``sSender_Server``): the answer to NAT_CONNECT, for NatNet ``version``."""
    group = [int(b) for b in multicast_group.split(".")]
    natnet_version = tuple(version) + (0,) * (4 - len(version))
    motive = MOTIVE_OF.get(tuple(version[:2]), MOTIVE_VERSION)
    return packet(NAT_SERVERINFO, _SERVER_INFO.pack(app_name.encode()[:255], *motive, *natnet_version,
                                                    clock_hz, data_port, int(multicast), *group))


def parse_server_info(payload: bytes) -> ServerInfo:
    if len(payload) < _SERVER_INFO.size:
        raise NatNetError(f"server info of {len(payload)} bytes, NatNet's has {_SERVER_INFO.size}")
    v = _SERVER_INFO.unpack_from(payload)
    return ServerInfo(app_name=v[0].split(b"\0", 1)[0].decode(errors="replace"), app_version=tuple(v[1:5]),
                      natnet_version=tuple(v[5:9]), clock_hz=v[9], data_port=v[10], multicast=bool(v[11]),
                      multicast_group=".".join(map(str, v[12:16])))


def model_def(bodies: dict[int, str], version: tuple[int, ...] = NATNET_VERSION) -> bytes:
    """NAT_MODELDEF: one rigid-body description per ``{id: name}`` (no parent, no offset, no markers), laid out
    for NatNet ``version``."""
    out = [struct.pack("<i", len(bodies))]
    for body_id, name in bodies.items():
        desc = name.encode() + b"\0" + struct.pack("<ii3fi", body_id, -1, 0.0, 0.0, 0.0, 0)
        size = struct.pack("<i", len(desc)) if _sized(version) else b""
        out.append(struct.pack("<i", DATASET_RIGID_BODY) + size + desc)
    return packet(NAT_MODELDEF, b"".join(out))


class _Reader:
    """Little-endian fields from a payload; :class:`NatNetError` when it runs short."""

    def __init__(self, payload: bytes) -> None:
        self.data, self.at = payload, 0

    def take(self, fmt: str):
        try:
            values = struct.unpack_from("<" + fmt, self.data, self.at)
        except struct.error:
            raise NatNetError(f"payload ends at byte {len(self.data)}, {struct.calcsize('<' + fmt)} more wanted at "
                              f"{self.at}") from None
        self.at += struct.calcsize("<" + fmt)
        return values if len(values) > 1 else values[0]

    def text(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise NatNetError(f"an unterminated name at byte {self.at}")
        value = self.data[self.at:end].decode(errors="replace")
        self.at = end + 1
        return value

    def skip(self, n: int) -> None:
        if n < 0 or self.at + n > len(self.data):
            raise NatNetError(f"a size of {n} bytes at byte {self.at} runs past the payload ({len(self.data)})")
        self.at += n


def _rigid_body_description(r: _Reader, version: tuple[int, ...]) -> tuple[int, str]:
    """(id, name) of one rigid-body description (NatNet 3.0+: name, id, parent, offset, markers)."""
    name = r.text()
    body_id = r.take("i")
    r.take("i3f")  # parent, offset
    if tuple(version[:2]) >= (4, 2):
        r.take("4f")  # its orientation (NatNet 4.2)
    markers = r.take("i")
    r.skip(markers * 16)  # positions and required active labels
    if version[0] >= 4:
        for _ in range(markers):
            r.text()
    return body_id, name


def parse_rigid_body_names(payload: bytes, version: tuple[int, ...] = NATNET_VERSION) -> dict[int, str]:
    """``{id: name}`` of the rigid bodies in a NAT_MODELDEF payload of NatNet ``version`` (3.0 and later). From
    4.1 other descriptions are skipped by their size; before it marker sets and skeletons (whose bones are rigid
    bodies too) are walked, and a description of another kind (force plate, device, camera) ends the reading
    with the names found so far: Motive lists rigid bodies before those."""
    r = _Reader(payload)
    names: dict[int, str] = {}
    try:
        for _ in range(r.take("i")):
            kind = r.take("i")
            if _sized(version):
                size = r.take("i")
                end = r.at + size
                if kind == DATASET_RIGID_BODY:
                    body_id, name = _rigid_body_description(r, version)
                    names[body_id] = name
                r.at = end
                if end > len(payload):
                    raise NatNetError(f"a description of {size} bytes runs past the payload")
            elif kind == 0:  # marker set: name, marker names
                r.text()
                for _ in range(r.take("i")):
                    r.text()
            elif kind == DATASET_RIGID_BODY:
                body_id, name = _rigid_body_description(r, version)
                names[body_id] = name
            elif kind == 2:  # skeleton: name, id, its bones' rigid-body descriptions
                r.text()
                r.take("i")
                for _ in range(r.take("i")):
                    _rigid_body_description(r, version)
            else:
                break
        return names
    except (NatNetError, UnicodeDecodeError) as exc:
        raise NatNetError(f"model definitions unreadable: {exc}") from None


@dataclass(frozen=True, slots=True)
class Frame:
    """One NAT_FRAMEOFDATA: its number, rigid bodies (Motive's frame) and Motive's own times: ``timestamp_s``
    (s since Motive started streaming), and the high-resolution ticks (of the server's ``clock_hz``) of the
    cameras' mid-exposure, of the data reaching Motive and of its transmission."""

    number: int
    bodies: tuple[BodyPose, ...]
    timestamp_s: float
    mid_exposure_ticks: int
    received_ticks: int
    transmit_ticks: int


def frame_of_data(frame_number: int, bodies: list[BodyPose], *, timestamp_s: float, mid_exposure_ticks: int,
                  received_ticks: int, transmit_ticks: int, clock_hz: int,
                  version: tuple[int, ...] = NATNET_VERSION) -> bytes:
    """NAT_FRAMEOFDATA of NatNet ``version``: frame number, the data sets (marker sets, legacy markers, rigid
    bodies, skeletons, assets (4.1), labeled markers, force plates, devices: only rigid bodies here; from 4.1
    each count followed by its size in bytes), timecode, ``timestamp_s`` (s since the stream started), the three
    high-resolution timestamps (ticks of ``clock_hz``), from 4.1 the precision timestamp (s, fraction of a
    second in 2^-32), frame params (0) and the end-of-data tag (0)."""
    rigid = b"".join(_RIGID_BODY.pack(b.id, *b.pos_m, *b.quat_xyzw, b.mean_error_m, TRACKING_VALID if b.tracked else 0)
                     for b in bodies)
    sized = _sized(version)
    empty = struct.pack("<ii", 0, 0) if sized else struct.pack("<i", 0)
    rigid_head = struct.pack("<ii", len(bodies), len(rigid)) if sized else struct.pack("<i", len(bodies))
    secs = mid_exposure_ticks // clock_hz
    frac = (mid_exposure_ticks % clock_hz) * (1 << 32) // clock_hz
    times = struct.pack("<IIdQQQ", 0, 0, timestamp_s, mid_exposure_ticks, received_ticks, transmit_ticks)
    precision = struct.pack("<II", secs & 0xFFFFFFFF, frac) if sized else b""
    payload = b"".join((
        struct.pack("<i", frame_number),
        empty,  # marker sets
        empty,  # legacy unlabeled markers
        rigid_head, rigid,
        empty,  # skeletons
        empty if sized else b"",  # assets (4.1)
        empty,  # labeled markers
        empty,  # force plates
        empty,  # devices
        times, precision, struct.pack("<hi", 0, 0),
    ))
    return packet(NAT_FRAMEOFDATA, payload)


def _frame_rigid_body(r: _Reader) -> BodyPose:
    body_id, x, y, z, qx, qy, qz, qw, error, params = r.take("i3f4ffh")
    return BodyPose(body_id, (x, y, z), (qx, qy, qz, qw), bool(params & TRACKING_VALID), error)


def parse_frame(payload: bytes, version: tuple[int, ...] = NATNET_VERSION) -> Frame:
    """A NAT_FRAMEOFDATA payload of NatNet ``version`` (:func:`supported`) read as OptiTrack's SDK reads it: its
    rigid bodies and Motive's times; every other data set skipped (by its size from 4.1, field by field
    before). :class:`NatNetError` for a payload that is not one."""
    r = _Reader(payload)
    sized = _sized(version)

    def data_set(read_item=None) -> list:
        """One data set: its items read with ``read_item``; from 4.1 one not wanted is skipped by its size."""
        n = r.take("i")
        if not 0 <= n <= 100_000:
            raise NatNetError(f"a data set of {n} items")
        if sized:
            size = r.take("i")
            if read_item is None:
                r.skip(size)
                return []
        return [read_item() for _ in range(n)]

    def channels() -> None:  # a force plate or device: id, channels, each a count of floats
        r.take("i")
        for _ in range(r.take("i")):
            r.skip(4 * r.take("i"))

    number = r.take("i")
    data_set(None if sized else lambda: (r.text(), r.skip(12 * r.take("i"))))  # marker sets
    data_set(None if sized else lambda: r.skip(12))  # legacy unlabeled markers
    bodies = tuple(data_set(lambda: _frame_rigid_body(r)))
    data_set(None if sized else lambda: (r.take("i"), [_frame_rigid_body(r) for _ in range(r.take("i"))]))  # skeletons
    if sized:
        data_set()  # assets (4.1)
    data_set(None if sized else lambda: r.skip(26))  # labeled markers: id, position, size, params, residual
    data_set(None if sized else channels)  # force plates
    data_set(None if sized else channels)  # devices
    r.take("II")  # timecode
    timestamp_s, mid, received, transmit = r.take("dQQQ")
    return Frame(number, bodies, timestamp_s, mid, received, transmit)


def motive_pose(pos_enu_m, rpy_rad, up_axis: str) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """A body's ENU position and ZYX Euler angles (roll, pitch, yaw about ENU x, y, z of a FLU body) as
    Motive streams it with ``up_axis`` ``"y"`` or ``"z"``: (position (3,), quaternion (x, y, z, w)).
    A rigid body defined level and facing Motive's +x has the identity orientation there."""
    m = MOTIVE_FROM_ENU[up_axis]
    roll, pitch, yaw = rpy_rad
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    world_from_body = np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])
    p = m @ np.asarray(pos_enu_m, dtype=float)
    return (float(p[0]), float(p[1]), float(p[2])), quat_xyzw(m @ world_from_body @ m.T)


def quat_xyzw(r: np.ndarray) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w), w >= 0, of rotation matrix ``r`` (3, 3) (Shepperd's method)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = (0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s)
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = ((r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = ((r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s)
    sign = -1.0 if q[3] < 0 else 1.0
    return tuple(float(sign * v) for v in q)  # type: ignore[return-value]
