"""The network's input vector z: named, versioned feature sets, and the applied-thrust model.

A *feature set* says which signals make up z, in which order and units. Every network file
declares the one it was trained on (metadata ``feature_set`` = ``"<name>@<version>"``); the
estimator builds exactly those features for it and refuses a file whose set it cannot build.

=================  ==========================================================================
``paper@1``        [p_z, v_z, T_{k−1}, φ, θ]: the paper's input (Sec. V-C). T_{k−1} is the
                   controller's own previous output: in near-steady flight the teacher label
                   is almost exactly g − T/m, so a network with this input can learn the
                   feedback identity instead of the aerodynamics (kept to reproduce the paper).
``state@1``        [p_z, v_z, φ, θ]: measured state only; cannot learn the identity.
``state_speed@1``  [p_z, v_z, φ, θ, v_xy]: state plus horizontal speed (drag, translational
                   lift and near-ground turbulence grow with it).
``applied@1``      [p_z, v_z, T_applied, φ, θ]: the thrust acting on the vehicle, estimated
                   from the commands through the identified first-order lag and delay
                   (:class:`ThrustLag`), as Neural-Lander/Neural-Fly feed rotor speed or the
                   flight controller's output rather than the outer-loop command.
=================  ==========================================================================

Each column's *role* matters to the stability certificate (:mod:`neso.certificate.roles`): the
tracked ``state`` (position and velocity of the network's axis), whose rates are the tracking and
observer errors'; the ``thrust``, which the controller makes from the network's own output (the
loop through ``u_z``); the ``attitude``, moved by the horizontal force and, through the tilt of
the force, by that loop too; the horizontal ``speed``, whose rate the tilt limit bounds.
``FeatureSet.state_columns`` and ``FeatureSet.role_columns`` say which.

Signals (:class:`FeatureSignals`) are scalars for one sample or arrays of N samples; the same
code builds both, so the features the estimator flies and the ones a dataset trains on are
built by one function.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from neso.types import StateMeasurement


@dataclass(frozen=True, slots=True)
class FeatureSignals:
    """Everything a feature may use at a sample (scalars) or at N samples (arrays).

    ``pos_enu_m``, ``vel_enu_mps``: (3,) or (N, 3), ENU, measured. ``roll_rad``, ``pitch_rad``:
    measured attitude. ``thrust_prev_n``: thrust commanded at the previous sample (N, the
    controller's model). ``thrust_applied_n``: the estimate of the thrust acting now (N).
    """

    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    roll_rad: float | np.ndarray
    pitch_rad: float | np.ndarray
    thrust_prev_n: float | np.ndarray
    thrust_applied_n: float | np.ndarray

    @staticmethod
    def of(meas: StateMeasurement, thrust_prev_n: float, thrust_applied_n: float) -> "FeatureSignals":
        return FeatureSignals(meas.pos_enu_m, meas.vel_enu_mps, meas.roll_rad, meas.pitch_rad,
                              thrust_prev_n, thrust_applied_n)


ROLES = ("state", "thrust", "attitude", "speed")


@dataclass(frozen=True, slots=True)
class Column:
    """One input: its unit, its role (:data:`ROLES`, see module docstring), and how to build it."""

    unit: str
    role: str
    build: Callable[[FeatureSignals], float | np.ndarray]

    @property
    def tracked_state(self) -> bool:
        return self.role == "state"


def _speed_xy(s: FeatureSignals):
    v = np.asarray(s.vel_enu_mps)
    return np.hypot(v[..., 0], v[..., 1])


COLUMNS: dict[str, Column] = {
    "pos_z_m": Column("m", "state", lambda s: np.asarray(s.pos_enu_m)[..., 2]),
    "vel_z_mps": Column("m/s", "state", lambda s: np.asarray(s.vel_enu_mps)[..., 2]),
    "thrust_prev_n": Column("N", "thrust", lambda s: s.thrust_prev_n),
    "thrust_applied_n": Column("N", "thrust", lambda s: s.thrust_applied_n),
    "roll_rad": Column("rad", "attitude", lambda s: s.roll_rad),
    "pitch_rad": Column("rad", "attitude", lambda s: s.pitch_rad),
    "speed_xy_mps": Column("m/s", "speed", _speed_xy),
}


class FeatureSetError(ValueError):
    """A feature set that does not exist (or not in this version); the message lists the known ones."""


@dataclass(frozen=True, slots=True)
class FeatureSet:
    """A named, versioned input vector. ``columns``: names from :data:`COLUMNS`, in order."""

    name: str
    version: int
    columns: tuple[str, ...]
    description: str

    @property
    def key(self) -> str:
        """``"<name>@<version>"``, what network files record."""
        return f"{self.name}@{self.version}"

    @property
    def size(self) -> int:
        return len(self.columns)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(COLUMNS[c].unit for c in self.columns)

    @property
    def state_columns(self) -> tuple[int, ...]:
        """Indices of the tracked-state columns (position and velocity of the network's axis)."""
        return tuple(i for i, c in enumerate(self.columns) if COLUMNS[c].tracked_state)

    @property
    def role_columns(self) -> dict[str, tuple[int, ...]]:
        """Indices of the columns of each role (:data:`ROLES`; a role with none maps to ``()``)."""
        return {role: tuple(i for i, c in enumerate(self.columns) if COLUMNS[c].role == role) for role in ROLES}

    @property
    def uses_applied_thrust(self) -> bool:
        return "thrust_applied_n" in self.columns

    def build(self, signals: FeatureSignals) -> np.ndarray:
        """z of shape (size,) for one sample, (N, size) for N."""
        return np.stack([np.asarray(COLUMNS[c].build(signals), dtype=float) for c in self.columns], axis=-1)


FEATURE_SETS: dict[str, FeatureSet] = {fs.key: fs for fs in (
    FeatureSet("paper", 1, ("pos_z_m", "vel_z_mps", "thrust_prev_n", "roll_rad", "pitch_rad"),
               "the paper's [p_z, v_z, T_{k-1}, roll, pitch]; the previous command lets it learn the feedback identity"),
    FeatureSet("state", 1, ("pos_z_m", "vel_z_mps", "roll_rad", "pitch_rad"),
               "measured state only [p_z, v_z, roll, pitch]"),
    FeatureSet("state_speed", 1, ("pos_z_m", "vel_z_mps", "roll_rad", "pitch_rad", "speed_xy_mps"),
               "measured state and horizontal speed [p_z, v_z, roll, pitch, v_xy]"),
    FeatureSet("applied", 1, ("pos_z_m", "vel_z_mps", "thrust_applied_n", "roll_rad", "pitch_rad"),
               "state and the applied thrust through the identified lag [p_z, v_z, T_applied, roll, pitch]"),
)}
PAPER_FEATURE_SET = "paper@1"
#: The default for new networks, chosen by measurement (docs/method.md "What the simulation shows"): without any
#: thrust input it cannot learn the feedback identity at any bound; with the applied thrust and the LMI's
#: certified bound (1.49 > 1/m) a network did, and the noise-free landing limit-cycled.
DEFAULT_FEATURE_SET = "state@1"
#: Files written before feature sets were recorded carry none: they were trained on the paper's input.
LEGACY_FEATURE_SET = PAPER_FEATURE_SET


def feature_set(key: str) -> FeatureSet:
    """The feature set ``key`` (``"name@version"``, or a bare name for its newest version)."""
    if key in FEATURE_SETS:
        return FEATURE_SETS[key]
    versions = [fs for fs in FEATURE_SETS.values() if fs.name == key]
    if versions:
        return max(versions, key=lambda fs: fs.version)
    raise FeatureSetError(f"unknown feature set {key!r}; this version builds {', '.join(sorted(FEATURE_SETS))}")


# -- the applied-thrust model ----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ThrustLag:
    """The vehicle's thrust response to a command: transport delay, then a first-order lag.

    ``time_constant_s`` τ ≥ 0, ``delay_s`` d ≥ 0. Identified from flight data by
    :func:`neso.labels.identify_thrust_lag`; recorded with every network that uses it.
    """

    time_constant_s: float = 0.0
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("time_constant_s", "delay_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1] s, got {v!r}")

    def coefficients(self, dt_s: float) -> tuple[int, float, float, float]:
        """``(m, a, b_old, b_new)``: with u_j the command issued at sample j (held for one period,
        acting from t_j + d), the thrust at sample k is ``y_k = a·y_{k−1} + b_old·u_{k−2−m} +
        b_new·u_{k−1−m}``, exact for a zero-order-held input (d = mΔ + r, 0 ≤ r < Δ)."""
        m = int(math.floor(self.delay_s / dt_s + 1e-9))
        r = self.delay_s - m * dt_s
        if self.time_constant_s <= 0.0:
            return m, 0.0, 0.0, 1.0
        a = math.exp(-dt_s / self.time_constant_s)
        tail = math.exp(-(dt_s - r) / self.time_constant_s)  # decay over the part after the switch
        return m, a, tail * (1.0 - math.exp(-r / self.time_constant_s)), 1.0 - tail


class AppliedThrust:
    """The thrust acting at each sample, estimated online from the commands (:class:`ThrustLag`)."""

    def __init__(self, lag: ThrustLag, dt_s: float) -> None:
        self.lag = lag
        self._m, self._a, self._b_old, self._b_new = lag.coefficients(dt_s)
        self._commands: deque[float] = deque(maxlen=self._m + 2)
        self.thrust_n = 0.0

    def reset(self, thrust_n: float) -> None:
        """Steady state at ``thrust_n`` (N)."""
        self._commands.clear()
        self._commands.extend([float(thrust_n)] * (self._m + 2))
        self.thrust_n = float(thrust_n)

    def update(self, thrust_prev_n: float) -> float:
        """Advance one sample given the command issued at the previous sample; returns the
        thrust acting now (N)."""
        self._commands.append(float(thrust_prev_n))
        u_old, u_new = self._commands[0], self._commands[1]
        self.thrust_n = self._a * self.thrust_n + self._b_old * u_old + self._b_new * u_new
        return self.thrust_n


def applied_thrust_series(thrust_prev_n: np.ndarray, lag: ThrustLag, dt_s: float) -> np.ndarray:
    """:class:`AppliedThrust` over a whole series: ``thrust_prev_n[k]`` is the command issued at
    sample k−1 (N); the result's sample k is the thrust acting at sample k. Starts in steady state
    at the first command. The same recursion, run as one linear filter."""
    from scipy.signal import lfilter, lfilter_zi  # offline only: keep it out of the loop's start-up

    x = np.asarray(thrust_prev_n, dtype=float)
    if x.size == 0:
        return x.copy()
    m, a, b_old, b_new = lag.coefficients(dt_s)
    num = np.zeros(m + 2)
    num[m], num[m + 1] = b_new, b_old
    den = np.array([1.0, -a])
    return lfilter(num, den, x, zi=lfilter_zi(num, den) * x[0])[0]


class FeatureBuilder:
    """z for one feature set, sample by sample, with the applied-thrust state it needs."""

    def __init__(self, fset: FeatureSet, lag: ThrustLag, dt_s: float) -> None:
        self.feature_set = fset
        self.applied = AppliedThrust(lag, dt_s)

    def reset(self, meas: StateMeasurement, thrust_n: float) -> np.ndarray:
        self.applied.reset(thrust_n)
        return self.feature_set.build(FeatureSignals.of(meas, thrust_n, thrust_n))

    def build(self, meas: StateMeasurement, thrust_prev_n: float) -> np.ndarray:
        applied = self.applied.update(thrust_prev_n)
        return self.feature_set.build(FeatureSignals.of(meas, thrust_prev_n, applied))


def acceleration_labels(vel_mps: np.ndarray, acc_cmd_mps2: np.ndarray, dt_s: float, *, cutoff_hz: float | None = 5.0) -> np.ndarray:
    """Neural-Lander-style labels: measured minus commanded z acceleration.

    ``vel_mps`` (N,) measured z velocity, ``acc_cmd_mps2`` (N,) the nominal acceleration the
    command applied over [k, k+1). The measured acceleration is the forward difference
    (v_{k+1} − v_k)/Δ, so the result has N − 1 rows (the last sample has no successor).

    Labels are made offline, so the velocity is first low-passed with a zero-phase
    2nd-order Butterworth at ``cutoff_hz`` (no lag); ``None`` keeps the raw difference. Raw
    differences of motion-capture velocity are noise-dominated (σ ≈ 5 m/s² here) and a
    network trained on them made PD+NN diverge — the noise the paper avoids by not using
    acceleration at all.
    """
    vel = np.asarray(vel_mps, dtype=float)
    if cutoff_hz is not None:
        from scipy.signal import butter, filtfilt  # offline only: keep it out of the loop's start-up

        b, a = butter(2, cutoff_hz / (0.5 / dt_s))
        vel = filtfilt(b, a, vel)
    acc_meas = np.diff(vel) / dt_s
    return acc_meas - np.asarray(acc_cmd_mps2)[:-1]
