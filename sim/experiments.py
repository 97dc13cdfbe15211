"""The paper's Section V in simulation, from nothing: teacher data → base network → Exp. 1, 2,
the L_N ablation, Exp. 3 with Total Disturbance Retraining — for one or more recipes side by side.

A recipe (:mod:`neso.learning`) decides what the networks are: inputs, labels, bound and units,
TDR normalisation. The methods without a network (``pd``, ``pd_eso``) and the ESO-teacher
flights do not depend on it and are flown once; every recipe trains its own networks on the same
teacher data and flies the same seeds. Flights run in a process pool (one worker per core) and
every flight is seeded, so a run is reproducible. Results come back in the shape
``neso experiment paper --json`` writes (see :func:`results_json`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
from neso.control import ControlConfig
from neso.eso import EsoConfig
from neso.estimator import NeuralEsoConfig
from neso.features import ThrustLag, acceleration_labels, feature_set
from neso.learning import (DEFAULT_RECIPE, RECIPES, FlightSeries, Recipe, features, identify_thrust_lag, labels,
                           recipe_bound)
from neso.metrics import summarise
from neso.network import LipschitzMLP
from neso.trajectories import Landing, Lemniscate
from neso.types import OMEGA_O_RPS
from sim.flights import FlightPool, FlightTask, landing_metrics, lemniscate_rmse_cm, steady_spectrum
from sim.runner import FlightLog
from sim.scenarios import make_scenario

LANDING_METHODS = ("pd", "pd_nn", "pd_eso", "neural_eso")
OOD_METHODS = ("pd", "pd_nn", "pd_eso", "neural_eso")
LEMNISCATE_METHODS = ("pd", "pd_nn", "pd_eso", "neural_observer", "neural_eso", "neural_eso_tdr")
SHARED_METHODS = ("pd", "pd_eso")  # no network: flown once for every recipe
ABLATION_FACTORS = (0.2, 0.5, 1.0, 2.0)  # × the recipe's base bound (the paper's L_N ∈ {0.2, 0.5, 1, 2})


@dataclass(frozen=True)
class PaperConfig:
    """Everything the pipeline chooses. ``recipes``: the recipes flown side by side (the first is
    the one ``results`` reports at the top level). The L_N ablation flies each recipe's base bound
    times :data:`ABLATION_FACTORS`."""

    trials: int = 5
    recipes: tuple[str, ...] = (DEFAULT_RECIPE, "paper")
    omega_o_rps: float = OMEGA_O_RPS
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

    def base_bound(self, recipe: Recipe) -> float:
        """The recipe's bound in its units (the certified one for these gains when it asks for it)."""
        return recipe_bound(recipe, self.control.kp[2], self.control.kd[2], self.omega_o_rps,
                            self.control.vehicle.mass_kg)


# -- datasets --------------------------------------------------------------------------
def _late(series: FlightSeries, skip_s: float) -> np.ndarray:
    return series.t_s >= series.t_s[0] + skip_s


def training_pairs(logs: list[FlightLog], recipe_label: str, fset_key: str, lag: ThrustLag, *,
                   skip_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(z (N, n), y (N,)) of flights: the feature set's inputs and the label ``recipe_label``
    (:func:`neso.learning.labels`), the first ``skip_s`` of each flight left out (observer warm-up)."""
    fset = feature_set(fset_key)
    zs, ys = [], []
    for log in logs:
        series = log.series()
        keep = _late(series, skip_s)
        zs.append(features(series, fset, lag)[keep])
        ys.append(labels(series, recipe_label, lag)[keep])
    return np.concatenate(zs), np.concatenate(ys)


def acceleration_dataset(logs: list[FlightLog], fset_key: str, lag: ThrustLag, dt_s: float, *,
                         skip_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(z, y) with y = measured − commanded z acceleration (the PD+NN baseline's labels)."""
    fset = feature_set(fset_key)
    zs, ys = [], []
    for log in logs:
        series = log.series()
        keep = np.isfinite(log.t_s)
        y = acceleration_labels(log.vel_meas_mps[keep, 2], log.acc_cmd_mps2[keep, 2], dt_s)
        zs.append(features(series, fset, lag)[:-1][_late(series, skip_s)[:-1]])
        ys.append(y[_late(series, skip_s)[:-1]])
    return np.concatenate(zs), np.concatenate(ys)


def label_quality(log: FlightLog, kind: str, lag: ThrustLag, *, late_s: float = 3.0, dt_s: float = 0.02) -> dict:
    """A label against the simulator's truth (the disturbance relative to the applied thrust, averaged over
    each period, through the labels' 5 Hz zero-phase low-pass): RMS (m/s²), the shift of best match (s) and
    the correlation of the label's error with the commanded thrust rate (an echo of the command)."""
    from neso.learning import zero_phase

    series = log.series()
    truth = zero_phase(log.applied_disturbance_truth_z(dt_s)[1:len(series)], dt_s, 5.0)
    y = labels(series, kind, lag)[1:]
    late = series.t_s[1:] >= series.t_s[0] + late_s
    err = y - truth
    best = min(range(12), key=lambda k: float(np.mean(((y[k:] - truth[:len(truth) - k]) ** 2)[late[k:]])))
    t_dot = np.diff(log.thrust_n[:len(series)]) / dt_s
    return {"rms_mps2": float(np.sqrt(np.mean(err[late] ** 2))), "lag_s": best * dt_s,
            "corr_with_thrust_rate": float(np.corrcoef(err[late], t_dot[late])[0, 1])}


def train(z: np.ndarray, y: np.ndarray, *, bound: float, units: str, config: PaperConfig, name: str,
          fset_key: str, lag: ThrustLag, recipe_name: str, init=None, scalers: str = "init", source: str = ""):
    from neso.learning import recipe_blocks
    from neso.training import train_lipschitz_mlp

    blocks, block_bounds = recipe_blocks(RECIPES[recipe_name], feature_set(fset_key), bound)
    return train_lipschitz_mlp(
        z, y, lipschitz_bound=bound, bound_units=units, epochs=config.epochs, seed=config.seed, init=init,
        scalers=scalers, blocks=blocks, block_bounds=block_bounds, metadata={"id": name, "training_data": source, "feature_set": fset_key, "recipe": recipe_name,
                                   "thrust_lag_s": repr(lag.time_constant_s), "thrust_delay_s": repr(lag.delay_s),
                                   "mass_kg": repr(float(config.control.vehicle.mass_kg))},
    )


# -- metrics ---------------------------------------------------------------------------
def disturbance_z_std_mps2(log: FlightLog, config: PaperConfig, scenario: str) -> float | None:
    """The spread (std, m/s²) of the true z disturbance the controller's nominal model does not explain, in the
    window each experiment scores (the lemniscate's cycles; a landing's steady state); None if it diverged."""
    if log.diverged:
        return None
    start = (config.lemniscate.cycle_start_s if scenario == "lemniscate_near_ground"
             else config.landing.descent_end_s + config.settle_after_descent_s)
    keep = np.isfinite(log.t_s) & (log.t_s >= start)
    return float(np.std(log.f_true[keep, 2]))


# -- the pipeline -----------------------------------------------------------------------
@dataclass
class PaperRun:
    results: dict  # the first recipe's results (the documented shape)
    details: dict
    logs: dict  # experiment → method → [FlightLog] (for plots), first recipe
    seconds: float
    networks: dict = field(default_factory=dict)  # file stem → LipschitzMLP, first recipe
    by_recipe: dict = field(default_factory=dict)  # recipe → {"results", "details", "logs", "networks", "flown"}
    lag: ThrustLag | None = None  # the thrust response identified on the teacher flights


class _Flights:
    """Task factory and timer of one pipeline run."""

    def __init__(self, config: PaperConfig, pool: FlightPool, log) -> None:
        self.config, self.pool, self.log = config, pool, log
        self.est_cfg = config.estimator_config()
        self.seeds = [config.seed * 1000 + 1 + i for i in range(config.trials)]
        self.timing: dict[str, float] = {}
        self._since = time.perf_counter()

    def tasks(self, scenario, method, networks, trajectory, seeds=None) -> list[FlightTask]:
        return [FlightTask(scenario, method, networks, s, trajectory, self.est_cfg, self.config.control,
                           self.config.sim_overrides) for s in (self.seeds if seeds is None else seeds)]

    def tick(self, label: str) -> None:
        now = time.perf_counter()
        self.timing[label] = round(now - self._since, 3)
        self.log(f"  {label}: {self.timing[label]:.1f} s")
        self._since = now


def run_paper(config: PaperConfig = PaperConfig(), *, log=print) -> PaperRun:
    started = time.perf_counter()
    pool = FlightPool(config.workers)
    flights = _Flights(config, pool, log)
    try:
        log("collecting ESO-teacher data (pd_eso, nominal landing)")
        teacher_seeds = [config.seed * 1000 + 500 + i for i in range(config.teacher_flights)]
        teacher_logs = pool.map(flights.tasks("nominal_landing", "pd_eso", {}, config.landing, teacher_seeds))
        fit = identify_thrust_lag([t.series() for t in teacher_logs])
        lag, lag_var = fit.lag, fit.variance_mps4
        log(f"  thrust response identified on the teacher flights: lag {lag.time_constant_s * 1e3:.1f} ms, "
            f"delay {lag.delay_s * 1e3:.1f} ms" + (f" ({fit.note})" if fit.at_edge else ""))
        shared = _shared_flights(flights)
        flights.tick("teacher_data_and_baselines")
        by_recipe = {}
        for name in config.recipes:
            recipe = RECIPES[name]
            log(f"recipe {name}: {recipe.description}")
            by_recipe[name] = _run_recipe(recipe, flights, teacher_logs, shared, lag)
            by_recipe[name]["details"]["thrust_lag"] = {"time_constant_s": lag.time_constant_s, "delay_s": lag.delay_s,
                                                        "label_variance_mps4": lag_var}
    finally:
        pool.close()
    first = by_recipe[config.recipes[0]]
    details = dict(first["details"], timing_s=flights.timing)
    return PaperRun(results=first["results"], details=details, logs=first["logs"],
                    seconds=time.perf_counter() - started, networks=first["networks"], by_recipe=by_recipe, lag=lag)


def _shared_flights(flights: _Flights) -> dict:
    """scenario → method → logs of the methods without a network."""
    c = flights.config
    plan = [("nominal_landing", c.landing), ("ood_slope", c.landing), ("lemniscate_near_ground", c.lemniscate),
            ("nominal_landing_noiseless", c.landing)]
    groups = flights.pool.map_groups([flights.tasks(s, m, {}, traj) for s, traj in plan for m in SHARED_METHODS])
    out: dict = {}
    for (scenario, _), i in zip(plan, range(0, len(groups), len(SHARED_METHODS))):
        out[scenario] = dict(zip(SHARED_METHODS, groups[i:i + len(SHARED_METHODS)]))
    return out


def _run_recipe(recipe: Recipe, flights: _Flights, teacher_logs: list[FlightLog], shared: dict, lag: ThrustLag) -> dict:
    config, pool = flights.config, flights.pool
    bound = config.base_bound(recipe)
    details: dict = {"recipe": recipe.name, "feature_set": recipe.feature_set, "bound_units": recipe.bound_units,
                     "base_bound": bound, "networks": {}, "settling_time_s": {}}
    fs = recipe.feature_set
    z_t, y_t = training_pairs(teacher_logs, recipe.base_label, fs, lag)
    z_a, y_a = acceleration_dataset(teacher_logs, fs, lag, config.control.dt_s)
    flights.log(f"  training on {len(y_t)} samples: bounds {[round(f * bound, 4) for f in ABLATION_FACTORS]} "
                f"({recipe.bound_units}), acceleration (PD+NN)")
    nets: dict[float, LipschitzMLP] = {}
    paper = recipe.bound_units == "normalised"
    for factor in ABLATION_FACTORS:
        name = f"base-L{factor * bound}" if paper else ("base" if factor == 1.0 else f"base-x{factor:g}")
        res = train(z_t, y_t, bound=factor * bound, units=recipe.bound_units, config=config,
                    name=name, fset_key=fs, lag=lag, recipe_name=recipe.name,
                    source=f"{recipe.base_label}_teacher:nominal_landing")
        nets[factor] = res.network
        details["networks"][f"base_x{factor:g}"] = _network_details(res, config)
    acc_res = train(z_a, y_a, bound=bound, units=recipe.bound_units, config=config,
                    name=f"{recipe.name}-acceleration" if paper else "acceleration",
                    fset_key=fs, lag=lag, recipe_name=recipe.name, source="acceleration:nominal_landing")
    details["networks"]["acceleration"] = _network_details(acc_res, config)
    base = {"base": nets[1.0], "acceleration": acc_res.network}
    flights.tick(f"{recipe.name}: training")

    results: dict = {}
    logs: dict = {}
    for scenario, methods in (("nominal_landing", LANDING_METHODS), ("ood_slope", OOD_METHODS)):
        results[scenario], logs[scenario] = _landing_experiment(flights, scenario, methods, base, shared, details)
    flights.tick(f"{recipe.name}: experiments 1-2")
    results["lipschitz_ablation"] = _ablation(flights, nets, results, recipe, bound)
    flights.tick(f"{recipe.name}: lipschitz_ablation")
    results["noise_free_nominal"], logs["noise_free_nominal"] = _noise_free(flights, base, shared)

    tdr_traj = replace(config.lemniscate, cycles=config.tdr_cycles)
    (tdr_log,) = pool.map(flights.tasks("lemniscate_near_ground", "neural_eso", base, tdr_traj,
                                        [config.seed * 1000 + 900]))
    tdr_res = tdr_network(tdr_log, recipe, config, base, lag, tdr_traj)
    details["networks"]["tdr"] = _network_details(tdr_res, config)
    details["tdr_samples"] = int(tdr_res.n_train + tdr_res.n_val)
    details["labels"] = {"landing (teacher)": {k: label_quality(teacher_logs[0], k, lag) for k in ("eso", "applied")},
                         "lemniscate (TDR flight)": {k: label_quality(tdr_log, k, lag) for k in ("tdr", "applied")}}
    nets3 = dict(base, tdr=tdr_res.network)
    own = [m for m in LEMNISCATE_METHODS if m not in SHARED_METHODS]
    groups = pool.map_groups([flights.tasks("lemniscate_near_ground", m, nets3, config.lemniscate) for m in own])
    logs["lemniscate_near_ground"] = {m: (shared["lemniscate_near_ground"][m] if m in SHARED_METHODS
                                          else groups[own.index(m)]) for m in LEMNISCATE_METHODS}
    results["lemniscate_near_ground"] = {"metric": "z_rmse_cm", "methods": {
        m: summarise([lemniscate_rmse_cm(f, config) for f in fl]) for m, fl in logs["lemniscate_near_ground"].items()}}
    flights.tick(f"{recipe.name}: lemniscate_near_ground")
    networks = {_file_stem(n.metadata["id"]): n for n in nets.values()}
    networks.update(acceleration=acc_res.network, tdr=tdr_res.network)
    return {"results": results, "details": details, "logs": logs, "networks": networks, "flown": nets3}


def tdr_network(tdr_log: FlightLog, recipe: Recipe, config: PaperConfig, base: dict, lag: ThrustLag, tdr_traj):
    """Total Disturbance Retraining: the recipe's TDR labels of a neural_eso lemniscate flight ``tdr_log``
    (``tdr_traj``, its ramp left out), fine-tuned from ``base["base"]``; the training result."""
    z_r, y_r = training_pairs([tdr_log], recipe.tdr_label, recipe.feature_set, lag, skip_s=tdr_traj.cycle_start_s)
    return train(z_r, y_r, bound=config.base_bound(recipe), units=recipe.bound_units, config=config,
                 name=f"{recipe.name}-tdr" if recipe.bound_units == "normalised" else "tdr",
                 fset_key=recipe.feature_set, lag=lag, recipe_name=recipe.name, init=base["base"],
                 scalers=recipe.tdr_scalers, source=f"{recipe.tdr_label}:lemniscate_near_ground")


def _landing_experiment(flights: _Flights, scenario, methods, networks, shared, details):
    config = flights.config
    own = [m for m in methods if m not in SHARED_METHODS]
    groups = flights.pool.map_groups([flights.tasks(scenario, m, networks, config.landing) for m in own])
    logs = {m: (shared[scenario][m] if m in SHARED_METHODS else groups[own.index(m)]) for m in methods}
    out = {"metric": "steady_state_abs_z_error_cm", "methods": {}}
    details["settling_time_s"][scenario] = {}
    for method, fl in logs.items():
        metrics = [landing_metrics(f, config) for f in fl]
        out["methods"][method] = summarise([m[0] for m in metrics])
        details["settling_time_s"][scenario][method] = summarise([m[1] for m in metrics])
    return out, logs


def _noise_free(flights: _Flights, networks: dict, shared: dict) -> tuple[dict, dict]:
    """The nominal landing with noise-free motion capture: steady-state error, thrust spread and the
    dominant frequency of the error (a limit cycle shows as a peak with a large thrust spread)."""
    config = flights.config
    (ours,) = flights.pool.map_groups([flights.tasks("nominal_landing_noiseless", "neural_eso", networks, config.landing)])
    logs = {"pd_eso": shared["nominal_landing_noiseless"]["pd_eso"], "neural_eso": ours}
    out = {"metric": "steady_state_abs_z_error_cm", "methods": {}, "thrust_std_n": {}, "peak_hz": {}}
    for method, fl in logs.items():
        out["methods"][method] = summarise([landing_metrics(f, config)[0] for f in fl])
        stats = [steady_spectrum(f, config) for f in fl if not f.diverged]
        out["thrust_std_n"][method] = summarise([s[0] for s in stats])
        out["peak_hz"][method] = summarise([s[1] for s in stats])
    return out, logs


def _ablation(flights: _Flights, nets: dict, results: dict, recipe: Recipe, bound: float) -> dict:
    config = flights.config
    out = {"metric": "steady_state_abs_z_error_cm", "units": recipe.bound_units, "nominal": {}, "ood": {}}
    others = [f for f in ABLATION_FACTORS if f != 1.0]
    for key, scenario in (("nominal", "nominal_landing"), ("ood", "ood_slope")):
        groups = flights.pool.map_groups(
            [flights.tasks(scenario, "neural_eso", {"base": nets[f]}, config.landing) for f in others])
        row = {f: summarise([landing_metrics(fl, config)[0] for fl in g]) for f, g in zip(others, groups)}
        row[1.0] = results[scenario]["methods"]["neural_eso"]
        out[key] = {_bound_key(f * bound): row[f] for f in ABLATION_FACTORS}
    return out


def _bound_key(value: float) -> str:
    return f"{value:.4g}" if value != round(value, 1) else str(round(value, 1))


def _network_details(result, config: PaperConfig) -> dict:
    net = result.network
    cert = flight_certificate(NetworkSlopes.of(net), kp=config.control.kp[2], kd=config.control.kd[2],
                              omega_o=config.omega_o_rps, plant=LoopPlant.of(config.control))
    return {
        "bound": net.lipschitz_bound,
        "bound_units": net.bound_units,
        "certified_lipschitz_normalised": net.certified_lipschitz_normalised(),
        "certified_lipschitz_physical": net.certified_lipschitz_physical(),
        "certified_lipschitz_state": net.certified_lipschitz_state(),
        "certificate_holds": cert.holds,
        "certificate": cert.to_dict(),
        "val_loss_vs_mean": result.val_loss_vs_mean,
        "slopes": result.slopes,
        "start": net.metadata.get("start", ""),
        "largest_certified_physical": cert.max_certified,
        "feature_set": net.feature_set.key,
        "val_loss": result.val_loss,
        "n_train": result.n_train,
        "n_val": result.n_val,
    }


def results_json(run: PaperRun, trials: int) -> dict:
    """The documented shape (``experiments`` for the first recipe), plus every recipe side by side."""
    return {"experiments": run.results, "seconds": run.seconds, "trials": trials,
            "recipe": next(iter(run.by_recipe), None),
            "recipes": {name: {"experiments": r["results"], "details": r["details"]} for name, r in run.by_recipe.items()}}


def _file_stem(net_id: str) -> str:
    """``base-L1.0`` → ``base-L1`` (the paper's file names), other ids as they are."""
    head, _, bound = net_id.partition("-L")
    return f"{head}-L{float(bound):g}" if bound else net_id


def save_networks(run: PaperRun, directory) -> list:
    """Write every recipe's networks: the first recipe's into ``directory`` (``base``, ``base-x<f>``,
    ``acceleration``, ``tdr``), the others into ``directory/<recipe>/`` (the paper's as ``base-L<L_N>``)."""
    from pathlib import Path

    from neso.netfile import save_network

    paths = []
    for i, (name, rec) in enumerate(run.by_recipe.items()):
        folder = Path(directory) if i == 0 else Path(directory) / name
        folder.mkdir(parents=True, exist_ok=True)
        for stem, net in rec["networks"].items():
            path = folder / f"{stem}.safetensors"
            save_network(path, net)
            paths.append(path)
    return paths
