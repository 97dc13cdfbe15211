"""ENU/FLU (this project) ⇄ NED/FRD (PX4, MAVLink) attitude conversions. Pure numpy, no state.

``ned_from_enu`` swaps x/y and flips z; ``flu_from_frd`` flips y and z. A body attitude
``R_enu_flu`` (ZYX Euler roll, pitch, yaw) is ``R_ned_frd = T R_enu_flu B`` in PX4's frames
(``T``, ``B`` are their own inverses). For small angles this is roll → roll, pitch → −pitch,
yaw → π/2 − yaw. Quaternions are (w, x, y, z), Hamilton, ``world_from_body``.
"""
from __future__ import annotations

import math

import numpy as np

from neso.rotations import euler_zyx_from_world_from_body, world_from_body_zyx

NED_FROM_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
FLU_FROM_FRD = np.diag([1.0, -1.0, -1.0])


def attitude_ned_from_enu(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float]:
    """ZYX Euler (rad) of an ENU/FLU attitude, expressed as NED/FRD."""
    r = NED_FROM_ENU @ world_from_body_zyx(roll_rad, pitch_rad, yaw_rad) @ FLU_FROM_FRD
    return euler_zyx_from_world_from_body(r)


def attitude_enu_from_ned(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float]:
    """ZYX Euler (rad) of a NED/FRD attitude, expressed as ENU/FLU."""
    r = NED_FROM_ENU @ world_from_body_zyx(roll_rad, pitch_rad, yaw_rad) @ FLU_FROM_FRD
    return euler_zyx_from_world_from_body(r)


def quat_from_matrix(r: np.ndarray) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation matrix (3, 3), w ≥ 0."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    sign = -1.0 if q[0] < 0 else 1.0
    return tuple(float(sign * v) for v in q)


def matrix_from_quat(q_wxyz) -> np.ndarray:
    w, x, y, z = (float(v) for v in q_wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quat_ned_from_enu_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """The NED/FRD quaternion (w, x, y, z) of an ENU/FLU ZYX-Euler attitude."""
    return quat_from_matrix(NED_FROM_ENU @ world_from_body_zyx(roll_rad, pitch_rad, yaw_rad) @ FLU_FROM_FRD)


def quat_to_euler_ned(q_wxyz) -> tuple[float, float, float]:
    """ZYX Euler (rad) of a quaternion, in the quaternion's own frames."""
    return euler_zyx_from_world_from_body(matrix_from_quat(q_wxyz))


def tilt_rad(roll_rad: float, pitch_rad: float) -> float:
    """Angle between the body z axis and the vertical (rad) for ZYX roll and pitch."""
    return math.acos(max(-1.0, min(1.0, math.cos(roll_rad) * math.cos(pitch_rad))))
