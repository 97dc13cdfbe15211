"""The network's input vector z and the labels it learns from (paper Sec. III-A, V-C).

z_k = [pos_z, vel_z, previous thrust, roll, pitch] — position and velocity measured,
thrust the one commanded at the previous sample (the paper's T_{k−1}), no acceleration.
"""
from __future__ import annotations

import numpy as np

from neso.types import StateMeasurement

FEATURE_NAMES = ("pos_z_m", "vel_z_mps", "thrust_prev_n", "roll_rad", "pitch_rad")
N_FEATURES = len(FEATURE_NAMES)



def network_features(meas: StateMeasurement, thrust_prev_n: float) -> np.ndarray:
    """z (5,) from one measurement and the thrust (N) commanded at the previous sample."""
    return np.array(
        [meas.pos_enu_m[2], meas.vel_enu_mps[2], thrust_prev_n, meas.roll_rad, meas.pitch_rad]
    )


def acceleration_labels(vel_mps: np.ndarray, acc_cmd_mps2: np.ndarray, dt_s: float, *, cutoff_hz: float | None = 5.0) -> np.ndarray:
    """Neural-Lander-style labels: measured minus commanded z acceleration.

    ``vel_mps`` (N,) measured z velocity, ``acc_cmd_mps2`` (N,) the nominal acceleration the
    command applied over [k, k+1). The measured acceleration is the forward difference
    (v_{k+1} − v_k)/Δ, so the result has N − 1 rows (the last sample has no successor).

    Labels are made offline, so the velocity is first low-passed with a zero-phase
    2nd-order Butterworth at ``cutoff_hz`` (no lag); ``None`` keeps the raw difference. Raw
    differences of motion-capture velocity are noise-dominated (σ ≈ 5 m/s² here) and a
    network trained on them made PD+NN diverge — the noise the paper avoids by not using
    acceleration at all.
    """
    vel = np.asarray(vel_mps, dtype=float)
    if cutoff_hz is not None:
        from scipy.signal import butter, filtfilt  # offline only: keep it out of the loop's start-up

        b, a = butter(2, cutoff_hz / (0.5 / dt_s))
        vel = filtfilt(b, a, vel)
    acc_meas = np.diff(vel) / dt_s
    return acc_meas - np.asarray(acc_cmd_mps2)[:-1]
