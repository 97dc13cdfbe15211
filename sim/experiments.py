"""The paper's Section V in simulation, from nothing: teacher data → base network → Exp. 1, 2,
the L_N ablation, Exp. 3 with Total Disturbance Retraining — for one or more recipes side by side,
each experiment beside PD+ESO at gains tuned on the same kind of flights (:mod:`sim.tuning`).

A recipe (:mod:`neso.learning`) decides what the networks are: inputs, labels, bound and units,
TDR normalisation. The methods without a network (``pd``, ``pd_eso``) and the ESO-teacher
flights do not depend on it and are flown once; every recipe trains its own networks on the same
teacher data and flies the same seeds. Flights run in a process pool (one worker per core) and
every flight is seeded, so a run is reproducible. Results come back in the shape
``neso experiment paper --json`` writes (see :func:`results_json`).

**The tuned baseline.** Before the recipes, :func:`sim.tuning.tune_pd_eso` finds z gains per kind of flight on
seeds of their own. A method with the suffix :data:`TUNED` flies at them (``pd_eso_tuned``, ``neural_eso_tuned``,
``neural_eso_tdr_tuned``); the learned pathway's networks there are trained to the budget of those gains and TDR
retrains on a flight flown at them, so the comparison with ``pd_eso_tuned`` isolates what the network adds. The
``robustness`` result measures the tuning's conditions (×3 noise, no noise) for PD+ESO and the learned pathway at
both sets of gains on the evaluation seeds.
"""
from __future__ import annotations

import math
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
from sim.tuning import (KINDS, SCENARIO_KIND, TUNED, TuningConfig, TuningResult, ZGains, failed_conditions, robustness,
                        robustness_tasks, tune_pd_eso)
from sim.tuning import task as gains_task

LANDING_METHODS = ("pd", "pd_nn", "pd_eso", "pd_eso_tuned", "neural_eso", "neural_eso_tuned")
OOD_METHODS = LANDING_METHODS
LEMNISCATE_METHODS = ("pd", "pd_nn", "pd_eso", "pd_eso_tuned", "neural_observer", "neural_eso", "neural_eso_tuned",
                      "neural_eso_tdr", "neural_eso_tdr_tuned")
SHARED_METHODS = ("pd", "pd_eso", "pd_eso_tuned")  # no network: flown once for every recipe
#: kind of flight → the methods whose robustness (sim.tuning's conditions) is measured on the evaluation seeds
ROBUSTNESS_METHODS = {"landing": ("pd_eso", "pd_eso_tuned", "neural_eso", "neural_eso_tuned"),
                      "lemniscate": ("pd_eso", "pd_eso_tuned", "neural_eso", "neural_eso_tuned", "neural_eso_tdr",
                                     "neural_eso_tdr_tuned")}
ABLATION_FACTORS = (0.2, 0.5, 1.0, 2.0)  # × the recipe's base bound (the paper's L_N ∈ {0.2, 0.5, 1, 2})


@dataclass(frozen=True)
class PaperConfig:
    """Everything the pipeline chooses. ``recipes``: the recipes flown side by side (the first is
    the one ``results`` reports at the top level). The L_N ablation flies each recipe's base bound
    times :data:`ABLATION_FACTORS`. ``tuning``: the search for the tuned baseline's gains
    (:mod:`sim.tuning`); ``tuned``: kind → gains to fly instead of searching (None: search)."""

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
    tuning: TuningConfig = field(default_factory=TuningConfig)
    tuned: dict | None = None  # kind ("landing", "lemniscate") → ZGains, given instead of searched

    def paper_gains(self) -> ZGains:
        """The flown z gains (the paper's by default)."""
        return ZGains.of(self.control, self.omega_o_rps)

    def estimator_config(self) -> NeuralEsoConfig:
        return NeuralEsoConfig(eso=EsoConfig(omega_o_rps=self.omega_o_rps, dt_s=self.control.dt_s))

    def base_bound(self, recipe: Recipe, gains: ZGains | None = None) -> float:
        """The recipe's bound in its units (the certified one for ``gains``, default the flown ones, when it asks
        for it)."""
        g = gains or self.paper_gains()
        return recipe_bound(recipe, g.kp, g.kd, g.omega_o_rps, self.control.vehicle.mass_kg)


def method_gains(method: str, scenario: str, config: PaperConfig, tuned: TuningResult | None) -> tuple[str, ZGains]:
    """(``method`` without :data:`TUNED`, the z gains it flies in ``scenario``)."""
    if method.endswith(TUNED):
        if tuned is None:
            raise ValueError(f"{method} flies at tuned gains and none were found")
        return method[:-len(TUNED)], tuned.for_scenario(scenario)
    return method, config.paper_gains()


# -- datasets --------------------------------------------------------------------------
def _late(series: FlightSeries, skip_s: float) -> np.ndarray:
    return series.t_s >= series.t_s[0] + skip_s


def training_pairs(logs: list[FlightLog], recipe_label: str, fset_key: str, lag: ThrustLag, *,
                   skip_s: float = 0.5, regressors: str = "state") -> tuple[np.ndarray, np.ndarray]:
    """(z (N, n), y (N,)) of flights: the feature set's inputs (the tracked state from ``regressors``,
    :data:`neso.learning.REGRESSORS`) and the label ``recipe_label`` (:func:`neso.learning.labels`), the first
    ``skip_s`` of each flight left out (observer warm-up)."""
    fset = feature_set(fset_key)
    zs, ys = [], []
    for log in logs:
        series = log.series()
        keep = _late(series, skip_s)
        zs.append(features(series, fset, lag, regressors)[keep])
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
    by_recipe: dict = field(default_factory=dict)  # recipe → {"results", "details", "logs", "networks", "flown",
    #                                                 "flown_tuned"}
    lag: ThrustLag | None = None  # the thrust response identified on the teacher flights
    tuned: TuningResult | None = None  # the tuned baseline's gains and their search


class _Flights:
    """Task factory and timer of one pipeline run."""

    def __init__(self, config: PaperConfig, pool: FlightPool, log) -> None:
        self.config, self.pool, self.log = config, pool, log
        self.seeds = [config.seed * 1000 + 1 + i for i in range(config.trials)]
        self.timing: dict[str, float] = {}
        self.tuned: TuningResult | None = None
        self._since = time.perf_counter()

    def tasks(self, scenario, method, networks, trajectory, seeds=None) -> list[FlightTask]:
        """``method`` in ``scenario`` on the evaluation seeds (or ``seeds``), at the gains :func:`method_gains` says."""
        name, gains = method_gains(method, scenario, self.config, self.tuned)
        return [gains_task(self.config, scenario, name, networks, gains, s, trajectory)
                for s in (self.seeds if seeds is None else seeds)]

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
        flights.tuned = (TuningResult(dict(config.tuned), config.paper_gains(), {"given": True}) if config.tuned
                         else tune_pd_eso(config, pool, log))
        flights.tick("tuning")
        shared = _shared_flights(flights)
        shared_robustness = _robustness(flights, {m: {} for m in ("pd_eso", "pd_eso_tuned")})
        flights.tick("teacher_data_and_baselines")
        by_recipe = {}
        for name in config.recipes:
            recipe = RECIPES[name]
            log(f"recipe {name}: {recipe.description}")
            by_recipe[name] = _run_recipe(recipe, flights, teacher_logs, shared, shared_robustness, lag)
            by_recipe[name]["details"]["thrust_lag"] = {"time_constant_s": lag.time_constant_s, "delay_s": lag.delay_s,
                                                        "label_variance_mps4": lag_var}
            by_recipe[name]["details"]["tuning"] = flights.tuned.details
            by_recipe[name]["details"]["tuned_gains"] = {k: g.to_dict() for k, g in flights.tuned.gains.items()}
    finally:
        pool.close()
    first = by_recipe[config.recipes[0]]
    details = dict(first["details"], timing_s=flights.timing)
    return PaperRun(results=first["results"], details=details, logs=first["logs"],
                    seconds=time.perf_counter() - started, networks=first["networks"], by_recipe=by_recipe, lag=lag,
                    tuned=flights.tuned)


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


def _run_recipe(recipe: Recipe, flights: _Flights, teacher_logs: list[FlightLog], shared: dict,
                shared_robustness: dict, lag: ThrustLag) -> dict:
    config, pool = flights.config, flights.pool
    bound = config.base_bound(recipe)
    details: dict = {"recipe": recipe.name, "feature_set": recipe.feature_set, "bound_units": recipe.bound_units,
                     "base_bound": bound, "networks": {}, "settling_time_s": {}}
    fs = recipe.feature_set
    z_t, y_t = training_pairs(teacher_logs, recipe.base_label, fs, lag, regressors=recipe.regressors)
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
    tuned = _tuned_networks(flights, recipe, nets[1.0], bound, z_t, y_t, lag, details)
    flights.tick(f"{recipe.name}: training")

    results: dict = {}
    logs: dict = {}
    for scenario, methods in (("nominal_landing", LANDING_METHODS), ("ood_slope", OOD_METHODS)):
        results[scenario], logs[scenario] = _landing_experiment(flights, scenario, methods, base, tuned["landing"],
                                                                shared, details)
    flights.tick(f"{recipe.name}: experiments 1-2")
    results["lipschitz_ablation"] = _ablation(flights, nets, results, recipe, bound)
    flights.tick(f"{recipe.name}: lipschitz_ablation")
    results["noise_free_nominal"], logs["noise_free_nominal"] = _noise_free(flights, base, tuned["landing"], shared)

    tdr_traj = replace(config.lemniscate, cycles=config.tdr_cycles)
    tdr_seed = [config.seed * 1000 + 900]
    tdr_log, tdr_log_tuned = pool.map(flights.tasks("lemniscate_near_ground", "neural_eso", base, tdr_traj, tdr_seed) +
                                      flights.tasks("lemniscate_near_ground", "neural_eso_tuned", tuned["lemniscate"],
                                                    tdr_traj, tdr_seed))
    tdr_res = tdr_network(tdr_log, recipe, config, base, lag, tdr_traj)
    lem_gains = flights.tuned.gains["lemniscate"]
    tdr_tuned = tdr_network(tdr_log_tuned, recipe, config, tuned["lemniscate"], lag, tdr_traj,
                            bound=config.base_bound(recipe, lem_gains))
    details["networks"]["tdr"] = _network_details(tdr_res, config)
    details["networks"]["tdr_tuned"] = _network_details(tdr_tuned, config, lem_gains)
    details["tdr_samples"] = int(tdr_res.n_train + tdr_res.n_val)
    details["labels"] = {"landing (teacher)": {k: label_quality(teacher_logs[0], k, lag) for k in ("eso", "applied")},
                         "lemniscate (TDR flight)": {k: label_quality(tdr_log, k, lag) for k in ("tdr", "applied")}}
    nets3 = dict(base, tdr=tdr_res.network)
    nets3_tuned = dict(tuned["lemniscate"], tdr=tdr_tuned.network)
    own = [m for m in LEMNISCATE_METHODS if m not in SHARED_METHODS]
    as_gain = _tdr_as_gain(config, {"pd_eso_tdr_gain": (config.paper_gains(), tdr_res.network),
                                    "pd_eso_tdr_gain_tuned": (lem_gains, tdr_tuned.network)})
    details["tdr_as_gain"] = {m: g.to_dict() for m, g in as_gain.items()}
    groups = pool.map_groups([flights.tasks("lemniscate_near_ground", m, nets3_tuned if m.endswith(TUNED) else nets3,
                                            config.lemniscate) for m in own] +
                             [[gains_task(config, "lemniscate_near_ground", "pd_eso", {}, g, s, config.lemniscate)
                               for s in flights.seeds] for g in as_gain.values()])
    logs["lemniscate_near_ground"] = {m: (shared["lemniscate_near_ground"][m] if m in SHARED_METHODS
                                          else groups[own.index(m)]) for m in LEMNISCATE_METHODS}
    logs["lemniscate_near_ground"].update(zip(as_gain, groups[len(own):]))
    results["lemniscate_near_ground"] = {"metric": "z_rmse_cm", "methods": {
        m: summarise([lemniscate_rmse_cm(f, config) for f in fl]) for m, fl in logs["lemniscate_near_ground"].items()}}
    flights.tick(f"{recipe.name}: lemniscate_near_ground")
    results["robustness"] = _robustness(flights, {
        "neural_eso": base, "neural_eso_tuned": tuned, "neural_eso_tdr": nets3,
        "neural_eso_tdr_tuned": {"landing": tuned["landing"], "lemniscate": nets3_tuned}}, shared_robustness)
    flights.tick(f"{recipe.name}: robustness")
    networks = {_file_stem(n.metadata["id"]): n for n in nets.values()}
    networks.update(acceleration=acc_res.network, tdr=tdr_res.network)
    return {"results": results, "details": details, "logs": logs, "networks": networks, "flown": nets3,
            "flown_tuned": {"landing": tuned["landing"], "lemniscate": nets3_tuned}}


def _tdr_as_gain(config: PaperConfig, flown: dict) -> dict:
    """method → the gains PD+ESO flies to show what a TDR network learned as gain: the gains its network was flown
    at plus its slopes on p_z and v_z (:func:`neso.learning.equivalent_gains`), where those stay positive."""
    from neso.learning import equivalent_gains

    out = {}
    for method, (gains, net) in flown.items():
        change = equivalent_gains(net.learned["slopes"])
        if change is not None and min(change.gains(gains.kp, gains.kd)) > 0:
            out[method] = ZGains(*change.gains(gains.kp, gains.kd), gains.omega_o_rps)
    return out


def _tuned_networks(flights: _Flights, recipe: Recipe, base_net: LipschitzMLP, bound: float, z_t, y_t,
                    lag: ThrustLag, details: dict) -> dict:
    """kind → networks flown at that kind's tuned gains: the base network trained on the same teacher data to the
    recipe's bound for those gains (the flown one when the bound is the same, as the paper recipe's is)."""
    config = flights.config
    by_bound = {bound: base_net}
    out = {}
    for kind in KINDS:
        gains = flights.tuned.gains[kind]
        b = config.base_bound(recipe, gains)
        if b not in by_bound:
            res = train(z_t, y_t, bound=b, units=recipe.bound_units, config=config, name=f"base-tuned-{kind}",
                        fset_key=recipe.feature_set, lag=lag, recipe_name=recipe.name,
                        source=f"{recipe.base_label}_teacher:nominal_landing")
            by_bound[b] = res.network
            details["networks"][f"base_tuned_{kind}"] = _network_details(res, config, gains)
        out[kind] = {"base": by_bound[b]}
    details["tuned_bounds"] = {kind: config.base_bound(recipe, flights.tuned.gains[kind]) for kind in KINDS}
    return out


def tdr_network(tdr_log: FlightLog, recipe: Recipe, config: PaperConfig, base: dict, lag: ThrustLag, tdr_traj, *,
                bound: float | None = None):
    """Total Disturbance Retraining: the recipe's TDR labels of a neural_eso lemniscate flight ``tdr_log``
    (``tdr_traj``, its ramp left out), fine-tuned from ``base["base"]`` to ``bound`` (default the recipe's for the
    flown gains); the training result."""
    z_r, y_r = training_pairs([tdr_log], recipe.tdr_label, recipe.feature_set, lag, skip_s=tdr_traj.cycle_start_s,
                              regressors=recipe.regressors)
    return train(z_r, y_r, bound=config.base_bound(recipe) if bound is None else bound, units=recipe.bound_units,
                 config=config,
                 name=f"{recipe.name}-tdr" if recipe.bound_units == "normalised" else "tdr",
                 fset_key=recipe.feature_set, lag=lag, recipe_name=recipe.name, init=base["base"],
                 scalers=recipe.tdr_scalers, source=f"{recipe.tdr_label}:lemniscate_near_ground")


def _landing_experiment(flights: _Flights, scenario, methods, networks, tuned_networks, shared, details):
    config = flights.config
    own = [m for m in methods if m not in SHARED_METHODS]
    groups = flights.pool.map_groups([flights.tasks(scenario, m, tuned_networks if m.endswith(TUNED) else networks,
                                                    config.landing) for m in own])
    logs = {m: (shared[scenario][m] if m in SHARED_METHODS else groups[own.index(m)]) for m in methods}
    out = {"metric": "steady_state_abs_z_error_cm", "methods": {}}
    details["settling_time_s"][scenario] = {}
    for method, fl in logs.items():
        metrics = [landing_metrics(f, config) for f in fl]
        out["methods"][method] = summarise([m[0] for m in metrics])
        details["settling_time_s"][scenario][method] = summarise([m[1] for m in metrics])
    return out, logs


def _noise_free(flights: _Flights, networks: dict, tuned_networks: dict, shared: dict) -> tuple[dict, dict]:
    """The nominal landing with noise-free motion capture: steady-state error, thrust spread and the
    dominant frequency of the error (a limit cycle shows as a peak with a large thrust spread)."""
    config = flights.config
    ours, tuned = flights.pool.map_groups([
        flights.tasks("nominal_landing_noiseless", "neural_eso", networks, config.landing),
        flights.tasks("nominal_landing_noiseless", "neural_eso_tuned", tuned_networks, config.landing)])
    noiseless = shared["nominal_landing_noiseless"]
    logs = {"pd_eso": noiseless["pd_eso"], "pd_eso_tuned": noiseless["pd_eso_tuned"], "neural_eso": ours,
            "neural_eso_tuned": tuned}
    out = {"metric": "steady_state_abs_z_error_cm", "methods": {}, "thrust_std_n": {}, "peak_hz": {}}
    for method, fl in logs.items():
        out["methods"][method] = summarise([landing_metrics(f, config)[0] for f in fl])
        stats = [steady_spectrum(f, config) for f in fl if not f.diverged]
        out["thrust_std_n"][method] = summarise([s[0] for s in stats])
        out["peak_hz"][method] = summarise([s[1] for s in stats])
    return out, logs


def _robustness(flights: _Flights, networks: dict, done: dict | None = None) -> dict:
    """The tuning's conditions 2 and 3 (:mod:`sim.tuning`) measured on the evaluation seeds for each kind's
    :data:`ROBUSTNESS_METHODS` among ``networks`` (method → its networks, or for a tuned method kind → its networks);
    ``done``: an earlier call's result whose methods are reused. Each method's figures, and whether it meets the
    conditions against PD+ESO at the flown gains on the same seeds."""
    config, tuning = flights.config, flights.config.tuning
    out = {"noise_factor": tuning.noise_factor, "hold_after_s": tuning.hold_after_s,
           "max_thrust_std_ratio": tuning.max_thrust_std_ratio, "kinds": {}}
    for kind, methods in ROBUSTNESS_METHODS.items():
        scenario, lemniscate = KINDS[kind], kind == "lemniscate"
        have = dict((done or {}).get("kinds", {}).get(kind, {}))
        todo = [m for m in methods if m in networks and m not in have]
        plans = []
        for m in todo:
            name, gains = method_gains(m, scenario, config, flights.tuned)
            nets = networks[m][kind] if m.endswith(TUNED) and kind in networks[m] else networks[m]
            plans.append(robustness_tasks(config, tuning, name, nets, gains, flights.seeds, lemniscate=lemniscate))
        for m, logs in zip(todo, flights.pool.map_groups(plans)):
            have[m] = robustness(logs, config, tuning, lemniscate=lemniscate).to_dict()
        out["kinds"][kind] = {m: have[m] for m in methods if m in have}
    return _judged(out, tuning)


def _judged(out: dict, tuning: TuningConfig) -> dict:
    """Each method's ``why``: the conditions it fails against ``pd_eso``'s figures of the same kind."""
    from sim.tuning import Robustness

    def rob(d: dict) -> Robustness:
        missing = {"lemniscate_rmse_cm": None, "quiet_thrust_std_n": math.inf}  # to_dict's None: none flown, crashed
        return Robustness(**{k: (missing.get(k, math.nan) if v is None else v) for k, v in d.items()
                             if k in Robustness.__dataclass_fields__})

    for by_method in out["kinds"].values():
        if "pd_eso" not in by_method:
            continue
        ref = rob(by_method["pd_eso"])
        for d in by_method.values():
            d["why"] = failed_conditions(rob(d), ref, tuning)
    return out


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


def _network_details(result, config: PaperConfig, gains: ZGains | None = None) -> dict:
    net = result.network
    g = gains or config.paper_gains()
    cert = flight_certificate(NetworkSlopes.of(net), kp=g.kp, kd=g.kd, omega_o=g.omega_o_rps,
                              plant=LoopPlant.of(config.control))
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
        "gain_change": net.learned["gain_change"],
        "start": net.metadata.get("start", ""),
        "largest_certified_physical": cert.max_certified,
        "gains": g.to_dict(),
        "feature_set": net.feature_set.key,
        "val_loss": result.val_loss,
        "n_train": result.n_train,
        "n_val": result.n_val,
    }


def results_json(run: PaperRun, trials: int) -> dict:
    """The documented shape (``experiments`` for the first recipe), plus every recipe side by side."""
    return {"experiments": run.results, "seconds": run.seconds, "trials": trials,
            "recipe": next(iter(run.by_recipe), None),
            "tuned_gains": {k: g.to_dict() for k, g in run.tuned.gains.items()} if run.tuned else None,
            "tuned_gains_fly": dict(SCENARIO_KIND),
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
