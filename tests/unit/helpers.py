"""Small builders shared by the unit tests (no fixtures with side effects)."""
from __future__ import annotations

import numpy as np

from neso.network import LipschitzMLP
from neso.types import StateMeasurement


def random_network(seed: int = 0, sizes=(5, 20, 25, 10, 1), bound: float = 10.0) -> LipschitzMLP:
    rng = np.random.default_rng(seed)
    ws = tuple(rng.normal(0, 0.5, (o, i)) for i, o in zip(sizes[:-1], sizes[1:]))
    bs = tuple(rng.normal(0, 0.1, o) for o in sizes[1:])
    net = LipschitzMLP(ws, bs, np.zeros(sizes[0]), np.ones(sizes[0]), np.zeros(sizes[-1]), np.ones(sizes[-1]), 1e9)
    return net.scaled_to_bound(bound)


def measurement(pos=(0.0, 0.0, 1.0), vel=(0.0, 0.0, 0.0), t_s=0.0, roll=0.0, pitch=0.0) -> StateMeasurement:
    return StateMeasurement(t_s=t_s, pos_enu_m=np.array(pos, float), vel_enu_mps=np.array(vel, float),
                            roll_rad=roll, pitch_rad=pitch, yaw_rad=0.0)
