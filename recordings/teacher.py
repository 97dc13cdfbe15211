"""The ESO teacher run offline over any recording: per-sample state, thrust and the ESO's f̂.

A recording with estimates has its teacher labels already (the f̂ flown under the ``eso`` pathway);
one without (a PX4 log imported, a flight under another estimator) gets them here: the estimator
service's own step object (:class:`flight.estimator.EstimatorCore`, pathway ``eso``, no network)
runs over the recorded states and setpoints exactly as ``--what-if`` runs it
(:func:`recordings.offline.run_estimator`), restarting after every gap in the states.

:func:`eso_teacher` returns arrays, one row per state sample, so other label kinds can be built on
them (the state and the thrust are there to build any network input from; the arrays carry the
names of a ``FlightSeries``: ``t_s``, ``pos_enu_m``, ``vel_enu_mps``, ``roll_rad``, ``pitch_rad``,
``thrust_prev_n``, ``f_hat_mps2``, ``pathway``).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from neso.types import OMEGA_O_RPS
from recordings.offline import GAP_PERIODS, run_estimator
from recordings.reader import Recording, RecordingError


@dataclass(frozen=True)
class TeacherRun:
    """One row per recorded state sample (N). Frames ENU/FLU, SI."""

    seq: np.ndarray  # (N,) int
    t_s: np.ndarray  # (N,)
    pos_enu_m: np.ndarray  # (N, 3)
    vel_enu_mps: np.ndarray  # (N, 3)
    attitude_rad: np.ndarray  # (N, 3) roll, pitch, yaw
    thrust_n: np.ndarray  # (N,) commanded over the period after the sample (NaN: no setpoint recorded)
    thrust_prev_n: np.ndarray  # (N,) commanded over the period before it (what the ESO was told; NaN: none)
    f_hat_mps2: np.ndarray  # (N, 3) the ESO's x̂₃ (NaN where the step object gave none)
    warm: np.ndarray  # (N,) bool: the observer had run skip_s since its (re)start
    airborne: np.ndarray  # (N,) bool: not on the ground (truth, telemetry, or thrust commanded)
    omega_o_rps: float
    pathway: str = "eso"  # the labels' pathway (the observer alone)

    def __len__(self) -> int:
        return len(self.t_s)

    # the fields of neso.learning.FlightSeries (issue 11) by their names there
    @property
    def roll_rad(self) -> np.ndarray:
        return self.attitude_rad[:, 0]

    @property
    def pitch_rad(self) -> np.ndarray:
        return self.attitude_rad[:, 1]


def _on_ground(rec: Recording, vehicle: str | None, seq: np.ndarray, stamp: np.ndarray, thrust_n: np.ndarray):
    """(N,) bool: the simulator's truth says so, the vehicle reports it is not in the air (telemetry,
    held from the newest report), or no thrust was commanded."""
    on_ground = ~(thrust_n > 0)
    truth = rec.channel("truth", vehicle)
    if len(truth):
        ground = dict(zip(np.asarray(truth.columns["seq"], dtype=np.int64), np.asarray(truth.columns["on_ground"])))
        on_ground |= np.array([bool(ground.get(s, False)) for s in seq])
    tel = rec.channel("telemetry", vehicle)
    if len(tel):
        ts = np.asarray(tel.columns["stamp_s"], dtype=float)
        order = np.argsort(ts, kind="stable")
        i = np.searchsorted(ts[order], stamp, side="right") - 1
        in_air = np.asarray(tel.columns["in_air"], dtype=bool)[order]
        on_ground |= np.where(i >= 0, ~in_air[np.clip(i, 0, None)], True)
    return on_ground


def eso_teacher(rec: Recording, *, omega_o_rps: float = OMEGA_O_RPS, skip_s: float = 0.5, vehicle: str | None = None,
                gap_periods: float = GAP_PERIODS) -> TeacherRun:
    """The ESO (pathway ``eso``, observer bandwidth ``omega_o_rps``) over ``rec``'s states and
    setpoints; :class:`RecordingError` if it has no states or no setpoints."""
    from flight.estimator import EstimatorConfig, EstimatorCore, NetworkChoice

    states, setpoints = rec.channel("state", vehicle).messages(), rec.channel("setpoint", vehicle).messages()
    if not states or not setpoints:
        raise RecordingError(f"{rec.path}: the ESO teacher needs recorded states and setpoints "
                             f"({len(states)} states, {len(setpoints)} setpoints)")
    config = EstimatorConfig(network="", pathway="eso", omega_o_rps=omega_o_rps)
    ours = run_estimator(states, setpoints, lambda dt_s: EstimatorCore(dataclasses.replace(config, dt_s=dt_s), None,
                                                                       NetworkChoice(None, "none", None),
                                                                       clock=time.monotonic),
                         gap_periods=gap_periods)
    seq = np.array([m.seq for m in states], dtype=np.int64)
    t = np.array([m.t_s for m in states])
    sp = {m.seq: m.thrust_n for m in setpoints}
    thrust = np.array([sp.get(int(s), np.nan) for s in seq])
    nan3 = (np.nan,) * 3
    est = [ours.get(int(s)) for s in seq]
    f_hat = np.array([e.f_hat_mps2 if e is not None else nan3 for e in est])
    warm_ticks = np.array([e.warm_ticks if e is not None else 0 for e in est])
    dt = np.median(np.diff(t)) if len(t) > 1 else 0.02
    thrust_prev = np.array([sp.get(int(s) - 1, np.nan) for s in seq])
    stamp = np.array([m.stamp_s for m in states])
    return TeacherRun(seq=seq, t_s=t, pos_enu_m=np.array([m.pos_enu_m for m in states]),
                      vel_enu_mps=np.array([m.vel_enu_mps for m in states]),
                      attitude_rad=np.array([(m.roll_rad, m.pitch_rad, m.yaw_rad) for m in states]),
                      thrust_n=thrust, thrust_prev_n=thrust_prev, f_hat_mps2=f_hat,
                      warm=(warm_ticks * dt >= skip_s) & np.all(np.isfinite(f_hat), axis=1),
                      airborne=~_on_ground(rec, vehicle, seq, stamp, thrust), omega_o_rps=omega_o_rps)
