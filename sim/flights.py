"""Seeded simulated flights in a process pool, and the scores the experiments give them.

A :class:`FlightTask` is everything one flight needs (scenario, method, networks, seed, trajectory, the estimator's
and the controller's configs, world overrides); :func:`run_flight` flies it in-process (:func:`sim.runner.fly`);
:class:`FlightPool` flies many on a pool of processes. The scores read a flight's log with the experiment's timing
(``config``: a :class:`sim.experiments.PaperConfig`, of which they use ``landing``, ``lemniscate``,
``settle_after_descent_s``, ``settling_band_m`` and ``control.dt_s``).
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context

import numpy as np

from neso.control import ControlConfig
from neso.estimator import NeuralEsoConfig
from neso.methods import build_estimator
from neso.metrics import rmse_m, settling_time_s, steady_state_abs_error_m
from sim.runner import FlightLog, fly
from sim.scenarios import make_scenario


@dataclass(frozen=True)
class FlightTask:
    scenario: str
    method: str
    networks: dict
    seed: int
    trajectory: object
    estimator: NeuralEsoConfig
    control: ControlConfig
    sim_overrides: tuple[tuple[str, object], ...] = ()  # SimConfig fields replaced in the scenario


def run_flight(task: FlightTask) -> FlightLog:
    estimator = build_estimator(task.method, task.estimator, task.networks)
    return fly(
        sim_config=make_scenario(task.scenario, **dict(task.sim_overrides)), estimator=estimator,
        trajectory=task.trajectory, seed=task.seed, control=task.control,
    )


class FlightPool:
    """Runs flight tasks on ``workers`` processes (fork: the tasks' numpy networks travel pickled)."""

    def __init__(self, workers: int) -> None:
        self.workers = workers or os.cpu_count() or 1
        self._pool = ProcessPoolExecutor(self.workers, mp_context=get_context("fork")) if self.workers > 1 else None

    def map(self, tasks: list, fn=run_flight) -> list:
        """``fn`` (default ``run_flight``, a module-level function) over ``tasks``, in order."""
        if self._pool is None:
            return [fn(t) for t in tasks]
        return list(self._pool.map(fn, tasks))

    def map_groups(self, groups: list[list[FlightTask]]) -> list[list[FlightLog]]:
        """Fly every group's tasks in one pool pass; the logs come back grouped as given."""
        flat = self.map([t for group in groups for t in group])
        out, start = [], 0
        for group in groups:
            out.append(flat[start:start + len(group)])
            start += len(group)
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()


# -- scores ------------------------------------------------------------------------------------
def landing_metrics(log: FlightLog, config) -> tuple[float | None, float | None]:
    """(steady-state mean |z error| cm, settling time s) of one landing; (None, None) if it diverged."""
    if log.diverged:
        return None, None
    t, e = log.t_s, log.z_error_m
    descent_end = config.landing.descent_end_s
    ss = steady_state_abs_error_m(t, e, start_s=descent_end + config.settle_after_descent_s) * 100
    settle = settling_time_s(t, e, from_s=descent_end, band_m=config.settling_band_m)
    return ss, settle


def lemniscate_rmse_cm(log: FlightLog, config) -> float | None:
    if log.diverged:
        return None
    return rmse_m(log.t_s, log.z_error_m, start_s=config.lemniscate.cycle_start_s) * 100


def steady_spectrum(log: FlightLog, config) -> tuple[float, float]:
    """(thrust std N, frequency of the largest peak of the z error Hz) after the descent has settled."""
    late = np.isfinite(log.t_s) & (log.t_s >= config.landing.descent_end_s + config.settle_after_descent_s)
    e = log.z_error_m[late] - np.mean(log.z_error_m[late])
    freqs = np.fft.rfftfreq(len(e), config.control.dt_s)
    return float(np.std(log.thrust_n[late])), float(freqs[1 + np.argmax(np.abs(np.fft.rfft(e))[1:])])
