"""Learning the disturbance or the loop (issue 32): the closed-loop bias of a network retrained in flight, measured.

A network's label is measured in closed loop, where the state answers the disturbance: a push up raises the vehicle
until the observer catches it. On Experiment 3's lemniscate, flown at constant height, that answer is all the state
does in z, so a regression of the label on the measured p_z, v_z finds the loop — positive slopes, which, since the
controller subtracts f̂, are extra feedback gain — where the world's own physics has negative ones (ground effect
falls with height, rotor drag opposes the climb). This module flies it and measures, on the same seeds:

- TDR candidates made three ways from one base network and one TDR data flight: on the measured state (what every
  recipe did), on the reference (z*, ż*: an instrument the disturbance does not move; the certified recipe's
  default now), and on the reference of a data flight with a z dither (:class:`neso.trajectories.Dithered`, an
  excitation the disturbance does not cause). Each with its mean slopes ∂f_N/∂p_z, ∂f_N/∂v_z, the equivalent
  change of the controller's gains (Δk_p = slope in p_z, Δk_d = slope in v_z: the controller subtracts f_N),
  its validation loss against predicting the mean, and its lemniscate z RMSE; beside them PD+ESO at the flown
  gains and at the candidate's equivalent gains (what the "learning" is worth as a retune), and the world's own
  slopes (:func:`sim.quadrotor.z_disturbance_slopes`) at the lemniscate's height.
- How much of the lemniscate's disturbance repeats from one cycle to the next (the most any function of where the
  vehicle is on the figure eight can learn), with and without the motion capture's noise.
- Where learning the disturbance does pay: the landing's descent, where the ground effect changes faster than the
  observer follows it: z RMSE and peak over the descent under PD+ESO and Neural-ESO, with and without noise.

Pure computation over :mod:`sim.experiments` flights; ``neso experiment bias`` prints and writes it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from neso.control import ControlConfig
from neso.features import feature_set
from neso.learning import RECIPES, identify_thrust_lag, recipe_blocks
from neso.training import train_lipschitz_mlp
from neso.trajectories import Dithered
from sim.experiments import PaperConfig, training_pairs
from sim.flights import FlightPool, FlightTask, lemniscate_rmse_cm
from sim.mocap import NOISELESS_MOCAP
from sim.quadrotor import z_disturbance_slopes
from sim.scenarios import make_scenario

RECIPE = "certified"
VARIANTS = (("state", "plain"), ("reference", "plain"), ("reference", "dither"))


def _train(z, y, bound, init, config: PaperConfig):
    recipe = RECIPES[RECIPE]
    blocks, block_bounds = recipe_blocks(recipe, feature_set(recipe.feature_set), bound)
    return train_lipschitz_mlp(z, y, lipschitz_bound=bound, bound_units="physical", epochs=config.epochs,
                               seed=config.seed, init=init, scalers=recipe.tdr_scalers if init is not None else "fit",
                               blocks=blocks, block_bounds=block_bounds,
                               metadata={"feature_set": recipe.feature_set,
                                         "mass_kg": repr(float(config.control.vehicle.mass_kg))})


def _repeatable(t: np.ndarray, x: np.ndarray, start_s: float, period_s: float, bins: int = 150) -> float:
    """The share of ``x``'s variance after ``start_s`` that its average over the cycle's phase explains."""
    m = t >= start_s
    phase = ((t[m] - start_s) % period_s) / period_s
    b = np.minimum((phase * bins).astype(int), bins - 1)
    means = np.array([x[m][b == i].mean() if np.any(b == i) else 0.0 for i in range(bins)])
    return float(1.0 - np.var(x[m] - means[b]) / np.var(x[m]))


def _descent(log, landing) -> tuple[float, float]:
    """(z RMSE, peak |e_z|) in cm from the descent's start to 1 s after its end."""
    d = (log.t_s >= landing.hold_before_s) & (log.t_s <= landing.descent_end_s + 1.0)
    e = log.z_error_m[d]
    return float(np.sqrt(np.mean(e ** 2)) * 100), float(np.max(np.abs(e)) * 100)


def _stats(values) -> dict:
    v = np.asarray(values, dtype=float)
    return {"mean": float(np.mean(v)), "std": float(np.std(v)), "trials": v.tolist()}


def run_bias(config: PaperConfig = PaperConfig(), *, log=print) -> dict:
    """The measurements of the module docstring at ``config.control``'s gains (``config.trials`` seeds)."""
    recipe = RECIPES[RECIPE]
    pool = FlightPool(config.workers)
    est = config.estimator_config()
    seeds = [config.seed * 1000 + 1 + i for i in range(config.trials)]

    def tasks(scenario, method, nets, trajectory, seed_list, control=config.control):
        return [FlightTask(scenario, method, nets, s, trajectory, est, control) for s in seed_list]

    try:
        log("ESO-teacher landings and the base network (on the reference)")
        teacher = pool.map(tasks("nominal_landing", "pd_eso", {}, config.landing,
                                 [config.seed * 1000 + 500 + i for i in range(config.teacher_flights)]))
        lag = identify_thrust_lag([t.series() for t in teacher]).lag
        bound = config.base_bound(recipe)
        base = _train(*training_pairs(teacher, recipe.base_label, recipe.feature_set, lag, regressors="reference"),
                      bound, None, config)
        tdr_traj = replace(config.lemniscate, cycles=config.tdr_cycles)
        kp, kd = config.control.kp[2], config.control.kd[2]
        lemniscate = {"pd_eso": pool.map(tasks("lemniscate_near_ground", "pd_eso", {}, config.lemniscate, seeds)),
                      "neural_eso": pool.map(tasks("lemniscate_near_ground", "neural_eso", {"base": base.network},
                                                   config.lemniscate, seeds))}
        data_flights = {
            data: pool.map(tasks("lemniscate_near_ground", "neural_eso", {"base": base.network},
                                 tdr_traj if data == "plain" else Dithered(tdr_traj), [config.seed * 1000 + 900]))[0]
            for data in ("plain", "dither")}
        candidates = {}
        for regressors, data in VARIANTS:
            name = f"tdr_{regressors}_{data}"
            log(f"TDR on the {'dithered ' if data == 'dither' else ''}lemniscate, regressors: {regressors}")
            z, y = training_pairs([data_flights[data]], recipe.tdr_label, recipe.feature_set, lag,
                                  skip_s=tdr_traj.cycle_start_s, regressors=regressors)
            res = _train(z, y, bound, base.network, config)
            sp, sv = res.slopes["pos_z_m"], res.slopes["vel_z_mps"]
            retune = replace(config.control, kp=(*config.control.kp[:2], kp + sp), kd=(*config.control.kd[:2], kd + sv))
            flown = pool.map(tasks("lemniscate_near_ground", "neural_eso", {"base": res.network}, config.lemniscate,
                                   seeds))
            as_gain = pool.map(tasks("lemniscate_near_ground", "pd_eso", {}, config.lemniscate, seeds, retune))
            candidates[name] = {"regressors": regressors, "data": data, "slope_pos_z": sp, "slope_vel_z": sv,
                                "delta_kp": sp, "delta_kd": sv, "val_loss_vs_mean": res.val_loss_vs_mean,
                                "rmse_cm": _stats([lemniscate_rmse_cm(f, config) for f in flown]),
                                "pd_eso_at_equivalent_gains_rmse_cm": _stats([lemniscate_rmse_cm(f, config)
                                                                              for f in as_gain])}
        log("the lemniscate's repeatable share, and the landing's descent")
        lem = config.lemniscate
        noise_free = pool.map([FlightTask("lemniscate_near_ground", "pd_eso", {}, s, lem, est, config.control,
                                          (("mocap", NOISELESS_MOCAP),)) for s in seeds])
        repeat = {}
        for world, flights in (("noise", lemniscate["pd_eso"]), ("noise-free", noise_free)):
            def share(series):
                return float(np.mean([_repeatable(f.t_s, series(f), lem.cycle_start_s, lem.period_s) for f in flights]))

            repeat[world] = {"disturbance": share(lambda f: f.f_true[:, 2]),
                             "observer_error": share(lambda f: f.f_true[:, 2] - f.f_hat[:, 2]),
                             "z_error": share(lambda f: f.z_error_m),
                             "disturbance_rms_mps2": float(np.mean([np.std(f.f_true[f.t_s >= lem.cycle_start_s, 2])
                                                                    for f in flights]))}
        descent = {}
        for scenario in ("nominal_landing", "nominal_landing_noiseless"):
            for method, nets in (("pd_eso", {}), ("neural_eso", {"base": base.network})):
                runs = [_descent(f, config.landing) for f in pool.map(tasks(scenario, method, nets, config.landing, seeds))]
                descent[f"{scenario}/{method}"] = {"rmse_cm": _stats([r[0] for r in runs]),
                                                   "peak_cm": _stats([r[1] for r in runs])}
    finally:
        pool.close()
    world = make_scenario("lemniscate_near_ground")
    return {"gains": {"kp": kp, "kd": kd, "omega_o": config.omega_o_rps}, "bound": bound, "trials": config.trials,
            "base": {"slope_pos_z": base.slopes["pos_z_m"], "slope_vel_z": base.slopes["vel_z_mps"],
                     "val_loss_vs_mean": base.val_loss_vs_mean},
            "world_slopes": {f"{h:g} m": dict(zip(("pos_z", "vel_z"), z_disturbance_slopes(world, h)))
                             for h in (config.lemniscate.height_m, config.landing.end_height_m)},
            "lemniscate": {"pd_eso_rmse_cm": _stats([lemniscate_rmse_cm(f, config) for f in lemniscate["pd_eso"]]),
                           "neural_eso_rmse_cm": _stats([lemniscate_rmse_cm(f, config)
                                                         for f in lemniscate["neural_eso"]]),
                           "candidates": candidates},
            "repeatable_share": repeat, "descent": descent}


def format_bias(r: dict) -> str:
    g = r["gains"]
    lem = r["lemniscate"]
    pd = lem["pd_eso_rmse_cm"]["mean"]
    lines = [f"Learning the disturbance or the loop — k_p {g['kp']:g}, k_d {g['kd']:g}, ω_o {g['omega_o']:g}, "
             f"state budget {r['bound']:.3g}, {r['trials']} seeds",
             "  the world's own slopes: " + "; ".join(f"{h}: ∂f/∂p_z {s['pos_z']:+.2f} /s², ∂f/∂v_z {s['vel_z']:+.2f} /s"
                                                     for h, s in r["world_slopes"].items()),
             f"  base network (landing, on the reference): ∂f_N/∂p_z {r['base']['slope_pos_z']:+.2f}, ∂f_N/∂v_z "
             f"{r['base']['slope_vel_z']:+.2f}, val loss {r['base']['val_loss_vs_mean']:.3f} × the mean's",
             f"  lemniscate z RMSE: PD+ESO {pd:.3f} cm, Neural-ESO {lem['neural_eso_rmse_cm']['mean']:.3f} cm",
             "  TDR candidate          ∂f_N/∂p_z  ∂f_N/∂v_z  val/mean  RMSE cm (vs PD+ESO)  PD+ESO at k_p+Δ, k_d+Δ"]
    for name, c in lem["candidates"].items():
        rm, eq = c["rmse_cm"]["mean"], c["pd_eso_at_equivalent_gains_rmse_cm"]["mean"]
        lines.append(f"  {name:22s} {c['slope_pos_z']:+9.2f}  {c['slope_vel_z']:+9.2f}  {c['val_loss_vs_mean']:8.3f}  "
                     f"{rm:.3f} ({(rm / pd - 1) * 100:+5.1f} %)      {eq:.3f} ({(eq / pd - 1) * 100:+5.1f} %)")
    lines.append("  repeatable from cycle to cycle (share of variance): " + "; ".join(
        f"{w}: disturbance {v['disturbance']:.2f} (RMS {v['disturbance_rms_mps2']:.2f} m/s²), observer error "
        f"{v['observer_error']:.2f}, z error {v['z_error']:.2f}" for w, v in r["repeatable_share"].items()))
    lines.append("  landing descent (start to 1 s after): " + "; ".join(
        f"{k}: RMSE {v['rmse_cm']['mean']:.3f}, peak {v['peak_cm']['mean']:.3f} cm" for k, v in r["descent"].items()))
    return "\n".join(lines)


def config_for(kp: float | None, kd: float | None, base: PaperConfig = PaperConfig()) -> PaperConfig:
    """``base`` with the z gains replaced (None: keep)."""
    c = base.control
    return replace(base, control=ControlConfig(kp=(*c.kp[:2], kp if kp is not None else c.kp[2]),
                                               kd=(*c.kd[:2], kd if kd is not None else c.kd[2]), dt_s=c.dt_s,
                                               vehicle=c.vehicle))
