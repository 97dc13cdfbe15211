"""The estimator service's step object run offline over a recording's states and setpoints.

What ``--what-if`` and the offline ESO teacher share: the recorded samples fed, in their recorded
order (``stamp_s``; a setpoint before a state of the same stamp), to
:class:`flight.estimator.EstimatorCore`, exactly as the running service would get them. A gap in
the states (longer than ``gap_periods`` median periods: a logger dropout, a topic logged in bursts)
starts a fresh step object, as a restarted estimator would: the observer is not integrated across
time it never saw.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from neso.types import LOOP_PERIOD_S
from runtime.schema import EstimateMsg, SetpointMsg, StateMsg

GAP_PERIODS = 5.0


def split_at_gaps(t_s, gap_periods: float = GAP_PERIODS) -> list[slice]:
    """Contiguous runs of samples: a step longer than ``gap_periods`` median steps starts a new one."""
    t_s = np.asarray(t_s, dtype=float)
    if len(t_s) < 2:
        return [slice(0, len(t_s))]
    steps = np.diff(t_s)
    cuts = np.flatnonzero(steps > gap_periods * float(np.median(steps))) + 1
    bounds = [0, *cuts.tolist(), len(t_s)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]


def sample_period_s(t_s, default: float = LOOP_PERIOD_S) -> float:
    """The median step of ``t_s`` (s), ``default`` with fewer than two samples."""
    t_s = np.asarray(t_s, dtype=float)
    return float(np.median(np.diff(t_s))) if len(t_s) > 1 else default


def run_estimator(states: list[StateMsg], setpoints: list[SetpointMsg], make_core: Callable[[float], object], *,
                  gap_periods: float | None = GAP_PERIODS) -> dict[int, EstimateMsg]:
    """The estimates (by ``seq``) of ``make_core(dt_s)`` step objects over ``states`` and ``setpoints``:
    one per run of states between gaps (``gap_periods`` None: one for all), each with its run's
    median period. Setpoints reach the run of the state they answer."""
    t = np.array([m.t_s for m in states])
    runs = split_at_gaps(t, gap_periods) if gap_periods is not None else [slice(0, len(states))]
    by_seq = sorted(setpoints, key=lambda m: m.seq)
    seqs = np.array([m.seq for m in by_seq], dtype=np.int64)
    ours: dict[int, EstimateMsg] = {}
    for run in runs:
        run_states = states[run]
        if not run_states:
            continue
        core = make_core(sample_period_s(t[run]))
        if len(runs) == 1:
            run_setpoints = setpoints
        else:  # the setpoints answering this run's states (and the one before its first)
            lo, hi = run_states[0].seq - 1, run_states[-1].seq
            a, b = np.searchsorted(seqs, lo, "left"), np.searchsorted(seqs, hi, "right")
            run_setpoints = by_seq[a:b]
        events = sorted([(m.stamp_s, 1, m) for m in run_states] + [(m.stamp_s, 0, m) for m in run_setpoints],
                        key=lambda e: (e[0], e[1]))
        for _, kind, msg in events:
            outputs = core.on_state(msg, 0.0) if kind == 1 else core.on_setpoint(msg, 0.0)
            for est in outputs:
                ours[est.seq] = est
    return ours
