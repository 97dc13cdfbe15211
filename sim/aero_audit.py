"""Experiment 3's near-ground aerodynamics, measured: which effects the lemniscate contains, how
much each moves the true z disturbance, and how much of that disturbance is a function of
candidate network inputs.

Both measurements fly Experiment 3's lemniscate (``lemniscate_near_ground``, the paper's
Lemniscate, 5 full cycles) under PD+ESO with the paper's trial seeds and look at the full
cycles only (t >= ``cycle_start_s``):

- ``audit_effects``: each effect of the world switched off, and each candidate from the
  literature switched on. Along the flown trajectory: at every tick the state is branched into
  the other world (``QuadrotorSim.branch``) and stepped with the same setpoint; the effect's
  contribution to the true z disturbance ``FlightLog.f_true[:, 2]`` (truth, m/s^2) is the
  difference, same state and random draws: mean, RMS, peak. In closed loop: the same seeds
  flown in the other world, pd_eso z RMSE with and without.
- ``disturbance_predictability``: R^2 and residual RMS of the true z disturbance fitted on
  candidate network inputs (as the network would measure them), by least squares and by a
  small MLP, held out one seed at a time; the disturbance referenced to the command (f_true_z
  as the simulator defines it) and to the applied thrust (``applied_referenced_f_z``).

Pure computation over :mod:`sim.experiments` flights; ``neso experiment aero`` prints and
writes it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from neso.features import ThrustLag, applied_thrust_series

from sim.experiments import PaperConfig
from sim.flights import FlightPool, FlightTask
from sim.ground_effect import NoGroundEffect
from sim.rotor_aero import CheesemanBennettWashout, FaesslerTranslationalLift, RotorSpeedDrag, ThrustProportionalDrag
from sim.runner import FlightLog
from sim.scenarios import make_scenario
from sim.turbulence import NO_TURBULENCE

SCENARIO = "lemniscate_near_ground"
METHOD = "pd_eso"

# The literature's speed- and thrust-dependent rotor aerodynamics (sim.rotor_aero), as one world change.
LITERATURE_ROTOR_AERO: tuple[tuple[str, object], ...] = (
    ("rotor_drag", RotorSpeedDrag()),
    ("translational_lift", FaesslerTranslationalLift()),
    ("ground_effect_washout", CheesemanBennettWashout()),
)


@dataclass(frozen=True)
class Effect:
    """One effect of the audit: ``in_world`` effects are switched off, candidates switched on.
    ``change(config)`` returns the SimConfig fields to replace."""

    name: str
    in_world: bool
    constant: str
    source: str
    change: Callable


def _params(cfg, **kw):
    return {"params": replace(cfg.params, **kw)}


def _inner(cfg, **kw):
    return {"inner_loop": replace(cfg.inner_loop, **kw)}


EFFECTS: tuple[Effect, ...] = (
    Effect("ground effect (per rotor)", True, "1 + 0.215 e^(-h/0.195 m)", "DESIGN.md fit to Neural-Lander's real-flight network",
           lambda c: {"ground_effect": NoGroundEffect()}),
    Effect("ground effect under tilt (rotor heights vs hub)", True, "hub offsets R (+-a, +-a, 0), a = 0.127 m",
           "Sanchez-Cuevas et al. 2017 partial ground effect: each rotor at its own height",
           lambda c: {"ground_effect_per_rotor": False}),
    Effect("rotor drag, in-plane (x, y)", True, "0.4, 0.4 1/s", "Faessler et al. RA-L 2018 (0.544, 0.386 identified)",
           lambda c: _params(c, drag_coeff_per_s=(0.0, 0.0, c.params.drag_coeff_per_s[2]))),
    Effect("rotor drag, axial (z)", True, "0.5 1/s", "momentum theory, T V / (2 v_h)",
           lambda c: _params(c, drag_coeff_per_s=(*c.params.drag_coeff_per_s[:2], 0.0))),
    Effect("near-ground gusts", True, "sigma = 0.05 + 1.0 v e^(-h/0.2) m/s", "assumed (simplified MIL-F-8785C form)",
           lambda c: {"turbulence": NO_TURBULENCE}),
    Effect("battery sag", True, "-2 %/min", "LiPo 4.2 -> 3.7 V, thrust ~ V^2",
           lambda c: _params(c, battery_sag_per_min=0.0)),
    Effect("mass 5 % above the model", True, "1.05 vs 1.0 kg", "brief",
           lambda c: _params(c, mass_kg=1.0)),
    Effect("command transport delay", True, "10 ms", "MAVLink + PX4 scheduling",
           lambda c: {"command_delay_s": 0.0}),
    Effect("thrust lag", True, "44.8 ms", "Neural-Lander's u <- 0.8u + 0.2u_d at 100 Hz",
           lambda c: _inner(c, thrust_time_constant_s=1e-4)),
    Effect("rotor thrust limits (clipping, no desaturation)", True, "each rotor in [0, 4.9 N]",
           "max thrust 19.62 N (thrust/weight 2); PX4's mixer desaturation not modelled",
           lambda c: _inner(c, rotor_thrust_limits=False)),
    Effect("rotor drag ~ rotor speed (sqrt T_i)", False, "factor mean sqrt(T_i / T_h)",
           "Mahony et al. RAM 2012; Svacha et al. ICUAS 2017; RotorPy", lambda c: {"rotor_drag": RotorSpeedDrag()}),
    Effect("rotor drag ~ thrust", False, "factor T / T_h", "Kai, Hamel, Samson 2017",
           lambda c: {"rotor_drag": ThrustProportionalDrag()}),
    Effect("translational lift k_h v_h^2", False,
           f"k_h = {FaesslerTranslationalLift().k_h_per_m(make_scenario(SCENARIO).params.hover_induced_velocity_mps):.4f} 1/m",
           "Faessler et al. RA-L 2018 k_h = 0.009 1/m, scaled at equal V/v_h",
           lambda c: {"translational_lift": FaesslerTranslationalLift()}),
    Effect("ground-effect washout with forward speed", False, "image term / (1 + (V/v_h)^2), v_h = 9.11 m/s",
           "Cheeseman & Bennett, ARC R&M 3021, 1955", lambda c: {"ground_effect_washout": CheesemanBennettWashout()}),
)


def _tasks(config: PaperConfig, overrides: tuple[tuple[str, object], ...], seeds: list[int]) -> list[FlightTask]:
    est = config.estimator_config()
    return [FlightTask(SCENARIO, METHOD, {}, s, config.lemniscate, est, config.control, overrides) for s in seeds]


def _window(log: FlightLog, config: PaperConfig) -> np.ndarray:
    return np.isfinite(log.t_s) & (log.t_s >= config.lemniscate.cycle_start_s)


def _stats(x: np.ndarray) -> dict:
    return {"mean": float(np.mean(x)), "rms": float(np.sqrt(np.mean(x * x))), "peak": float(np.max(np.abs(x)))}


def _rmse_cm(logs: list[FlightLog], config: PaperConfig) -> float:
    errs = [np.sqrt(np.mean(log.z_error_m[_window(log, config)] ** 2)) * 100 for log in logs]
    return float(np.mean(errs))


def paper_seeds(config: PaperConfig) -> list[int]:
    """The trial seeds ``run_paper`` flies (seed * 1000 + 1 ...)."""
    return [config.seed * 1000 + 1 + i for i in range(config.trials)]


@dataclass(frozen=True)
class _BranchTask:
    flight: FlightTask
    variants: tuple  # SimConfig per effect


def _fly_with_branches(task: _BranchTask) -> tuple[FlightLog, np.ndarray]:
    """One flight, and at every tick each variant world branched off the flown state and stepped
    with the same setpoint: (log, f_z of each variant (n_variants, N))."""
    from neso.methods import build_estimator
    from sim.runner import fly

    t = task.flight
    n = int(round(t.trajectory.duration_s / t.control.dt_s))
    f_variant = np.full((len(task.variants), n), np.nan)

    def before_step(k, sim, setpoint):
        for i, cfg in enumerate(task.variants):
            twin = sim.branch(cfg)
            twin.step(setpoint)
            f_variant[i, k] = twin.truth.disturbance_acc_enu_mps2[2]

    log = fly(sim_config=make_scenario(t.scenario, **dict(t.sim_overrides)),
              estimator=build_estimator(t.method, t.estimator, t.networks), trajectory=t.trajectory,
              seed=t.seed, control=t.control, before_step=before_step)
    return log, f_variant


def audit_effects(config: PaperConfig = PaperConfig(), *, effects=EFFECTS,
                  world: tuple[tuple[str, object], ...] = (), pool: FlightPool | None = None) -> dict:
    """Each effect's contribution to f_true_z on the lemniscate flown in the world
    ``make_scenario`` gives with ``world`` applied.

    Along the trajectory: at every tick the flown state is branched into the world with the
    effect switched (``QuadrotorSim.branch``) and stepped with the same setpoint; the effect's
    contribution is f_z with it minus f_z without it, from the same state and random draws.
    In closed loop: the same seeds flown without (or with) the effect, z RMSE of each."""
    seeds = paper_seeds(config)
    base_cfg = make_scenario(SCENARIO, **dict(world))
    changes = [effect.change(base_cfg) for effect in effects]
    variants = tuple(replace(base_cfg, **c) for c in changes)
    own = pool or FlightPool(config.workers)
    try:
        branched = own.map([_BranchTask(t, variants) for t in _tasks(config, world, seeds)], _fly_with_branches)
        closed = own.map_groups([_tasks(config, tuple({**dict(world), **c}.items()), seeds) for c in changes])
    finally:
        if pool is None:
            own.close()
    base = [log for log, _ in branched]
    f_all = np.concatenate([log.f_true[_window(log, config), 2] for log in base])
    out = {
        "scenario": SCENARIO, "method": METHOD, "seeds": seeds,
        "window_s": [config.lemniscate.cycle_start_s, config.lemniscate.duration_s],
        "f_true_z_mps2": _stats(f_all) | {"std": float(np.std(f_all))},
        "z_rmse_cm": _rmse_cm(base, config),
        "effects": [],
    }
    for i, (effect, logs) in enumerate(zip(effects, closed)):
        sign = 1.0 if effect.in_world else -1.0  # always "with the effect" minus "without"
        d = np.concatenate([sign * (log.f_true[:, 2] - f[i])[_window(log, config)] for log, f in branched])
        with_, without = (base, logs) if effect.in_world else (logs, base)
        out["effects"].append({
            "effect": effect.name, "in_world": effect.in_world, "switched": "off" if effect.in_world else "on",
            "constant": effect.constant, "source": effect.source,
            "delta_f_z_mps2": _stats(d),
            "z_rmse_cm": {"with": _rmse_cm(with_, config), "without": _rmse_cm(without, config)},
        })
    return out


# ------------------------------------------------------------------ disturbance predictability
FEATURE_SETS: dict[str, tuple[str, ...]] = {
    "state [p_z, v_z, roll, pitch]": ("p_z", "v_z", "roll", "pitch"),
    "state + v_h": ("p_z", "v_z", "roll", "pitch", "v_h"),
    "state + v_h, v_h^2": ("p_z", "v_z", "roll", "pitch", "v_h", "v_h2"),
    "state + applied thrust": ("p_z", "v_z", "roll", "pitch", "T_applied"),
    "state + v_h, v_h^2 + applied thrust": ("p_z", "v_z", "roll", "pitch", "v_h", "v_h2", "T_applied"),
    "paper [p_z, v_z, T_k-1, roll, pitch]": ("p_z", "v_z", "T_prev", "roll", "pitch"),
    "paper + applied thrust": ("p_z", "v_z", "T_prev", "roll", "pitch", "T_applied"),
}


def candidate_inputs(log: FlightLog, *, lag_s: float, delay_s: float, dt_s: float) -> dict[str, np.ndarray]:
    """The candidate network inputs of every tick, as measured (mocap), plus the applied-thrust
    estimate; each (N,)."""
    vel = log.vel_meas_mps
    v_h = np.hypot(vel[:, 0], vel[:, 1])
    return {
        "p_z": log.pos_meas_m[:, 2], "v_z": vel[:, 2], "roll": log.att_meas_rad[:, 0], "pitch": log.att_meas_rad[:, 1],
        "v_h": v_h, "v_h2": v_h * v_h, "T_prev": log.thrust_prev_n,
        "T_applied": applied_thrust_series(log.thrust_prev_n, ThrustLag(lag_s, delay_s), dt_s),
    }


def _fit_linear(x: np.ndarray, y: np.ndarray, x_test: np.ndarray) -> np.ndarray:
    a = np.column_stack([x, np.ones(len(x))])
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return np.column_stack([x_test, np.ones(len(x_test))]) @ coef


def _fit_mlp(x: np.ndarray, y: np.ndarray, x_test: np.ndarray, *, seed: int, epochs: int) -> np.ndarray:
    import torch

    torch.manual_seed(seed)
    mu, sd = x.mean(0), x.std(0) + 1e-9
    ym, ys = y.mean(), y.std() + 1e-9
    xt = torch.tensor((x - mu) / sd, dtype=torch.float32)
    yt = torch.tensor((y - ym) / ys, dtype=torch.float32)[:, None]
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 32), torch.nn.Tanh(), torch.nn.Linear(32, 32),
                              torch.nn.Tanh(), torch.nn.Linear(32, 1))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        for idx in torch.randperm(len(xt), generator=gen).split(256):
            opt.zero_grad()
            loss = torch.mean((net(xt[idx]) - yt[idx]) ** 2)
            loss.backward()
            opt.step()
    with torch.no_grad():
        pred = net(torch.tensor((x_test - mu) / sd, dtype=torch.float32))[:, 0].numpy()
    return pred * ys + ym


def applied_referenced_f_z(log: FlightLog, t_applied_n: np.ndarray, *, nominal_mass_kg: float,
                           gravity_mps2: float = 9.81) -> np.ndarray:
    """f_true_z moved from the command's reference to the applied thrust's: the z acceleration
    that neither gravity nor the applied thrust along the measured attitude explains,
    f_true_z + (a_cmd,z(k-1) + g) - T_applied cos(roll) cos(pitch) / m_nom (m/s^2, (N,); the first
    element, which has no previous command, is NaN). What a lag-consistent label aims at."""
    believed = np.full(len(log.t_s), np.nan)
    believed[1:] = log.acc_cmd_mps2[:-1, 2] + gravity_mps2  # R_cmd e3 T_cmd / m_nom, z
    applied = t_applied_n * np.cos(log.att_meas_rad[:, 0]) * np.cos(log.att_meas_rad[:, 1]) / nominal_mass_kg
    return log.f_true[:, 2] + believed - applied


TARGETS = ("command", "applied")


def disturbance_predictability(logs: list[FlightLog], config: PaperConfig = PaperConfig(), *,
                               feature_sets: dict[str, tuple[str, ...]] = FEATURE_SETS,
                               mlp_epochs: int = 40, target: str = "command") -> dict:
    """R^2 and residual RMS (m/s^2) of the true z disturbance fitted on each feature set, leave one
    flight (seed) out, predictions pooled over the held-out flights. ``target``: ``command`` is
    f_true_z as the simulator defines it (against the command the controller believes acts),
    ``applied`` is ``applied_referenced_f_z``. The thrust lag and delay for the applied-thrust
    estimate are the world's (the identified values)."""
    if target not in TARGETS:
        raise ValueError(f"unknown target {target!r}; known: {TARGETS}")
    cfg = make_scenario(SCENARIO)
    kw = {"lag_s": cfg.inner_loop.thrust_time_constant_s, "delay_s": cfg.command_delay_s, "dt_s": config.control.dt_s}
    per_flight = []
    for log in logs:
        k = _window(log, config)
        k[0] = False
        inputs = candidate_inputs(log, **kw)
        y = log.f_true[:, 2] if target == "command" else applied_referenced_f_z(
            log, inputs["T_applied"], nominal_mass_kg=config.control.vehicle.mass_kg,
            gravity_mps2=config.control.vehicle.gravity_mps2)
        per_flight.append(({name: v[k] for name, v in inputs.items()}, y[k]))
    y_all = np.concatenate([y for _, y in per_flight])
    out = {"target": target, "samples": int(len(y_all)), "flights": len(per_flight),
           "f_z_std_mps2": float(np.std(y_all)), "fits": []}
    for label, names in feature_sets.items():
        preds = {"linear": [], "mlp": []}
        for i, (held_x, _) in enumerate(per_flight):
            train = [j for j in range(len(per_flight)) if j != i]
            x = np.concatenate([np.column_stack([per_flight[j][0][n] for n in names]) for j in train])
            y = np.concatenate([per_flight[j][1] for j in train])
            x_test = np.column_stack([held_x[n] for n in names])
            preds["linear"].append(_fit_linear(x, y, x_test))
            preds["mlp"].append(_fit_mlp(x, y, x_test, seed=config.seed + i, epochs=mlp_epochs))
        row = {"features": label, "inputs": list(names)}
        for kind, parts in preds.items():
            resid = y_all - np.concatenate(parts)
            row[kind] = {"r2": float(1.0 - np.sum(resid**2) / np.sum((y_all - y_all.mean()) ** 2)),
                         "residual_rms_mps2": float(np.sqrt(np.mean(resid**2)))}
        out["fits"].append(row)
    return out


def run_aero(config: PaperConfig = PaperConfig(), *, log=print) -> dict:
    """The audit in the world the scenario gives with ``config.sim_overrides``, and the
    predictability there, with the literature's rotor aerodynamics (``LITERATURE_ROTOR_AERO``)
    added and, for context, with the rotors' thrust limits lifted; the same seeds throughout."""
    world = tuple(config.sim_overrides)
    lifted = replace(make_scenario(SCENARIO, **dict(world)).inner_loop, rotor_thrust_limits=False)
    worlds = {
        "as flown": world,
        "with the literature's rotor aero": tuple({**dict(world), **dict(LITERATURE_ROTOR_AERO)}.items()),
        "without rotor thrust limits (context)": tuple({**dict(world), "inner_loop": lifted}.items()),
    }
    pool = FlightPool(config.workers)
    try:
        log("auditing effects on the lemniscate (pd_eso, same seeds, each effect off / on)")
        audit = audit_effects(config, world=world, pool=pool)
        flights = dict(zip(worlds, pool.map_groups([_tasks(config, w, paper_seeds(config)) for w in worlds.values()])))
    finally:
        pool.close()
    log("fitting f_true_z on candidate inputs (least squares and MLP, leave one seed out)")
    predict = {f"{name}, {target} reference": disturbance_predictability(logs, config, target=target)
               for target in TARGETS for name, logs in flights.items()}
    return {"audit": audit, "predictability": predict,
            "literature_rotor_aero": {name: type(part).__name__ for name, part in LITERATURE_ROTOR_AERO}}


def format_aero(result: dict) -> str:
    """The audit and the predictability as text tables."""
    a = result["audit"]
    f = a["f_true_z_mps2"]
    lines = [
        f"Experiment 3 lemniscate, {a['method']}, seeds {a['seeds']}, t in {a['window_s']} s: "
        f"f_true_z mean {f['mean']:+.3f}, std {f['std']:.3f}, peak {f['peak']:.2f} m/s^2; z RMSE {a['z_rmse_cm']:.2f} cm",
        "",
        "Effect (switched)                                   in world  contribution to f_true_z [m/s^2]   "
        "pd_eso z RMSE [cm]",
        "                                                              mean     RMS      peak           with / without",
    ]
    for e in a["effects"]:
        d = e["delta_f_z_mps2"]
        lines.append(f"  {e['effect'][:48]:48s}  {'yes' if e['in_world'] else 'no ':8s}  {d['mean']:+.3f}   {d['rms']:.3f}    "
                     f"{d['peak']:.3f}          {e['z_rmse_cm']['with']:.2f} / {e['z_rmse_cm']['without']:.2f}")
    for name, p in result["predictability"].items():
        lines += ["", f"true z disturbance on candidate inputs, {name}: {p['samples']} samples, {p['flights']} "
                      f"flights (one held out at a time), std {p['f_z_std_mps2']:.3f} m/s^2",
                  "  inputs                                   least squares R^2 / resid RMS   MLP R^2 / resid RMS"]
        for row in p["fits"]:
            lin, mlp = row["linear"], row["mlp"]
            lines.append(f"  {row['features']:40s} {lin['r2']:6.3f} / {lin['residual_rms_mps2']:.3f}"
                         f"                {mlp['r2']:6.3f} / {mlp['residual_rms_mps2']:.3f}")
    return "\n".join(lines)
