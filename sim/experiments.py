"""The paper's Section V in simulation, from nothing: teacher data → base network → Exp. 1, 2,
the L_N ablation, Exp. 3 with Total Disturbance Retraining.

Pure orchestration over :mod:`sim.runner` and :mod:`neso`; flights run in a process pool
(one worker per core) and every flight is seeded, so a run is reproducible. Results come
back in the shape ``neso experiment paper --json`` writes (see :func:`results_json`).
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from multiprocessing import get_context

import numpy as np

from neso.control import ControlConfig
from neso.eso import EsoConfig
from neso.estimator import NeuralEsoConfig
from neso.features import acceleration_labels
from neso.methods import build_estimator
from neso.metrics import rmse_m, settling_time_s, steady_state_abs_error_m, summarise
from neso.network import LipschitzMLP
from neso.trajectories import Landing, Lemniscate
from sim.runner import FlightLog, fly
from sim.scenarios import make_scenario

LANDING_METHODS = ("pd", "pd_nn", "pd_eso", "neural_eso")
OOD_METHODS = ("pd", "pd_nn", "pd_eso", "neural_eso")
LEMNISCATE_METHODS = ("pd", "pd_nn", "pd_eso", "neural_observer", "neural_eso", "neural_eso_tdr")


@dataclass(frozen=True)
class PaperConfig:
    """Everything the pipeline chooses. ``base_lipschitz`` and ``lipschitz_values`` are bounds
    on the *normalised* network (z-scored inputs and labels), as the paper trains them."""

    trials: int = 5
    base_lipschitz: float = 1.0
    lipschitz_values: tuple[float, ...] = (0.2, 0.5, 1.0, 2.0)
    omega_o_rps: float = 15.0
    control: ControlConfig = field(default_factory=ControlConfig)
    teacher_flights: int = 3
    tdr_cycles: int = 5  # 5 cycles × 6 s = the paper's 30 s of OOD data
    epochs: int = 100
    workers: int = 0  # 0: one per core
    landing: Landing = field(
        default_factory=lambda: Landing(end_height_m=make_scenario("nominal_landing").reference_height_m))
    lemniscate: Lemniscate = field(
        default_factory=lambda: Lemniscate(height_m=make_scenario("lemniscate_near_ground").reference_height_m))
    settle_after_descent_s: float = 2.0  # steady-state window starts this long after the descent
    settling_band_m: float = 0.01
    seed: int = 0
    sim_overrides: tuple[tuple[str, object], ...] = ()  # SimConfig fields replaced in every scenario

    def estimator_config(self) -> NeuralEsoConfig:
        return NeuralEsoConfig(eso=EsoConfig(omega_o_rps=self.omega_o_rps, dt_s=self.control.dt_s))


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


class _Pool:
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


# -- datasets --------------------------------------------------------------------------
def teacher_dataset(logs: list[FlightLog], *, skip_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(z (N, 5), y (N,)) with y = f̂_z of flights under an observer pathway (ESO teacher or TDR)."""
    zs, ys = [], []
    for log in logs:
        keep = np.isfinite(log.t_s) & (log.t_s >= log.t_s[0] + skip_s)
        zs.append(log.z[keep])
        ys.append(log.f_hat[keep, 2])
    return np.concatenate(zs), np.concatenate(ys)


def acceleration_dataset(logs: list[FlightLog], dt_s: float, *, skip_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(z, y) with y = measured − commanded z acceleration (the PD+NN baseline's labels)."""
    zs, ys = [], []
    for log in logs:
        keep = np.isfinite(log.t_s)
        y = acceleration_labels(log.vel_meas_mps[keep, 2], log.acc_cmd_mps2[keep, 2], dt_s)
        z = log.z[keep][:-1]
        late = log.t_s[keep][:-1] >= log.t_s[0] + skip_s
        zs.append(z[late])
        ys.append(y[late])
    return np.concatenate(zs), np.concatenate(ys)


def train(z: np.ndarray, y: np.ndarray, *, bound: float, config: PaperConfig, name: str, init=None, source: str = ""):
    from neso.training import train_lipschitz_mlp

    result = train_lipschitz_mlp(
        z, y, lipschitz_bound=bound, epochs=config.epochs, seed=config.seed, init=init,
        metadata={"id": name, "training_data": source},
    )
    return result


# -- metrics ---------------------------------------------------------------------------
def landing_metrics(log: FlightLog, config: PaperConfig) -> tuple[float | None, float | None]:
    """(steady-state mean |z error| cm, settling time s) of one landing; (None, None) if it diverged."""
    if log.diverged:
        return None, None
    t, e = log.t_s, log.z_error_m
    descent_end = config.landing.descent_end_s
    ss = steady_state_abs_error_m(t, e, start_s=descent_end + config.settle_after_descent_s) * 100
    settle = settling_time_s(t, e, from_s=descent_end, band_m=config.settling_band_m)
    return ss, settle


def lemniscate_rmse_cm(log: FlightLog, config: PaperConfig) -> float | None:
    if log.diverged:
        return None
    return rmse_m(log.t_s, log.z_error_m, start_s=config.lemniscate.cycle_start_s) * 100


# -- the pipeline -----------------------------------------------------------------------
@dataclass
class PaperRun:
    results: dict
    details: dict
    logs: dict  # experiment → method → [FlightLog] (for plots)
    seconds: float
    networks: dict = field(default_factory=dict)  # file stem → LipschitzMLP (base-L<b>, acceleration, tdr)


def run_paper(config: PaperConfig = PaperConfig(), *, log=print) -> PaperRun:
    started = time.perf_counter()
    pool = _Pool(config.workers)
    est_cfg = config.estimator_config()
    seeds = [config.seed * 1000 + 1 + i for i in range(config.trials)]
    details: dict = {"networks": {}, "timing_s": {}, "settling_time_s": {}}
    logs: dict = {}

    def tasks(scenario, method, networks, trajectory, trial_seeds=seeds):
        return [FlightTask(scenario, method, networks, s, trajectory, est_cfg, config.control, config.sim_overrides)
                for s in trial_seeds]

    def tick(label, since):
        details["timing_s"][label] = round(time.perf_counter() - since, 3)
        log(f"  {label}: {details['timing_s'][label]:.1f} s")
        return time.perf_counter()

    try:
        t0 = time.perf_counter()
        log("collecting ESO-teacher data (pd_eso, nominal landing)")
        teacher_seeds = [config.seed * 1000 + 500 + i for i in range(config.teacher_flights)]
        teacher_logs = pool.map(tasks("nominal_landing", "pd_eso", {}, config.landing, teacher_seeds))
        z_t, y_t = teacher_dataset(teacher_logs)
        z_a, y_a = acceleration_dataset(teacher_logs, config.control.dt_s)
        t0 = tick("teacher_data", t0)

        log(f"training networks on {len(y_t)} samples: L_N ∈ {config.lipschitz_values} (ESO teacher), acceleration (PD+NN)")
        bounds = sorted(set(config.lipschitz_values) | {config.base_lipschitz})
        nets: dict[float, LipschitzMLP] = {}
        for bound in bounds:
            res = train(z_t, y_t, bound=bound, config=config, name=f"base-L{bound}", source="eso_teacher:nominal_landing")
            nets[bound] = res.network
            details["networks"][f"base_L{bound}"] = _network_details(res)
        acc_res = train(z_a, y_a, bound=config.base_lipschitz, config=config, name="acceleration", source="acceleration:nominal_landing")
        details["networks"]["acceleration"] = _network_details(acc_res)
        base = {"base": nets[config.base_lipschitz], "acceleration": acc_res.network}
        t0 = tick("training", t0)

        results: dict = {}
        log("experiment 1: nominal landing")
        results["nominal_landing"], logs["nominal_landing"] = _landing_experiment(
            pool, tasks, "nominal_landing", LANDING_METHODS, base, config, details)
        t0 = tick("nominal_landing", t0)
        log("experiment 2: OOD slope")
        results["ood_slope"], logs["ood_slope"] = _landing_experiment(
            pool, tasks, "ood_slope", OOD_METHODS, base, config, details)
        t0 = tick("ood_slope", t0)

        log("L_N ablation")
        ablation = {"metric": "steady_state_abs_z_error_cm", "nominal": {}, "ood": {}}
        for key, scenario in (("nominal", "nominal_landing"), ("ood", "ood_slope")):
            others = [b for b in config.lipschitz_values if b != config.base_lipschitz]
            groups = pool.map_groups([tasks(scenario, "neural_eso", {"base": nets[b]}, config.landing) for b in others])
            for bound, flights in zip(others, groups):
                ablation[key][str(bound)] = summarise([landing_metrics(f, config)[0] for f in flights])
            if config.base_lipschitz in config.lipschitz_values:
                ablation[key][str(config.base_lipschitz)] = results[scenario]["methods"]["neural_eso"]
            ablation[key] = {str(b): ablation[key][str(b)] for b in config.lipschitz_values}
        results["lipschitz_ablation"] = ablation
        t0 = tick("lipschitz_ablation", t0)

        log("experiment 3: lemniscate near ground, TDR on 30 s of OOD data under Neural-ESO")
        tdr_traj = replace(config.lemniscate, cycles=config.tdr_cycles)
        (tdr_log,) = pool.map(tasks("lemniscate_near_ground", "neural_eso", base, tdr_traj, [config.seed * 1000 + 900]))
        z_r, y_r = teacher_dataset([tdr_log], skip_s=tdr_traj.cycle_start_s)
        tdr_res = train(z_r, y_r, bound=config.base_lipschitz, config=config, name="tdr", init=base["base"],
                        source="tdr:lemniscate_near_ground")
        details["networks"]["tdr"] = _network_details(tdr_res)
        details["tdr_samples"] = int(len(y_r))
        nets3 = dict(base, tdr=tdr_res.network)
        groups = pool.map_groups([tasks("lemniscate_near_ground", m, nets3, config.lemniscate) for m in LEMNISCATE_METHODS])
        lem = {"metric": "z_rmse_cm", "methods": {}}
        logs["lemniscate_near_ground"] = dict(zip(LEMNISCATE_METHODS, groups))
        for method, flights in logs["lemniscate_near_ground"].items():
            lem["methods"][method] = summarise([lemniscate_rmse_cm(f, config) for f in flights])
        results["lemniscate_near_ground"] = lem
        tick("lemniscate_near_ground", t0)
    finally:
        pool.close()
    seconds = time.perf_counter() - started
    networks = {f"base-L{b:g}": net for b, net in nets.items()}
    networks.update(acceleration=acc_res.network, tdr=tdr_res.network)
    return PaperRun(results=results, details=details, logs=logs, seconds=seconds, networks=networks)


def _landing_experiment(pool, tasks, scenario, methods, networks, config, details):
    logs = dict(zip(methods, pool.map_groups([tasks(scenario, m, networks, config.landing) for m in methods])))
    out = {"metric": "steady_state_abs_z_error_cm", "methods": {}}
    details["settling_time_s"][scenario] = {}
    for method, flights in logs.items():
        metrics = [landing_metrics(f, config) for f in flights]
        out["methods"][method] = summarise([m[0] for m in metrics])
        details["settling_time_s"][scenario][method] = summarise([m[1] for m in metrics])
    return out, logs


def _network_details(result) -> dict:
    net = result.network
    return {
        "lipschitz_bound_normalised": net.lipschitz_bound,
        "certified_lipschitz_normalised": net.certified_lipschitz_normalised(),
        "certified_lipschitz_physical": net.certified_lipschitz_physical(),
        "val_loss": result.val_loss,
        "n_train": result.n_train,
        "n_val": result.n_val,
    }


def results_json(run: PaperRun, trials: int) -> dict:
    """Exactly the shape the issue specifies for ``--json``."""
    return {"experiments": run.results, "seconds": run.seconds, "trials": trials}
