"""NatNet, OptiTrack Motive's streaming protocol, as packets: built for the simulated Motive
(:mod:`sim.natnet_server`) and read where a client must check what a server offers.

Pure: bytes in, bytes out; no sockets. Layouts follow OptiTrack's published parsers (NatNet SDK
4.1 ``PacketClient.cpp``/``NatNetClient.py``, the ``natnetsdk`` package) and the reader we fly,
libmotioncapture 1.1's ``src/optitrack.cpp``. Every packet is ``uint16 message id, uint16 payload
bytes, payload``, little-endian. We speak NatNet **4.1** (Motive 3.1 and later): counts of the
frame's data sets and of each model description are followed by their size in bytes.

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
MOTIVE_VERSION = (3, 1, 0, 0)  # the application version a NatNet 4.1 server reports
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


def server_info(*, data_port: int, multicast: bool, multicast_group: str, clock_hz: int,
                app_name: str = "Motive") -> bytes:
    """NAT_SERVERINFO (``sSender_Server``): the answer to NAT_CONNECT."""
    group = [int(b) for b in multicast_group.split(".")]
    return packet(NAT_SERVERINFO, _SERVER_INFO.pack(app_name.encode()[:255], *MOTIVE_VERSION, *NATNET_VERSION,
                                                    clock_hz, data_port, int(multicast), *group))


def parse_server_info(payload: bytes) -> ServerInfo:
    if len(payload) < _SERVER_INFO.size:
        raise NatNetError(f"server info of {len(payload)} bytes, NatNet's has {_SERVER_INFO.size}")
    v = _SERVER_INFO.unpack_from(payload)
    return ServerInfo(app_name=v[0].split(b"\0", 1)[0].decode(errors="replace"), app_version=tuple(v[1:5]),
                      natnet_version=tuple(v[5:9]), clock_hz=v[9], data_port=v[10], multicast=bool(v[11]),
                      multicast_group=".".join(map(str, v[12:16])))


def model_def(bodies: dict[int, str]) -> bytes:
    """NAT_MODELDEF: one rigid-body description per ``{id: name}`` (no parent, no offset, no markers)."""
    out = [struct.pack("<i", len(bodies))]
    for body_id, name in bodies.items():
        desc = name.encode() + b"\0" + struct.pack("<ii3fi", body_id, -1, 0.0, 0.0, 0.0, 0)
        out.append(struct.pack("<ii", DATASET_RIGID_BODY, len(desc)) + desc)
    return packet(NAT_MODELDEF, b"".join(out))


def parse_rigid_body_names(payload: bytes) -> dict[int, str]:
    """``{id: name}`` of the rigid bodies in a NatNet 4.1 NAT_MODELDEF payload (other data sets skipped
    by their size)."""
    try:
        (n,), at = struct.unpack_from("<i", payload), 4
        names = {}
        for _ in range(n):
            kind, size = struct.unpack_from("<ii", payload, at)
            at += 8
            if kind == DATASET_RIGID_BODY:
                end = payload.index(b"\0", at)
                (body_id,) = struct.unpack_from("<i", payload, end + 1)
                names[body_id] = payload[at:end].decode(errors="replace")
            at += size
        return names
    except (struct.error, ValueError) as exc:
        raise NatNetError(f"model definitions unreadable: {exc}") from None


def frame_of_data(frame_number: int, bodies: list[BodyPose], *, timestamp_s: float, mid_exposure_ticks: int,
                  received_ticks: int, transmit_ticks: int, clock_hz: int) -> bytes:
    """NAT_FRAMEOFDATA, NatNet 4.1: frame number, the data sets (marker sets, legacy markers, rigid
    bodies, skeletons, assets, labeled markers, force plates, devices: only rigid bodies here, each count
    followed by its size in bytes), timecode, ``timestamp_s`` (s since the stream started), the three
    high-resolution timestamps (ticks of ``clock_hz``), the precision timestamp (s, fraction of a
    second in 2^-32), frame params (0) and the end-of-data tag (0)."""
    rigid = b"".join(_RIGID_BODY.pack(b.id, *b.pos_m, *b.quat_xyzw, b.mean_error_m, TRACKING_VALID if b.tracked else 0)
                     for b in bodies)
    empty = struct.pack("<ii", 0, 0)
    secs = mid_exposure_ticks // clock_hz
    frac = (mid_exposure_ticks % clock_hz) * (1 << 32) // clock_hz
    payload = b"".join((
        struct.pack("<i", frame_number),
        empty,  # marker sets
        empty,  # legacy unlabeled markers
        struct.pack("<ii", len(bodies), len(rigid)), rigid,
        empty,  # skeletons
        empty,  # assets
        empty,  # labeled markers
        empty,  # force plates
        empty,  # devices
        struct.pack("<IIdQQQIIhi", 0, 0, timestamp_s, mid_exposure_ticks, received_ticks, transmit_ticks,
                    secs & 0xFFFFFFFF, frac, 0, 0),
    ))
    return packet(NAT_FRAMEOFDATA, payload)


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
