"""What a network learns from a flight: the training pairs (features, label) and the recipes.

Pure and offline (training works on a buffer, so labels may be non-causal). One flight is a
:class:`FlightSeries` — the samples the estimator saw — whether it comes from the simulator
(:mod:`sim.experiments`) or from a recording (:mod:`recordings.dataset`); the same functions
make the pairs for both.

Labels (z axis, m/s²):

=============  ===================================================================================
``eso``        the ESO teacher, x̂₃ = f̂ of a flight under the ``eso`` pathway (paper Sec. III-A)
``tdr``        total disturbance, f_N + Δf̂ = f̂ of a flight under ``neural_eso`` (paper Sec. V-E)
``applied``    lag-consistent: a_z + g − T_applied·(R e₃)_z / m from the measured position's second
               derivative after a zero-phase low-pass (no lag) and the *applied* thrust (the commands through the identified lag and
               delay, :func:`identify_thrust_lag`). Both ESO labels see the command's thrust through
               the observer's model, so wherever the vehicle's thrust lags the command they carry
               −(T_cmd − T_applied)/m, an echo of the controller's own output, and the observer's
               own lag on top; this one carries neither.
=============  ===================================================================================

A :class:`Recipe` names everything that decides what a network is: its inputs (feature set), the
labels of the base network and of TDR, the bound and its units, and how TDR normalises.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neso.features import (DEFAULT_FEATURE_SET, PAPER_FEATURE_SET, FeatureSet, FeatureSignals, ThrustLag,
                           applied_thrust_series, feature_set)
from neso.types import GRAVITY_MPS2, VehicleModel

LABELS = ("eso", "tdr", "applied")
#: The pathway a flight must have flown for a label taken from its estimates.
LABEL_PATHWAYS = {"eso": ("eso",), "tdr": ("neural_eso",), "applied": None}
#: The zero-phase low-pass under the measured acceleration, Hz. Chosen on simulated flights against the
#: truth (docs/method.md "Labels"): 3 Hz on the position beat 2 and 5 Hz and every cutoff on the velocity.
SMOOTHING_CUTOFF_HZ = 3.0
IDENTIFICATION_CUTOFF_HZ = 5.0  # identify_thrust_lag needs the band where the lag shows
#: identify_thrust_lag's grid: τ 0–150 ms and d 0–60 ms in 2.5 ms steps (s)
LAG_TIME_CONSTANTS_S = np.arange(0.0, 0.1501, 0.0025)
LAG_DELAYS_S = np.arange(0.0, 0.0601, 0.0025)
#: What is flown when the fit sits at the top of its grid (the fit drifted, it measured no lag): the controller's own
#: nominal model, no lag and no delay — the assumption every observer and label here already makes without one.
FALLBACK_THRUST_LAG = ThrustLag()


@dataclass(frozen=True)
class FlightSeries:
    """One flight's samples as the estimator saw them (N samples at a fixed period).

    ``t_s`` (N,) s; ``pos_enu_m``, ``vel_enu_mps`` (N, 3) measured; ``roll_rad``, ``pitch_rad`` (N,)
    measured; ``thrust_prev_n`` (N,): the thrust commanded at the sample before (the control that
    acted over the period ending at this sample, N); ``f_hat_mps2`` (N, 3): the estimator's f̂
    (NaN where there was none); ``pathway`` (N,) of str or None; ``mass_kg``: the vehicle's mass the
    thrust in newtons is for (a recording's, or the controller's nominal model), kg; ``ref_pos_enu_m``,
    ``ref_vel_enu_mps`` (N, 3): the reference the controller tracked at each sample (None, or NaN rows,
    where it is not known: an imported log).
    """

    t_s: np.ndarray
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    thrust_prev_n: np.ndarray
    f_hat_mps2: np.ndarray
    pathway: np.ndarray | None = None
    mass_kg: float = VehicleModel().mass_kg
    ref_pos_enu_m: np.ndarray | None = None
    ref_vel_enu_mps: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def dt_s(self) -> float:
        d = np.diff(self.t_s)
        d = d[d > 0]
        return float(np.median(d)) if d.size else 0.02

    @property
    def tilt_cos(self) -> np.ndarray:
        """(R e₃)_z = cos φ cos θ (N,)."""
        return np.cos(self.roll_rad) * np.cos(self.pitch_rad)

    def signals(self, lag: ThrustLag, regressors: str = "state") -> FeatureSignals:
        """What the features are built from; with ``regressors="reference"`` the tracked axis' position and
        velocity are the reference's where it is known (:func:`features`)."""
        applied = applied_thrust_series(self.thrust_prev_n, lag, self.dt_s)
        pos, vel = self.pos_enu_m, self.vel_enu_mps
        if regressors == "reference" and self.ref_pos_enu_m is not None and self.ref_vel_enu_mps is not None:
            known = np.all(np.isfinite(self.ref_pos_enu_m), axis=1) & np.all(np.isfinite(self.ref_vel_enu_mps), axis=1)
            pos, vel = np.array(pos, dtype=float), np.array(vel, dtype=float)
            pos[known, 2], vel[known, 2] = self.ref_pos_enu_m[known, 2], self.ref_vel_enu_mps[known, 2]
        return FeatureSignals(pos, vel, self.roll_rad, self.pitch_rad, self.thrust_prev_n, applied)


#: What a network's tracked-state inputs are trained on. ``state``: the measured position and velocity, as it
#: flies them; but in closed loop the state answers the disturbance (a push up raises the vehicle until the
#: observer catches it), so a regression on it finds the loop: positive slopes, extra feedback gain, not
#: aerodynamics (issue 32). ``reference``: the reference's (z*, ż*), which the disturbance does not move: an
#: instrument for the state (p_z = z* − e with e the loop's answer); the network still flies on the measured
#: state, a tracking error (cm) away. Where the reference is not known (an imported log) the state is used.
REGRESSORS = ("state", "reference")


def features(series: FlightSeries, fset: FeatureSet, lag: ThrustLag = ThrustLag(), regressors: str = "state"
             ) -> np.ndarray:
    """z (N, fset.size) for every sample: the inputs the estimator builds in flight, or (``regressors``
    ``"reference"``, :data:`REGRESSORS`) the same with the tracked state taken from the reference."""
    if regressors not in REGRESSORS:
        raise ValueError(f"regressors must be one of {REGRESSORS}, got {regressors!r}")
    return fset.build(series.signals(lag, regressors))


def zero_phase(x: np.ndarray, dt_s: float, cutoff_hz: float = SMOOTHING_CUTOFF_HZ) -> np.ndarray:
    """``x`` (N,) through a 2nd-order Butterworth low-pass run forwards and backwards: no lag."""
    from scipy.signal import butter, filtfilt  # offline only

    x = np.asarray(x, dtype=float)
    if len(x) <= 9:
        return x.copy()
    b, a = butter(2, min(cutoff_hz / (0.5 / dt_s), 0.99))
    return filtfilt(b, a, x)


def smoothed_acceleration(pos_m: np.ndarray, dt_s: float, cutoff_hz: float = SMOOTHING_CUTOFF_HZ) -> np.ndarray:
    """Acceleration (N,) at every sample from measured position (N,): :func:`zero_phase`, then twice
    central differences (one-sided at the ends). From the position rather than a source's velocity,
    which carries the source's own filter lag."""
    return np.gradient(np.gradient(zero_phase(pos_m, dt_s, cutoff_hz), dt_s), dt_s)


def applied_label(series: FlightSeries, lag: ThrustLag, cutoff_hz: float = SMOOTHING_CUTOFF_HZ) -> np.ndarray:
    """The lag-consistent label (module docstring), z axis, m/s² (N,): the whole residual through the same
    zero-phase low-pass (acceleration and thrust alike, so neither leads the other), with the series' own mass."""
    dt = series.dt_s
    acc = smoothed_acceleration(series.pos_enu_m[:, 2], dt, cutoff_hz)
    lift = zero_phase(applied_thrust_series(series.thrust_prev_n, lag, dt) * series.tilt_cos, dt, cutoff_hz)
    return acc + GRAVITY_MPS2 - lift / series.mass_kg


def labels(series: FlightSeries, kind: str, lag: ThrustLag = ThrustLag()) -> np.ndarray:
    """The label ``kind`` (one of :data:`LABELS`) for every sample, z axis, m/s² (N,)."""
    if kind in ("eso", "tdr"):
        return np.asarray(series.f_hat_mps2, dtype=float)[:, 2].copy()
    if kind == "applied":
        return applied_label(series, lag)
    raise ValueError(f"label must be one of {LABELS}, got {kind!r}")


@dataclass(frozen=True)
class LagFit:
    """What :func:`identify_thrust_lag` found: ``lag`` the thrust response to fly and label with; ``fitted`` the grid's
    best; ``variance_mps4`` its residual variance ((m/s²)²); ``at_edge``: the fit sits at the top of the grid in τ or d,
    so it measured no lag (it drifted there) and ``lag`` is :data:`FALLBACK_THRUST_LAG`; ``note``: that, in words."""

    lag: ThrustLag
    fitted: ThrustLag
    variance_mps4: float
    at_edge: bool = False
    note: str = ""


def identify_thrust_lag(series: list[FlightSeries] | FlightSeries, *, time_constants_s: np.ndarray | None = None,
                        delays_s: np.ndarray | None = None) -> LagFit:
    """The first-order lag and delay from thrust command to measured acceleration, by grid search.

    For each candidate the residual ``a − T_applied·(R e₃)_z/m`` is made; what a wrong lag leaves in
    it is the difference between the true and the modelled applied thrust, a high-pass image of the
    command that adds variance. The candidate with the least residual variance (flights' means
    removed) is the fit. Defaults: :data:`LAG_TIME_CONSTANTS_S`, :data:`LAG_DELAYS_S`. The lag shows above
    its corner (3.5 Hz for 45 ms), where the position's second difference is noise: the acceleration here
    comes from the source's velocity through a 5 Hz zero-phase low-pass (thrust likewise); below ~3 Hz the
    fit drifts to the longest lag on the grid, which mimics the smoothing and the closed loop's own
    thrust–disturbance correlation (measured; issue 32: 150 ms on two gusty hovers of a vehicle whose motors
    lag 5 ms, and predictions of +878 % from it). A fit at the top of the grid in τ or d is therefore not
    used: :attr:`LagFit.lag` is then :data:`FALLBACK_THRUST_LAG` and the fit says so. Each flight's thrust is
    taken for its own ``mass_kg``.
    """
    flights = [series] if isinstance(series, FlightSeries) else list(series)
    taus = LAG_TIME_CONSTANTS_S if time_constants_s is None else np.asarray(time_constants_s)
    delays = LAG_DELAYS_S if delays_s is None else np.asarray(delays_s)
    accs = [np.gradient(zero_phase(s.vel_enu_mps[:, 2], s.dt_s, IDENTIFICATION_CUTOFF_HZ), s.dt_s) for s in flights]
    best = (ThrustLag(), np.inf)
    for tau in taus:
        for delay in delays:
            lag = ThrustLag(float(tau), float(delay))
            var = 0.0
            for s, acc in zip(flights, accs):
                lift = zero_phase(applied_thrust_series(s.thrust_prev_n, lag, s.dt_s) * s.tilt_cos, s.dt_s,
                                  IDENTIFICATION_CUTOFF_HZ)
                y = acc - lift / s.mass_kg
                var += float(np.sum((y - y.mean()) ** 2))
            var /= sum(len(s) for s in flights)
            if var < best[1]:
                best = (lag, var)
    fitted, var = best
    top_tau, top_delay = len(taus) > 1 and fitted.time_constant_s >= taus.max(), len(delays) > 1 and \
        fitted.delay_s >= delays.max()
    if not (top_tau or top_delay):
        return LagFit(fitted, fitted, var)
    edge = " and ".join(n for n, hit in ((f"τ {fitted.time_constant_s * 1e3:.1f} ms", top_tau),
                                         (f"delay {fitted.delay_s * 1e3:.1f} ms", top_delay)) if hit)
    note = (f"the thrust lag fit sits at the top of its grid ({edge}): it measured no lag; flying and labelling "
            f"with the fallback instead (lag {FALLBACK_THRUST_LAG.time_constant_s * 1e3:g} ms, delay "
            f"{FALLBACK_THRUST_LAG.delay_s * 1e3:g} ms: the controller's nominal model)")
    return LagFit(FALLBACK_THRUST_LAG, fitted, var, True, note)


# -- what a network learned, as gain ------------------------------------------------------------------
@dataclass(frozen=True)
class GainChange:
    """A network's mean slopes as a change of the z gains. The controller flies a_d = z̈* + k_p e + k_d ė − f̂
    with e = z* − z and f̂ ∋ f_N; a slope ∂f_N/∂p_z = s_p makes −f_N ∋ −s_p z = s_p e − s_p z*, the same as
    k_p + s_p on the error (and a feed-forward −s_p z* that does not act on it): ``dkp`` = +∂f_N/∂p_z (1/s²),
    ``dkd`` = +∂f_N/∂v_z (1/s). Positive slopes stiffen the loop; ground effect (thrust grows as the vehicle
    nears the ground, ∂f/∂p_z < 0) and drag (against the motion, ∂f/∂v_z < 0) soften it. Under the
    ``neural_eso`` pathway the observer removes the slow part of f_N (f̂ = H f + (1 − H) f_N, H its low-pass at
    ω_o), so the equivalence holds near and above the loop's bandwidth; the trainer's closed-loop prediction flies
    PD+ESO at the changed gains to see how much of a candidate's effect it is."""

    dkp: float
    dkd: float

    def gains(self, kp: float, kd: float) -> tuple[float, float]:
        """(k_p + Δk_p, k_d + Δk_d)."""
        return kp + self.dkp, kd + self.dkd

    def text(self, kp: float | None = None, kd: float | None = None) -> str:
        """``Δk_p +5.46 /s², Δk_d +1.58 /s`` and, with the flown gains, what they become."""
        out = f"Δk_p {self.dkp:+.3g} /s², Δk_d {self.dkd:+.3g} /s"
        if kp is not None and kd is not None:
            kp2, kd2 = self.gains(kp, kd)
            out += f" (k_p {kp:g} → {kp2:.3g}, k_d {kd:g} → {kd2:.3g})"
        return out

    def to_dict(self) -> dict:
        return {"dkp": self.dkp, "dkd": self.dkd}


POSITION_COLUMN, VELOCITY_COLUMN = "pos_z_m", "vel_z_mps"  # the tracked state's columns (neso.features.COLUMNS)


def equivalent_gains(slopes: dict) -> GainChange | None:
    """:class:`GainChange` of a network's mean physical slopes by input name (``TrainResult.slopes``, a network
    file's ``learned["slopes"]``); None without both of the tracked state's slopes."""
    try:
        return GainChange(float(slopes[POSITION_COLUMN]), float(slopes[VELOCITY_COLUMN]))
    except (KeyError, TypeError, ValueError):
        return None


# -- recipes --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Recipe:
    """How networks are made.

    ``feature_set``: the inputs. ``base_label``/``tdr_label``: :data:`LABELS` for the base network
    (ESO-teacher flights) and for Total Disturbance Retraining. ``bound_units``: ``normalised``
    (the paper's L_N on the z-scored map) or ``physical`` ((m/s²) per unit z, what the
    certificate needs). ``lipschitz_bound``: the bound in those units; ``None`` means the largest
    the stability certificate allows for the gains flown (physical units only).
    ``tdr_scalers``: ``init`` keeps the base network's z-scores, ``fit`` refits them on the new
    data (:func:`neso.training.train_lipschitz_mlp`). ``certified_fraction``: the physical bound on the state
    inputs as a fraction of the largest certified to fly well (:func:`neso.certificate.flight_budget`, with the
    other inputs at ``exogenous_fraction`` of it); ``exogenous_fraction``: the other inputs' bound as a
    multiple of the state inputs' (:func:`recipe_blocks`). Attitude and thrust inputs are in the loop
    through ``u_z`` and their rates are large (:mod:`neso.certificate.flight`): a small fraction.
    """

    name: str
    feature_set: str
    base_label: str
    tdr_label: str
    bound_units: str
    lipschitz_bound: float | None
    tdr_scalers: str
    certified_fraction: float = 0.9
    exogenous_fraction: float = 0.05
    regressors: str = "state"
    description: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.base_label not in LABELS or self.tdr_label not in LABELS:
            raise ValueError(f"labels must be in {LABELS}")
        if self.regressors not in REGRESSORS:
            raise ValueError(f"regressors must be one of {REGRESSORS}")
        if self.lipschitz_bound is None and self.bound_units != "physical":
            raise ValueError("a certified bound (lipschitz_bound None) is in physical units")


RECIPES: dict[str, Recipe] = {r.name: r for r in (
    Recipe("paper", PAPER_FEATURE_SET, "eso", "tdr", "normalised", 1.0, "init", description=
           "the paper as published: [p_z, v_z, T_k-1, roll, pitch], ESO and f_N + Δf̂ labels, L_N = 1 normalised, "
           "TDR keeps the base network's z-scores"),
    Recipe("certified", DEFAULT_FEATURE_SET, "eso", "applied", "physical", None, "fit", regressors="reference",
           description=
           "inputs free of the controller's output, lag-consistent TDR labels, trained to the largest bound the "
           "certificate allows for the gains flown, TDR z-scores refitted"),
)}
DEFAULT_RECIPE = "certified"


def recipe_of(metadata: dict) -> Recipe:
    """The recipe a network was made with (its metadata ``recipe``; older files: by their inputs)."""
    name = metadata.get("recipe")
    if name in RECIPES:
        return RECIPES[name]
    return RECIPES["paper"] if metadata.get("feature_set", PAPER_FEATURE_SET) == PAPER_FEATURE_SET else RECIPES[DEFAULT_RECIPE]


def recipe_bound(recipe: Recipe, kp: float, kd: float, omega_o: float, mass_kg: float = VehicleModel().mass_kg) -> float:
    """The bound a recipe trains to, in its units, for the z gains (1/s², 1/s) and ω_o (rad/s) flown on a vehicle
    of ``mass_kg``."""
    if recipe.lipschitz_bound is not None:
        return recipe.lipschitz_bound
    from neso.certificate import LoopPlant, flight_budget
    from neso.control import ControlConfig

    plant = LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=float(mass_kg))))
    roles = tuple(r for r, cols in feature_set(recipe.feature_set).role_columns.items() if cols and r != "state")
    return recipe.certified_fraction * flight_budget(kp, kd, omega_o, plant=plant, exogenous_roles=roles,
                                                     exogenous_fraction=recipe.exogenous_fraction)


def recipe_blocks(recipe: Recipe, fset: FeatureSet, bound: float):
    """``(blocks, bounds)`` for :func:`neso.training.train_lipschitz_mlp`: for a physical recipe, the state
    inputs under ``bound`` and every other input under ``recipe.exogenous_fraction × bound`` (each of them
    then stays within the slopes :func:`recipe_bound` certified); ``(None, None)`` otherwise (one bound on
    everything)."""
    state = fset.state_columns
    exo = tuple(i for i in range(fset.size) if i not in state)
    if recipe.bound_units != "physical" or not state or not exo:
        return None, None
    return (state, exo), (bound, recipe.exogenous_fraction * bound)
