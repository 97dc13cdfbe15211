"""Training pairs from flight recordings, as the paper builds them (Sec. V-C, Experiment 3).

Input: the network input ``z`` (5,) the estimator published with each estimate (the paper's
``[p_z, v_z, T_{k−1}, φ, θ]``, see ``neso.features``). Label (z axis, m/s²), as
``sim.experiments.teacher_dataset`` takes it from a flight log:

- ``eso``: the ESO teacher, ``x̂_3`` = f̂ while the estimator's pathway was ``eso``; a recording with
  no estimates (an imported PX4 log) gets them from the ESO run offline over its recorded state and
  thrust (:func:`teacher_selection`);
- ``tdr``: total disturbance reconstruction, ``f_N + Δf̂`` while it flew ``neural_eso``.

Samples are skipped while the estimator was not warm (its first ``skip_s`` after a (re)start:
``warm_ticks`` periods), while the vehicle was on the ground (the simulator's truth says so,
or the setpoint commanded no thrust), or under another pathway than the label needs.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recordings.reader import Recording, RecordingError, read_recording

LABELS = ("eso", "tdr")
LABEL_PATHWAYS = {"eso": ("eso",), "tdr": ("neural_eso",)}


@dataclass(frozen=True)
class TrainingSet:
    z: np.ndarray  # (N, 5) the paper's network input, as EstimateMsg.z carries it
    y_mps2: np.ndarray  # (N,) z-axis label, m/s²: "eso" → x̂_3; "tdr" → f_N + Δf̂
    label: str  # "eso" | "tdr"
    recordings: tuple[str, ...]  # the files it came from
    vehicle: str

    def __len__(self) -> int:
        return len(self.y_mps2)


@dataclass(frozen=True)
class Selection:
    """What one recording gave: the pairs kept and how many samples each rule dropped."""

    z: np.ndarray
    y_mps2: np.ndarray
    estimates: int
    dropped: dict[str, int]


def _last_by_seq(seqs: np.ndarray) -> np.ndarray:
    """Indices of the last row of every run of one ``seq`` (a re-sent sample is answered again,
    right after the first answer); rows stay in publication order."""
    if len(seqs) == 0:
        return np.zeros(0, dtype=int)
    return np.flatnonzero(np.append(seqs[1:] != seqs[:-1], True))


def select(rec: Recording, label: str, *, skip_s: float = 0.5, vehicle: str | None = None) -> Selection:
    """The training pairs of one recording (see the module docstring for the rules)."""
    if label not in LABELS:
        raise ValueError(f"label must be one of {LABELS}, got {label!r}")
    est = rec.channel("estimate", vehicle)
    if len(est) == 0 and label == "eso" and len(rec.channel("state", vehicle)):
        return teacher_selection(rec, skip_s=skip_s, vehicle=vehicle)  # no estimates: the ESO runs offline
    if len(est) == 0:
        return Selection(np.zeros((0, 5)), np.zeros(0), 0, {"no estimates recorded": 0})
    keep_rows = _last_by_seq(np.asarray(est.columns["seq"], dtype=np.int64))
    seq = np.asarray(est.columns["seq"], dtype=np.int64)[keep_rows]
    t = np.asarray(est.columns["t_s"])[keep_rows]
    z = np.asarray(est.columns["z"])[keep_rows]
    warm = np.asarray(est.columns["warm_ticks"])[keep_rows]
    pathway = np.array(est.columns["pathway"], dtype=object)[keep_rows]
    y = (np.asarray(est.columns["f_hat_mps2"])[keep_rows, 2] if label == "eso" else
         np.asarray(est.columns["f_n_mps2"])[keep_rows, 2] + np.asarray(est.columns["delta_f_hat_mps2"])[keep_rows, 2])
    dt = float(np.median(np.diff(t))) if len(t) > 1 and np.any(np.diff(t) > 0) else 0.02
    dt = dt if dt > 0 else 0.02
    ok_warm = warm * dt >= skip_s
    ok_pathway = np.isin(pathway, LABEL_PATHWAYS[label])
    on_ground = np.zeros(len(seq), dtype=bool)
    truth, setpoint = rec.channel("truth", vehicle), rec.channel("setpoint", vehicle)
    if len(truth):
        ground = dict(zip(np.asarray(truth.columns["seq"], dtype=np.int64), np.asarray(truth.columns["on_ground"]) > 0.5))
        on_ground |= np.array([ground.get(s, False) for s in seq])
    if len(setpoint):
        idle = dict(zip(np.asarray(setpoint.columns["seq"], dtype=np.int64), np.asarray(setpoint.columns["thrust_n"]) <= 0))
        on_ground |= np.array([idle.get(s, False) for s in seq])
    keep = ok_warm & ok_pathway & ~on_ground
    dropped = {"estimator not warm": int(np.sum(~ok_warm)),
               f"pathway not {'/'.join(LABEL_PATHWAYS[label])}": int(np.sum(ok_warm & ~ok_pathway)),
               "on the ground": int(np.sum(ok_warm & ok_pathway & on_ground))}
    return Selection(z[keep], y[keep], len(seq), dropped)


def teacher_selection(rec: Recording, *, skip_s: float = 0.5, vehicle: str | None = None) -> Selection:
    """``eso`` pairs of a recording without estimates (an imported PX4 log): the ESO teacher run
    offline over its states and setpoints (:func:`recordings.teacher.eso_teacher`)."""
    from recordings.teacher import eso_teacher

    run = eso_teacher(rec, skip_s=skip_s, vehicle=vehicle)
    keep = run.warm & run.airborne
    return Selection(run.z[keep], run.f_hat_mps2[keep, 2], len(run),
                     {"estimator not warm (offline ESO)": int(np.sum(~run.warm)),
                      "on the ground": int(np.sum(run.warm & ~run.airborne))})


def load_training_set(paths, label: str, *, skip_s: float = 0.5) -> TrainingSet:
    """Training pairs from one or more ``.rrd`` files (a path or a list of them) of one vehicle.
    Raises :class:`RecordingError` naming the file and the reasons when a file gives no usable
    sample, or when the files record different vehicles."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [str(p) for p in paths]
    if not paths:
        raise ValueError("no recordings given")
    zs, ys, vehicles = [], [], set()
    for path in paths:
        rec = read_recording(path)
        vehicles.add(rec.vehicle)
        sel = select(rec, label, skip_s=skip_s)
        if len(sel.y_mps2) == 0:
            reasons = ", ".join(f"{n} {why}" for why, n in sel.dropped.items() if n) or "no estimates recorded"
            raise RecordingError(f"{path}: no usable {label!r} samples out of {sel.estimates} estimates ({reasons})")
        zs.append(sel.z)
        ys.append(sel.y_mps2)
    if len(vehicles) != 1:
        raise RecordingError(f"recordings of different vehicles {sorted(vehicles)}: train one vehicle at a time")
    z = np.ascontiguousarray(np.concatenate(zs), dtype=float)
    y = np.ascontiguousarray(np.concatenate(ys), dtype=float)
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(y))):
        raise RecordingError(f"non-finite values in the training pairs from {paths}")
    return TrainingSet(z=z, y_mps2=y, label=label, recordings=tuple(paths), vehicle=vehicles.pop())
