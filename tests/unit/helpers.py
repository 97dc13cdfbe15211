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


def paper_error_system(kp: float, kd: float, omega_o: float) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (5×5), ``b`` (5,) of ``Ė = AE + bΔḟ``, ``E = [e, ė, x̃1, x̃2, f̃]``, one axis, written out from the
    paper (``ë = −k_p e − k_d ė − f̃``; observer poles at ``−ω_o``), independently of :mod:`neso.certificate`."""
    a = np.zeros((5, 5))
    a[0, 1], a[1, 0], a[1, 1], a[1, 4] = 1.0, -kp, -kd, -1.0
    w = omega_o
    a[2:, 2:] = [[-3 * w, 1.0, 0.0], [-3 * w * w, 0.0, 1.0], [-(w**3), 0.0, 0.0]]
    return a, np.array([0.0, 0.0, 0.0, 0.0, 1.0])


def lemma1_bound(inp, e: np.ndarray) -> np.ndarray:
    """Lemma 1's bound on ``|Δḟ|`` (m/s³) at error states ``e`` (rows of 5), corrected ``λ_c``."""
    lam_c = np.hypot(inp.kp, inp.kd + 1.0)
    return inp.lipschitz * (lam_c * np.linalg.norm(e[:, :2], axis=1) + np.linalg.norm(e[:, 2:], axis=1)) + inp.C_f


def worst_case_run(inp, p: np.ndarray, e0: np.ndarray, *, dt_s: float = 1e-3, steps: int = 8000,
                   every: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """The error system driven by the ``Δḟ`` that raises ``V = EᵀPE`` fastest within Lemma 1 (``|Δḟ|`` at its
    bound, sign of ``∂V̇/∂Δḟ``, + at 0), fixed-step RK4 from the rows of ``e0`` (N×5). Returns ``t_s`` (K,) and
    the states (K×N×5) every ``every`` steps."""
    a, b = paper_error_system(inp.kp, inp.kd, inp.omega_o)

    def rhs(x: np.ndarray) -> np.ndarray:
        s = np.where(x @ p @ b >= 0, 1.0, -1.0)
        return x @ a.T + np.outer(s * lemma1_bound(inp, x), b)

    e = np.array(e0, dtype=float)
    ts, out = [], []
    for k in range(1, steps + 1):
        k1 = rhs(e)
        k2 = rhs(e + 0.5 * dt_s * k1)
        k3 = rhs(e + 0.5 * dt_s * k2)
        e = e + dt_s / 6 * (k1 + 2 * k2 + 2 * k3 + rhs(e + dt_s * k3))
        if k % every == 0:
            ts.append(k * dt_s)
            out.append(e.copy())
    return np.array(ts), np.array(out)
