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


def velocity_feedback_network(gain: float, *, vehicle: str = "uav1", sizes=(5, 20, 25, 10, 1)) -> LipschitzMLP:
    """A deliberately bad network of the shipped network's shape and inputs (state_speed@1, v_z is input 1):
    f_N = ``gain``·v_z exactly. A negative gain takes damping away from the altitude loop (its Lipschitz
    constant |gain|, certified from the weights as 2·|gain|, is far outside the stability certificate, so it
    flies only by force)."""
    ws = [np.zeros((o, i)) for i, o in zip(sizes[:-1], sizes[1:])]
    ws[0][0, 1], ws[0][1, 1] = 1.0, -1.0  # relu(v_z), relu(−v_z)
    for w in ws[1:-1]:
        w[0, 0] = w[1, 1] = 1.0  # passed on unchanged (both are ≥ 0)
    ws[-1][0, 0], ws[-1][0, 1] = gain, -gain
    bs = [np.zeros(o) for o in sizes[1:]]
    meta = {"id": f"velocity-feedback{gain:g}", "feature_set": "state_speed@1", "val_loss": "0.1", "vehicle": vehicle}
    return LipschitzMLP(tuple(ws), tuple(bs), np.zeros(sizes[0]), np.ones(sizes[0]), np.zeros(1), np.ones(1),
                        2.0 * abs(gain), meta, "physical")
