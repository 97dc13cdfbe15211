"""Training pairs from flight recordings (paper Sec. V-C and Experiment 3, and this project's labels).

A recording becomes a :class:`neso.learning.FlightSeries` — the samples the estimator saw: the
recorded states, the thrust commanded at the sample before each (the setpoints), and the
estimator's f̂ and pathway when it recorded them — and the pairs are made by the same functions
the simulated pipeline uses: the inputs of a feature set (:mod:`neso.features`), built from the
recorded state and thrust whatever network flew, and a label (:mod:`neso.learning`):

- ``eso``: the ESO teacher, ``x̂_3`` = f̂ while the estimator's pathway was ``eso``; a recording with
  no estimates (an imported PX4 log) gets them from the ESO run offline over its recorded state and
  thrust (:func:`recordings.teacher.eso_teacher`);
- ``tdr``: total disturbance reconstruction, ``f_N + Δf̂`` while it flew ``neural_eso``;
- ``applied``: the lag-consistent label from the smoothed measured acceleration and the applied
  thrust (any pathway), with the thrust lag identified on the same recordings unless given.

The thrust in newtons is for the recording's own vehicle: its mass is the imported log's
(``import.mass_kg``) or the controller's ``mass_kg`` parameter recorded at the start of a live flight
(:func:`recorded_mass`), so a label in m/s² does not depend on the mass given (an import's newtons scale
with it). Samples are skipped while the vehicle was on the ground (the simulator's truth says so, the
vehicle's telemetry says it is not in the air, or the setpoint commanded no thrust); for the ESO labels while the estimator was not warm (its first
``skip_s`` after a (re)start) or flew another pathway than the label needs; for ``applied`` within
``skip_s`` of the start of a stretch of consecutive samples (the smoothing's edges).
"""
from __future__ import annotations

import dataclasses

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neso.features import DEFAULT_FEATURE_SET, FeatureSet, ThrustLag, feature_set
from neso.learning import LABEL_PATHWAYS, LABELS, FlightSeries, features, identify_thrust_lag, labels
from neso.types import VehicleModel
from recordings.reader import Recording, RecordingError, read_recording


@dataclass(frozen=True)
class TrainingSet:
    z: np.ndarray  # (N, n) the feature set's inputs
    y_mps2: np.ndarray  # (N,) z-axis label, m/s²
    label: str  # one of neso.learning.LABELS
    feature_set: str  # "name@version"
    thrust_lag: ThrustLag  # the applied-thrust model identified (or given): inputs, labels and predictions use it
    recordings: tuple[str, ...]  # the files it came from
    vehicle: str
    mass_kg: float = VehicleModel().mass_kg  # the vehicle's mass the recordings' thrust is for
    lag_source: str = "given"  # how thrust_lag was found
    regressors: str = "state"  # what the tracked-state inputs came from (neso.learning.REGRESSORS, or why not)

    def __len__(self) -> int:
        return len(self.y_mps2)


@dataclass(frozen=True)
class Selection:
    """What one recording gave: the pairs kept, how many samples each rule dropped, and the kept pairs' ``seq``."""

    z: np.ndarray
    y_mps2: np.ndarray
    estimates: int
    dropped: dict[str, int]
    seq: np.ndarray | None = None  # (N,) the state sample of each kept pair


def _last_by_seq(seqs: np.ndarray) -> np.ndarray:
    """Indices of the last row of every ``seq`` (a re-sent sample is answered again); sorted by seq."""
    if len(seqs) == 0:
        return np.zeros(0, dtype=int)
    order = np.argsort(seqs, kind="stable")
    s = seqs[order]
    return order[np.append(s[1:] != s[:-1], True)]


def _by_seq(channel, names: list[str]) -> tuple[np.ndarray, dict[str, object]]:
    if len(channel) == 0:
        return np.zeros(0, dtype=np.int64), {}
    seq = np.asarray(channel.columns["seq"], dtype=np.int64)
    rows = _last_by_seq(seq)
    out = {}
    for n in names:
        col = channel.columns[n]
        out[n] = np.asarray(col)[rows] if not isinstance(col, list) else np.array(col, dtype=object)[rows]
    return seq[rows], out


def recorded_mass(rec: Recording) -> tuple[float, str]:
    """(mass kg, where it came from) of the vehicle a recording flew: an imported log's ``import.mass_kg``
    (``--mass-kg``, or the nominal model's when it was assumed), a live flight's controller parameter
    ``mass_kg`` at its start; else the controller's nominal model (``assumed``)."""
    info = rec.properties.get("import") or {}
    if isinstance(info.get("mass_kg"), (int, float)) and info["mass_kg"] > 0:
        return float(info["mass_kg"]), "import (assumed)" if info.get("mass_assumed") else "import"
    controller = (rec.properties.get("params") or {}).get("controller") or {}
    if isinstance(controller, dict) and isinstance(controller.get("mass_kg"), (int, float)) and controller["mass_kg"] > 0:
        return float(controller["mass_kg"]), "controller"
    return VehicleModel().mass_kg, "assumed (nominal model)"


def _not_in_air(rec: Recording, vehicle: str | None, stamps_s: np.ndarray) -> np.ndarray:
    """(N,) True where the vehicle's newest telemetry at or before each stamp says it is not in the air
    (PX4's land detector; no telemetry: all False)."""
    tel = rec.channel("telemetry", vehicle)
    if len(tel) == 0:
        return np.zeros(len(stamps_s), dtype=bool)
    t = np.asarray(tel.columns["stamp_s"], dtype=float)
    order = np.argsort(t, kind="stable")
    t, in_air = t[order], np.asarray(tel.columns["in_air"]).astype(bool)[order]
    idx = np.searchsorted(t, stamps_s, side="right") - 1
    return np.where(idx >= 0, ~in_air[np.maximum(idx, 0)], True)


def flight_series(rec: Recording, vehicle: str | None = None) -> tuple[FlightSeries, np.ndarray, dict]:
    """The recording's samples as the estimator saw them: (series, seq (N,), extras) where extras
    holds ``warm_ticks`` (N,; −1 without an estimate) and ``on_ground`` (N,) bool."""
    seq, st = _by_seq(rec.channel("state", vehicle), ["t_s", "stamp_s", "pos_enu_m", "vel_enu_mps", "roll_rad",
                                                      "pitch_rad"])
    if len(seq) == 0:
        raise RecordingError(f"{rec.path}: no states recorded")
    sp_seq, sp = _by_seq(rec.channel("setpoint", vehicle), ["thrust_n"])
    est_seq, est = _by_seq(rec.channel("estimate", vehicle), ["f_hat_mps2", "pathway", "warm_ticks"])
    tr_seq, tr = _by_seq(rec.channel("truth", vehicle), ["on_ground"])
    ref_seq, ref = _by_seq(rec.channel("reference", vehicle), ["pos_enu_m", "vel_enu_mps"])
    thrust_by_seq = dict(zip(sp_seq.tolist(), np.asarray(sp.get("thrust_n", []), dtype=float).tolist()))
    thrust_prev = np.empty(len(seq))
    last = next(iter(thrust_by_seq.values()), 0.0)
    for i, s in enumerate(seq.tolist()):  # the setpoint that acted over the period before the sample
        last = thrust_by_seq.get(s - 1, last)
        thrust_prev[i] = last
    f_hat = np.full((len(seq), 3), np.nan)
    pathway = np.full(len(seq), None, dtype=object)
    warm = np.full(len(seq), -1, dtype=np.int64)
    if len(est_seq):
        pos = np.searchsorted(est_seq, seq)
        hit = (pos < len(est_seq)) & (est_seq[np.minimum(pos, len(est_seq) - 1)] == seq)
        f_hat[hit] = np.asarray(est["f_hat_mps2"])[pos[hit]]
        pathway[hit] = est["pathway"][pos[hit]]
        warm[hit] = np.asarray(est["warm_ticks"])[pos[hit]]
    ref_pos, ref_vel = np.full((len(seq), 3), np.nan), np.full((len(seq), 3), np.nan)
    if len(ref_seq):  # the reference the controller tracked at each sample (none in an imported log)
        pos = np.searchsorted(ref_seq, seq)
        hit = (pos < len(ref_seq)) & (ref_seq[np.minimum(pos, len(ref_seq) - 1)] == seq)
        ref_pos[hit] = np.asarray(ref["pos_enu_m"], dtype=float)[pos[hit]]
        ref_vel[hit] = np.asarray(ref["vel_enu_mps"], dtype=float)[pos[hit]]
    on_ground = np.zeros(len(seq), dtype=bool)
    if len(tr_seq):
        ground = dict(zip(tr_seq.tolist(), np.asarray(tr["on_ground"]).astype(bool).tolist()))
        on_ground |= np.array([ground.get(s, False) for s in seq.tolist()])
    if thrust_by_seq:
        on_ground |= np.array([thrust_by_seq.get(s, 1.0) <= 0 for s in seq.tolist()])
    on_ground |= _not_in_air(rec, vehicle, np.asarray(st["stamp_s"], dtype=float))
    series = FlightSeries(t_s=np.asarray(st["t_s"], dtype=float), pos_enu_m=np.asarray(st["pos_enu_m"], dtype=float),
                          vel_enu_mps=np.asarray(st["vel_enu_mps"], dtype=float),
                          roll_rad=np.asarray(st["roll_rad"], dtype=float),
                          pitch_rad=np.asarray(st["pitch_rad"], dtype=float), thrust_prev_n=thrust_prev,
                          f_hat_mps2=f_hat, pathway=pathway, mass_kg=recorded_mass(rec)[0], ref_pos_enu_m=ref_pos,
                          ref_vel_enu_mps=ref_vel)
    return series, seq, {"warm_ticks": warm, "on_ground": on_ground}


def _stretches(seq: np.ndarray) -> list[slice]:
    """Runs of consecutive sample numbers (a restarted source or dropped samples break them)."""
    if len(seq) == 0:
        return []
    cuts = np.flatnonzero(np.diff(seq) != 1) + 1
    bounds = [0, *cuts.tolist(), len(seq)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _sub(series: FlightSeries, part: slice) -> FlightSeries:
    return dataclasses.replace(
        series, t_s=series.t_s[part], pos_enu_m=series.pos_enu_m[part], vel_enu_mps=series.vel_enu_mps[part],
        roll_rad=series.roll_rad[part], pitch_rad=series.pitch_rad[part], thrust_prev_n=series.thrust_prev_n[part],
        f_hat_mps2=series.f_hat_mps2[part], pathway=None if series.pathway is None else series.pathway[part],
        ref_pos_enu_m=None if series.ref_pos_enu_m is None else series.ref_pos_enu_m[part],
        ref_vel_enu_mps=None if series.ref_vel_enu_mps is None else series.ref_vel_enu_mps[part])


def select(rec: Recording, label: str, fset: FeatureSet, lag: ThrustLag, *, skip_s: float = 0.5,
           vehicle: str | None = None, regressors: str = "state") -> Selection:
    """The training pairs of one recording (see the module docstring for the rules); ``regressors``: what the
    tracked-state inputs are taken from (:data:`neso.learning.REGRESSORS`)."""
    if label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    try:
        series, seq, extra = flight_series(rec, vehicle)
    except RecordingError:
        return Selection(np.zeros((0, fset.size)), np.zeros(0), 0, {"no states recorded": 0})
    if label == "eso" and not np.any(extra["warm_ticks"] >= 0):  # no estimates: the ESO runs offline
        series, extra = _offline_teacher(rec, series, seq, extra, skip_s, vehicle)
    dt = series.dt_s
    zs, ys, masks = [], [], []
    for part in _stretches(seq):  # labels are smoothed along a stretch, never across a gap
        sub = _sub(series, part)
        zs.append(features(sub, fset, lag, regressors))
        ys.append(labels(sub, label, lag))
        masks.append(sub.t_s >= sub.t_s[0] + skip_s)
    z, y, settled = np.concatenate(zs), np.concatenate(ys), np.concatenate(masks)
    needs = LABEL_PATHWAYS[label]
    if needs is None:  # a label made from measurements: its smoothing needs settled edges
        ok_warm, ok_pathway, why = settled, np.ones(len(seq), dtype=bool), "start of a stretch"
    else:
        ok_warm, ok_pathway, why = extra["warm_ticks"] * dt >= skip_s, np.isin(series.pathway, needs), "estimator not warm"
    keep = ok_warm & ok_pathway & ~extra["on_ground"] & np.isfinite(y)
    dropped = {why: int(np.sum(~ok_warm)),
               f"pathway not {'/'.join(needs or ())}": int(np.sum(ok_warm & ~ok_pathway)),
               "on the ground": int(np.sum(ok_warm & ok_pathway & extra["on_ground"]))}
    return Selection(z[keep], y[keep], len(seq), dropped, seq[keep])


def _offline_teacher(rec: Recording, series: FlightSeries, seq: np.ndarray, extra: dict, skip_s: float,
                     vehicle: str | None) -> tuple[FlightSeries, dict]:
    """The series with the ESO teacher's f̂ run offline over the recorded states and setpoints (a
    recording with no estimates, e.g. an imported PX4 log; :func:`recordings.teacher.eso_teacher`)."""
    from recordings.teacher import eso_teacher

    run = eso_teacher(rec, skip_s=skip_s, vehicle=vehicle)
    row = {int(s): i for i, s in enumerate(run.seq)}
    idx = np.array([row.get(int(s), -1) for s in seq])
    hit = idx >= 0
    f_hat = np.full((len(seq), 3), np.nan)
    f_hat[hit] = run.f_hat_mps2[idx[hit]]
    warm = np.where(hit & run.warm[np.maximum(idx, 0)], np.iinfo(np.int32).max, 0)  # the teacher says warm or not
    on_ground = extra["on_ground"] | ~(hit & run.airborne[np.maximum(idx, 0)])
    series = dataclasses.replace(series, f_hat_mps2=f_hat, pathway=np.full(len(seq), "eso", dtype=object))
    return series, {"warm_ticks": warm, "on_ground": on_ground}


def load_training_set(paths, label: str, *, feature_set_key: str = DEFAULT_FEATURE_SET,
                      lag: ThrustLag | None = None, skip_s: float = 0.5, regressors: str = "state") -> TrainingSet:
    """Training pairs from one or more ``.rrd`` files (a path or a list of them) of one vehicle.
    ``lag``: the applied-thrust model (None: identified on these recordings; the closed-loop prediction
    flies it whatever the label; when there is no airborne stretch to identify it on, a label and inputs
    that need it are refused, the others get no lag and say so in ``lag_source``). Raises :class:`RecordingError` naming the file and the reasons when a file gives
    no usable sample, or when the files record different vehicles."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise ValueError("no recordings given")
    fset = feature_set(feature_set_key)
    recs = [read_recording(p) for p in paths]
    vehicles = {r.vehicle for r in recs}
    if len(vehicles) != 1:
        raise RecordingError(f"recordings of different vehicles {sorted(vehicles)}: train one vehicle at a time")
    masses = {recorded_mass(r)[0] for r in recs}
    if len(masses) != 1:
        raise RecordingError(f"recordings of different vehicle masses {sorted(masses)} kg: train one vehicle at a time")
    lag_source = "given"
    if lag is None:
        try:
            fit = identify_thrust_lag(_airborne_series(recs))
            lag, lag_source = fit.lag, (fit.note if fit.at_edge else "identified")
        except RecordingError as exc:
            if label == "applied" or fset.uses_applied_thrust:
                raise
            lag, lag_source = ThrustLag(), f"none ({exc})"
    zs, ys = [], []
    for path, rec in zip(paths, recs):
        sel = select(rec, label, fset, lag, skip_s=skip_s, regressors=regressors)
        if len(sel.y_mps2) == 0:
            reasons = ", ".join(f"{n} {why}" for why, n in sel.dropped.items() if n) or "no estimates recorded"
            raise RecordingError(f"{path}: no usable {label!r} samples out of {sel.estimates} samples ({reasons})")
        zs.append(sel.z)
        ys.append(sel.y_mps2)
    z = np.ascontiguousarray(np.concatenate(zs), dtype=float)
    y = np.ascontiguousarray(np.concatenate(ys), dtype=float)
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(y))):
        raise RecordingError(f"non-finite values in the training pairs from {paths}")
    used = regressors
    if regressors == "reference" and any(len(r.channel("reference")) == 0 for r in recs):
        used = "state where no reference was recorded (an imported log)"
    return TrainingSet(z=z, y_mps2=y, label=label, feature_set=fset.key, thrust_lag=lag, recordings=tuple(paths),
                       vehicle=vehicles.pop(), mass_kg=masses.pop(), lag_source=lag_source, regressors=used)


def _airborne_series(recs: list[Recording]) -> list[FlightSeries]:
    """The airborne stretches of the recordings (for identifying the thrust response)."""
    out = []
    for rec in recs:
        try:
            series, seq, extra = flight_series(rec)
        except RecordingError:
            continue
        for part in _stretches(seq):
            idx = np.arange(part.start, part.stop)
            air = idx[~extra["on_ground"][idx]]
            if len(air) > 50:
                out.append(_sub(series, slice(air[0], air[-1] + 1)))
    if not out:
        raise RecordingError("no airborne stretch of at least 1 s to identify the thrust response on")
    return out
