"""Rotation helpers (ZYX Euler, ENU world / FLU body). Pure numpy, no state."""
from __future__ import annotations

import math

import numpy as np


def world_from_body_zyx(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Rotation matrix (3, 3) taking body-frame vectors to the world frame: Rz(yaw) Ry(pitch) Rx(roll)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def euler_zyx_from_world_from_body(world_from_body: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of a rotation matrix (3, 3); pitch in [-pi/2, pi/2]."""
    r = world_from_body
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return roll, pitch, yaw
