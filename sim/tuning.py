"""PD+ESO at tuned gains: the honest baseline a learned pathway must beat (issue 32).

The paper's z gains (k_p 10, k_d 6, ω_o 15) were chosen for the paper's vehicle, not for this world, and a network's
slopes on p_z and v_z act as extra feedback gain (:func:`neso.learning.equivalent_gains`): a learned pathway that
beats PD+ESO at soft gains may only be showing that the gains were soft. So every experiment also flies PD+ESO at
gains tuned on the same kind of flights, and the learned pathway at those gains too, its budget computed for them.

**The search** (:class:`TuningConfig`): a grid over the z axis's ``k_p × k_d × ω_o`` (x and y keep the flown
gains), each kind of flight on its own (:data:`KINDS`): ``landing`` (the nominal landing; its gains fly
Experiments 1 and 2 and the noise-free landing) and ``lemniscate`` (Experiment 3). Objective: the experiment's own
score (steady-state |e_z| of the landing, z RMSE of the lemniscate's cycles, cm) averaged over the tuning seeds
``seed·1000 + 700 + i`` — never the evaluation seeds (``seed·1000 + 1 …``), the teacher's (``+500``) or TDR's
(``+900``): a baseline scored on the seeds it was tuned on would be flattered.

**The conditions** (the same a learned pathway is measured against, ``robustness`` in :mod:`sim.experiments`),
checked from the best objective down; the first grid point that meets all four is chosen:

1. every flight of the objective flown (no crash, no divergence);
2. at ``noise_factor`` × the world's motion-capture noise (position and attitude), the landing with a
   ``hold_after_s`` hold at 0.1 m flown on every tuning seed, and the thrust's spread over the hold (what a limit
   cycle raises) at most ``max_thrust_std_ratio`` × the paper gains' in the same flights. The lemniscate at that
   noise is flown and reported for the lemniscate's gains, not required: near the ground at ×3 noise it crashes
   with any z gains, the paper's included (2 of 5 evaluation seeds), through the x-y loop's tilt jitter and the
   rotors' clipping (sim/README.md), which no choice of z gains decides;
3. without motion-capture noise (docs/method.md's limit-cycle test: what oscillates there oscillates by itself),
   the hold's thrust spread at most ``max_thrust_std_ratio`` × the paper gains';
4. PD+ESO certified at these gains (:func:`neso.certificate.flight_certificate`) with an eventual |e_z| bound at
   most ``CertificatePolicy.max_bound_ratio`` (×2) the paper gains' PD+ESO's — the most a network may make it
   worse: a lower ω_o flies these flights better but rejects a faster-changing disturbance later (the bound grows
   from 15.0 cm at the paper's gains to 43.5 cm at k_p 40, k_d 12, ω_o 1) —, and the budget a network may spend
   there (:func:`neso.certificate.flight_budget`, the certified recipe's 5 % of it in the attitude) at least
   ``min_budget_fraction`` × the paper gains'.

If no grid point meets them the paper's gains are kept, and the details say so.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from neso.control import ControlConfig
from neso.eso import EsoConfig
from neso.estimator import NeuralEsoConfig
from sim.flights import FlightPool, FlightTask, landing_metrics, lemniscate_rmse_cm, steady_spectrum
from sim.runner import FlightLog
from sim.scenarios import make_scenario

TUNED = "_tuned"  # a method's suffix: flown at the tuned gains of its experiment's kind
TUNING_SEED_OFFSET = 700  # tuning seeds: seed·1000 + 700 + i (evaluation +1…, teacher +500…, TDR +900)
#: kind of flight → the scenario its gains are tuned on
KINDS: dict[str, str] = {"landing": "nominal_landing", "lemniscate": "lemniscate_near_ground"}
#: scenario → the kind of flight whose tuned gains fly it
SCENARIO_KIND: dict[str, str] = {"nominal_landing": "landing", "ood_slope": "landing",
                                 "nominal_landing_noiseless": "landing", "lemniscate_near_ground": "lemniscate"}
NOISELESS = {"nominal_landing": "nominal_landing_noiseless"}


@dataclass(frozen=True)
class ZGains:
    """The z axis's gains: ``kp`` (1/s²), ``kd`` (1/s) and the observer bandwidth ``omega_o_rps`` (rad/s)."""

    kp: float
    kd: float
    omega_o_rps: float

    @staticmethod
    def of(control: ControlConfig, omega_o_rps: float) -> "ZGains":
        return ZGains(float(control.kp[2]), float(control.kd[2]), float(omega_o_rps))

    def control(self, base: ControlConfig) -> ControlConfig:
        """``base`` with these z gains (x and y as they are)."""
        return replace(base, kp=(*base.kp[:2], self.kp), kd=(*base.kd[:2], self.kd))

    def estimator(self, dt_s: float) -> NeuralEsoConfig:
        return NeuralEsoConfig(eso=EsoConfig(omega_o_rps=self.omega_o_rps, dt_s=dt_s))

    def text(self) -> str:
        return f"k_p {self.kp:g}, k_d {self.kd:g}, ω_o {self.omega_o_rps:g}"

    def to_dict(self) -> dict:
        return {"kp": self.kp, "kd": self.kd, "omega_o": self.omega_o_rps}


@dataclass(frozen=True)
class TuningConfig:
    """The search of the module docstring. Grids on the z axis: ``kp_grid`` (1/s²), ``kd_grid`` (1/s),
    ``omega_o_grid`` (rad/s); ``trials`` tuning seeds; ``noise_factor`` × the motion-capture noise for condition 2;
    ``hold_after_s`` (s) of hold after the landing's descent for conditions 2 and 3; ``max_thrust_std_ratio``: the
    hold's thrust spread at most this × the paper gains'; ``min_budget_fraction``: the learned budget at least this
    × the paper gains'; ``batch``: candidates whose conditions are flown in one pool pass; ``kinds``: the kinds of
    flight searched (:data:`KINDS`)."""

    kp_grid: tuple[float, ...] = (10.0, 20.0, 30.0, 40.0, 60.0)
    kd_grid: tuple[float, ...] = (6.0, 10.0, 12.0, 14.0, 16.0)
    omega_o_grid: tuple[float, ...] = (1.5, 2.5, 3.5, 5.0, 7.5, 10.0, 15.0)
    trials: int = 3
    noise_factor: float = 3.0
    hold_after_s: float = 20.0
    max_thrust_std_ratio: float = 2.0
    min_budget_fraction: float = 0.5
    batch: int = 4
    kinds: tuple[str, ...] = tuple(KINDS)

    def grid(self, paper: ZGains) -> list[ZGains]:
        """Every grid point, and the paper's gains (always a candidate)."""
        points = [ZGains(float(kp), float(kd), float(w))
                  for w, kp, kd in itertools.product(self.omega_o_grid, self.kp_grid, self.kd_grid)]
        return points if paper in points else [paper, *points]


#: What :func:`tune_pd_eso` finds in the default world with the default :class:`TuningConfig` (``neso experiment
#: paper``, seed 0: tuning seeds 700–702; docs/method.md "PD+ESO at tuned gains"), flown where no search runs
#: (``neso demo tdr``). ``tests/sim/test_tuning.py`` flies the search around them; a run whose search finds other
#: gains prints so.
TUNED_GAINS: dict[str, ZGains] = {"landing": ZGains(40.0, 12.0, 2.5), "lemniscate": ZGains(40.0, 12.0, 2.5)}


@dataclass
class TuningResult:
    """``gains``: kind → the gains chosen; ``paper``: the flown gains it started from; ``details``: the search
    (every grid point's objective, the candidates checked and why each failed, the chosen gains' figures)."""

    gains: dict[str, ZGains]
    paper: ZGains
    details: dict = field(default_factory=dict)

    def for_scenario(self, scenario: str) -> ZGains:
        return self.gains[SCENARIO_KIND[scenario]]


def tuning_seeds(config, tuning: TuningConfig) -> list[int]:
    """The seeds the gains are tuned on (``config``: a :class:`sim.experiments.PaperConfig`)."""
    return [config.seed * 1000 + TUNING_SEED_OFFSET + i for i in range(tuning.trials)]


def noisy(config, scenario: str, factor: float) -> tuple[tuple[str, object], ...]:
    """``config.sim_overrides`` with the scenario's motion-capture noise (position and attitude) × ``factor``."""
    mocap = dict(config.sim_overrides).get("mocap", make_scenario(scenario).mocap)
    scaled = replace(mocap, pos_noise_std_m=factor * mocap.pos_noise_std_m,
                     att_noise_std_rad=factor * mocap.att_noise_std_rad)
    return (*((k, v) for k, v in config.sim_overrides if k != "mocap"), ("mocap", scaled))


def task(config, scenario: str, method: str, networks: dict, gains: ZGains, seed: int, trajectory=None,
         sim_overrides=None) -> FlightTask:
    """One flight of ``method`` at ``gains`` (z; x and y as ``config.control``)."""
    trajectory = trajectory if trajectory is not None else (
        config.lemniscate if scenario == "lemniscate_near_ground" else config.landing)
    return FlightTask(scenario, method, networks, seed, trajectory, gains.estimator(config.control.dt_s),
                      gains.control(config.control), config.sim_overrides if sim_overrides is None else sim_overrides)


def score(log: FlightLog, config, scenario: str) -> float | None:
    """The experiment's own score of a flight (cm): steady-state |e_z| of a landing, z RMSE of the lemniscate's
    cycles; None if it crashed or diverged."""
    if scenario == "lemniscate_near_ground":
        return lemniscate_rmse_cm(log, config)
    return landing_metrics(log, config)[0]


# -- the conditions ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Robustness:
    """What conditions 2 and 3 measure for one method at one set of gains over some seeds: ``hold_flown`` /
    ``hold_total`` holds at ``noise_factor`` × the noise that neither crashed nor diverged; over those holds
    ``thrust_std_n`` (N, mean over seeds), ``z_rms_cm`` and ``peak_hz`` (the z error's largest spectral peak);
    the lemniscate at that noise (reported, not a condition): ``lemniscate_flown`` / ``lemniscate_total`` and the
    z RMSE of those flown, ``lemniscate_rmse_cm`` (None if none); without noise ``quiet_thrust_std_n`` (inf if a
    quiet hold crashed) and ``quiet_peak_hz``."""

    hold_flown: int
    hold_total: int
    thrust_std_n: float
    z_rms_cm: float
    peak_hz: float
    lemniscate_flown: int
    lemniscate_total: int
    lemniscate_rmse_cm: float | None
    quiet_thrust_std_n: float
    quiet_peak_hz: float

    def to_dict(self) -> dict:
        def clean(v):
            return v if v is None or math.isfinite(v) else None
        return {k: clean(v) if isinstance(v, float) else v for k, v in self.__dict__.items()}


def robustness_tasks(config, tuning: TuningConfig, method: str, networks: dict, gains: ZGains, seeds: list[int], *,
                     lemniscate: bool) -> list[FlightTask]:
    """The flights of conditions 2 and 3 for ``method`` at ``gains``: per seed the hold at ``noise_factor`` × the
    noise, the hold without noise, and (``lemniscate``) the lemniscate at that noise."""
    hold = replace(config.landing, hold_after_s=tuning.hold_after_s)
    out = []
    for s in seeds:
        out.append(task(config, "nominal_landing", method, networks, gains, s, hold,
                        noisy(config, "nominal_landing", tuning.noise_factor)))
        out.append(task(config, "nominal_landing_noiseless", method, networks, gains, s, hold))
        if lemniscate:
            out.append(task(config, "lemniscate_near_ground", method, networks, gains, s, None,
                            noisy(config, "lemniscate_near_ground", tuning.noise_factor)))
    return out


def robustness(logs: list[FlightLog], config, tuning: TuningConfig, *, lemniscate: bool) -> Robustness:
    """:class:`Robustness` of the flights :func:`robustness_tasks` made (same order)."""
    per = 3 if lemniscate else 2
    hold_config = replace(config, landing=replace(config.landing, hold_after_s=tuning.hold_after_s))
    noisy_holds, quiet_holds = logs[0::per], logs[1::per]
    lems = logs[2::per] if lemniscate else []
    flown = [log for log in noisy_holds if not log.diverged]
    spectra = [steady_spectrum(log, hold_config) for log in flown]
    rms = [_late_rms_cm(log, hold_config) for log in flown]
    quiet = [steady_spectrum(log, hold_config) for log in quiet_holds if not log.diverged]
    lem_scores = [s for s in (lemniscate_rmse_cm(log, config) for log in lems) if s is not None]
    mean = (lambda xs: float(np.mean(xs)) if xs else math.nan)  # noqa: E731
    return Robustness(
        hold_flown=len(flown), hold_total=len(noisy_holds),
        thrust_std_n=mean([s[0] for s in spectra]), z_rms_cm=mean(rms), peak_hz=mean([s[1] for s in spectra]),
        lemniscate_flown=len(lem_scores), lemniscate_total=len(lems),
        lemniscate_rmse_cm=mean(lem_scores) if lem_scores else None,
        quiet_thrust_std_n=(mean([q[0] for q in quiet]) if len(quiet) == len(quiet_holds) else math.inf),
        quiet_peak_hz=mean([q[1] for q in quiet]))


def _late_rms_cm(log: FlightLog, config) -> float:
    late = np.isfinite(log.t_s) & (log.t_s >= config.landing.descent_end_s + config.settle_after_descent_s)
    return float(np.sqrt(np.mean(log.z_error_m[late] ** 2))) * 100


def failed_conditions(r: Robustness, paper: Robustness, tuning: TuningConfig) -> list[str]:
    """Conditions 2 and 3 against the paper gains' figures ``paper``: one line per condition not met."""
    why = []
    if r.hold_flown < r.hold_total:
        why.append(f"at ×{tuning.noise_factor:g} noise {r.hold_total - r.hold_flown} of {r.hold_total} holds "
                   "crashed or diverged")
    elif r.thrust_std_n > tuning.max_thrust_std_ratio * paper.thrust_std_n:
        why.append(f"at ×{tuning.noise_factor:g} noise the hold's thrust std {r.thrust_std_n:.2f} N is over "
                   f"×{tuning.max_thrust_std_ratio:g} the paper gains' {paper.thrust_std_n:.2f} N")
    if r.quiet_thrust_std_n == math.inf:
        why.append("without noise a hold crashed or diverged")
    elif not r.quiet_thrust_std_n <= tuning.max_thrust_std_ratio * paper.quiet_thrust_std_n:
        why.append(f"without noise the hold's thrust std {r.quiet_thrust_std_n:.3f} N is over "
                   f"×{tuning.max_thrust_std_ratio:g} the paper gains' {paper.quiet_thrust_std_n:.3f} N (a limit cycle)")
    return why


def certificate_figures(gains: ZGains, control: ControlConfig, *, budget: bool = True) -> dict:
    """PD+ESO's verdict and eventual |e_z| bound (cm) at ``gains`` and (``budget``) the state budget a network may
    spend there (the certified recipe's: 5 % of it in the attitude), (m/s²) per unit z."""
    from neso.certificate import LoopPlant, NetworkSlopes, flight_budget, flight_certificate

    plant = LoopPlant.of(control)
    cert = flight_certificate(NetworkSlopes(0.0), kp=gains.kp, kd=gains.kd, omega_o=gains.omega_o_rps, plant=plant)
    out = {"pdeso_certified": cert.holds, "pdeso_bound_cm": cert.pdeso_bound_cm if cert.holds else None}
    if budget:
        out["budget"] = flight_budget(gains.kp, gains.kd, gains.omega_o_rps, plant=plant, exogenous_fraction=0.05) \
            if cert.holds else 0.0
    return out


def failed_certificate(cert: dict, paper: dict, tuning: TuningConfig) -> list[str]:
    """Condition 4 for :func:`certificate_figures` ``cert`` against the paper gains' ``paper``; one line per failure
    (the budget is checked only when ``cert`` has one)."""
    from neso.certificate import POLICY

    if not cert["pdeso_certified"]:
        return ["PD+ESO is not certified at these gains"]
    ratio = POLICY.max_bound_ratio
    if cert["pdeso_bound_cm"] > ratio * paper["pdeso_bound_cm"]:
        return [f"PD+ESO's eventual |e_z| bound {cert['pdeso_bound_cm']:.3g} cm is over ×{ratio:g} the paper gains' "
                f"{paper['pdeso_bound_cm']:.3g} cm"]
    if "budget" in cert and cert["budget"] < tuning.min_budget_fraction * paper["budget"]:
        return [f"the learned budget {cert['budget']:.3g} is under ×{tuning.min_budget_fraction:g} the paper gains' "
                f"{paper['budget']:.3g} (m/s²)/unit z"]
    return []


# -- the search -------------------------------------------------------------------------------------
def tune_pd_eso(config, pool: FlightPool, log=print, tuning: TuningConfig | None = None) -> TuningResult:
    """The search of the module docstring for each kind of flight (``config``: a
    :class:`sim.experiments.PaperConfig`, whose ``tuning``, ``control`` and ``omega_o_rps`` it starts from)."""
    tuning = tuning or config.tuning
    paper = ZGains.of(config.control, config.omega_o_rps)
    seeds = tuning_seeds(config, tuning)
    grid = tuning.grid(paper)
    kinds = {k: KINDS[k] for k in tuning.kinds}
    log(f"tuning PD+ESO's z gains: {len(grid)} grid points × {len(kinds)} kinds × {len(seeds)} seeds {seeds}")
    tasks = [task(config, scenario, "pd_eso", {}, g, s) for scenario in kinds.values() for g in grid for s in seeds]
    logs = pool.map(tasks)
    objective: dict[str, dict[ZGains, float | None]] = {}
    i = 0
    for kind, scenario in kinds.items():
        objective[kind] = {}
        for g in grid:
            scores = [score(lg, config, scenario) for lg in logs[i:i + len(seeds)]]
            i += len(seeds)
            objective[kind][g] = None if None in scores else float(np.mean(scores))
    paper_rob = robustness(pool.map(robustness_tasks(config, tuning, "pd_eso", {}, paper, seeds, lemniscate=True)),
                           config, tuning, lemniscate=True)
    paper_cert = certificate_figures(paper, config.control)
    details: dict = {"seeds": seeds, "config": _config_dict(tuning), "paper_gains": paper.to_dict(),
                     "paper_robustness": paper_rob.to_dict(), "paper_certificate": paper_cert,
                     "grid": [dict(g.to_dict(), **{k: objective[k][g] for k in kinds}) for g in grid], "kinds": {}}
    chosen = {}
    for kind in kinds:
        chosen[kind], details["kinds"][kind] = _choose(kind, objective[kind], paper, paper_rob, paper_cert, config,
                                                       pool, tuning, seeds, log)
    return TuningResult(chosen, paper, details)


def _choose(kind, objective, paper, paper_rob, paper_cert, config, pool, tuning, seeds, log) -> tuple[ZGains, dict]:
    """The best grid point of ``kind`` meeting the conditions (the paper's gains if none does), and the record."""
    ranked = sorted((g for g, v in objective.items() if v is not None), key=lambda g: objective[g])
    rejected = []
    for start in range(0, len(ranked), tuning.batch):
        batch = ranked[start:start + tuning.batch]
        flat = pool.map([t for g in batch for t in robustness_tasks(config, tuning, "pd_eso", {}, g, seeds,
                                                                      lemniscate=False)])
        for j, g in enumerate(batch):
            rob = robustness(flat[j * 2 * len(seeds):(j + 1) * 2 * len(seeds)], config, tuning, lemniscate=False)
            why = failed_conditions(rob, paper_rob, tuning)
            cert = {} if why else certificate_figures(g, config.control, budget=False)
            why = why or failed_certificate(cert, paper_cert, tuning)
            if not why:  # the budget's bisection last: it costs seconds
                cert = certificate_figures(g, config.control)
                why = failed_certificate(cert, paper_cert, tuning)
            if why:
                rejected.append({**g.to_dict(), "objective_cm": objective[g], "why": why})
                continue
            if kind == "lemniscate":  # the lemniscate at the noise: reported for the gains chosen, not a condition
                rob = robustness(pool.map(robustness_tasks(config, tuning, "pd_eso", {}, g, seeds, lemniscate=True)),
                                 config, tuning, lemniscate=True)
            log(f"  {kind}: {g.text()} — {objective[g]:.3f} cm on the tuning seeds (paper gains "
                f"{_fmt(objective.get(paper))}), {len(rejected)} better point(s) failed a condition")
            return g, {"gains": g.to_dict(), "objective_cm": objective[g], "paper_objective_cm": objective.get(paper),
                       "robustness": rob.to_dict(), "certificate": cert, "rejected": rejected}
    log(f"  {kind}: no grid point meets the conditions; the paper's gains are kept")
    return paper, {"gains": paper.to_dict(), "objective_cm": objective.get(paper),
                   "paper_objective_cm": objective.get(paper), "robustness": paper_rob.to_dict(),
                   "certificate": paper_cert, "rejected": rejected, "none_met": True}


def _fmt(v: float | None) -> str:
    return "crashed" if v is None else f"{v:.3f} cm"


def _config_dict(tuning: TuningConfig) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in tuning.__dict__.items()}
