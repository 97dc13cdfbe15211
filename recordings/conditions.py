"""The conditions a recorded flight met, for flying it again with another network (:mod:`sim.counterfactual`).

For every stretch of consecutive samples that has a reference (the vehicle was flying a mission),
the reference and the disturbance the vehicle met, reconstructed per axis as

    f = a − (R e₃ T_applied / m − g e₃)

with ``a`` the measured position's second derivative after a zero-phase low-pass, ``R`` the measured attitude, ``T_applied``
the commanded thrust through the identified delay and lag, the recorded vehicle's mass ``m``
(:func:`recordings.dataset.recorded_mass`) and ``g``: everything the nominal model does not explain, as a
function of time.
"""
from __future__ import annotations

import numpy as np

from neso.features import ThrustLag, applied_thrust_series
from neso.learning import smoothed_acceleration, zero_phase
from neso.rotations import world_from_body_zyx
from neso.types import GRAVITY_MPS2
from recordings.dataset import _by_seq, _stretches, flight_series
from recordings.reader import Recording
from sim.counterfactual import RecordedConditions


def recorded_conditions(rec: Recording, lag: ThrustLag, *, min_duration_s: float = 3.0) -> list[RecordedConditions]:
    """Every flown stretch of the recording (at least ``min_duration_s`` long) as conditions to fly again."""
    series, seq, extra = flight_series(rec)
    ref_seq, ref = _by_seq(rec.channel("reference"), ["pos_enu_m", "vel_enu_mps", "acc_enu_mps2", "yaw_rad"])
    if len(ref_seq) == 0:
        return []
    yaw_seq, yaw = _by_seq(rec.channel("state"), ["yaw_rad"])
    yaw_by_seq = dict(zip(yaw_seq.tolist(), np.asarray(yaw["yaw_rad"], dtype=float).tolist()))
    pos = np.searchsorted(ref_seq, seq)
    has_ref = (pos < len(ref_seq)) & (ref_seq[np.minimum(pos, len(ref_seq) - 1)] == seq) & ~extra["on_ground"]
    dt = series.dt_s
    out = []
    for part in _stretches(seq):
        idx = np.arange(part.start, part.stop)
        for run in _runs(idx[has_ref[idx]]):
            if len(run) * dt < min_duration_s:
                continue
            out.append(_conditions(series, run, ref, pos[run], yaw_by_seq, seq, lag, dt))
    return out


def _runs(idx: np.ndarray) -> list[np.ndarray]:
    if len(idx) == 0:
        return []
    cuts = np.flatnonzero(np.diff(idx) != 1) + 1
    return [r for r in np.split(idx, cuts) if len(r)]


def _conditions(series, run, ref, ref_rows, yaw_by_seq, seq, lag, dt) -> RecordedConditions:
    vel = series.vel_enu_mps[run]
    acc = np.column_stack([smoothed_acceleration(series.pos_enu_m[run, i], dt) for i in range(3)])
    thrust = applied_thrust_series(series.thrust_prev_n[run], lag, dt)
    yaws = np.array([yaw_by_seq.get(int(s), 0.0) for s in seq[run]])
    z_body = np.array([world_from_body_zyx(r, p, y)[:, 2] for r, p, y in
                       zip(series.roll_rad[run], series.pitch_rad[run], yaws)])
    lift = np.column_stack([zero_phase(z_body[:, i] * thrust, dt) for i in range(3)])  # filtered like the acceleration
    nominal = lift / series.mass_kg - np.array([0.0, 0.0, GRAVITY_MPS2])
    return RecordedConditions(
        t_s=series.t_s[run] - series.t_s[run[0]],
        ref_pos_enu_m=np.asarray(ref["pos_enu_m"], dtype=float)[ref_rows],
        ref_vel_enu_mps=np.asarray(ref["vel_enu_mps"], dtype=float)[ref_rows],
        ref_acc_enu_mps2=np.asarray(ref["acc_enu_mps2"], dtype=float)[ref_rows],
        ref_yaw_rad=np.asarray(ref["yaw_rad"], dtype=float)[ref_rows],
        disturbance_enu_mps2=acc - nominal,
        pos0_enu_m=series.pos_enu_m[run[0]], vel0_enu_mps=vel[0], thrust0_n=float(series.thrust_prev_n[run[0]]),
        lag=lag, dt_s=dt, mass_kg=series.mass_kg, pos_enu_m=series.pos_enu_m[run])
