"""Disturbance estimators: the Neural-ESO (four pathways) and the single-pathway neural observer.

Every estimator follows one template (:class:`DisturbanceEstimator`): ``reset`` with the
first measurement, then ``update`` once per sample with the measurement and the control
that acted over the previous period, returning a :class:`DisturbanceEstimate`.

Axes: the learned prior acts on ``network_axes`` (default z only, as in the paper). The
other axes always run the plain ESO: the paper flies the same planar controller for
every method and compares altitude only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from neso.eso import EsoConfig, ExtendedStateObserver, transition_matrix
from neso.features import FeatureBuilder
from neso.network import LipschitzMLP
from neso.types import PATHWAYS, StateMeasurement

_USES_ESO = {"neural_eso": True, "eso": True, "nn": False, "none": False}
_USES_PRIOR = {"neural_eso": True, "eso": False, "nn": True, "none": False}


@dataclass(frozen=True, slots=True)
class AppliedControl:
    """What acted over the previous control period.

    ``acc_cmd_enu_mps2`` (3,): the acceleration the command produces under the nominal
    model, g + R·[0, 0, T]/m (the ESO's known input). ``thrust_n``: the commanded thrust.
    """

    acc_cmd_enu_mps2: np.ndarray
    thrust_n: float


@dataclass(frozen=True, slots=True)
class DisturbanceEstimate:
    """f̂ = f_N + Δf̂, each (3,) in m/s² (ENU). ``f_n`` is the prior actually used, ``z`` the network input
    (the network's feature set; shape (0,) without a network)."""

    f_hat: np.ndarray
    f_n: np.ndarray
    delta_f_hat: np.ndarray
    pathway: str
    z: np.ndarray


class DisturbanceEstimator(Protocol):
    def reset(self, meas: StateMeasurement, thrust_n: float) -> None: ...

    def update(self, meas: StateMeasurement, applied: AppliedControl) -> DisturbanceEstimate: ...


@dataclass(frozen=True, slots=True)
class NeuralEsoConfig:
    """``transfer_time_s``: time constant with which an offset left by a switch to a pathway
    without an observer (``nn``, ``none``) fades out, so f̂ does not jump."""

    eso: EsoConfig = field(default_factory=EsoConfig)
    pathway: str = "neural_eso"
    network_axes: tuple[int, ...] = (2,)
    transfer_time_s: float = 0.5

    def __post_init__(self) -> None:
        if self.pathway not in PATHWAYS:
            raise ValueError(f"pathway must be one of {PATHWAYS}, got {self.pathway!r}")
        if not self.transfer_time_s > 0:
            raise ValueError("transfer_time_s must be positive")


class NeuralESO:
    """The dual-pathway estimator (paper eq. 8) with live pathway switching and network swap.

    Pathways on the network axes: ``neural_eso`` f̂ = f_N + Δf̂ (observer on the residual);
    ``eso`` f̂ = x̂3 (observer alone); ``nn`` f̂ = f_N; ``none`` f̂ = 0. Changes requested with
    :meth:`set_pathway` / :meth:`set_network` take effect at the next ``update`` and are
    bumpless: an observer pathway re-seeds its extended state so f̂ is continuous, a
    pathway without one carries the difference as an offset that fades with
    ``transfer_time_s``. The observer keeps running underneath every pathway so its
    position and velocity estimates are ready when it is switched back in.
    """

    def __init__(self, config: NeuralEsoConfig = NeuralEsoConfig(), network: LipschitzMLP | None = None) -> None:
        self.config = config
        self.eso = ExtendedStateObserver(config.eso)
        self.pathway = config.pathway
        self.network = network
        self._axes = np.array(config.network_axes, dtype=int)
        self._decay = math.exp(-config.eso.dt_s / config.transfer_time_s)
        self._pending_pathway: str | None = None
        self._pending_network: tuple[LipschitzMLP | None] | None = None
        self._offset = np.zeros(3)
        self._prior_in_observer = np.zeros(3)
        self._check_network(network)
        self._features = _builder(network, config.eso.dt_s)

    # -- live changes -------------------------------------------------------------
    def set_pathway(self, pathway: str) -> None:
        if pathway not in PATHWAYS:
            raise ValueError(f"pathway must be one of {PATHWAYS}, got {pathway!r}")
        self._pending_pathway = pathway

    def set_network(self, network: LipschitzMLP | None) -> None:
        self._check_network(network)
        self._pending_network = (network,)

    def _check_network(self, network: LipschitzMLP | None) -> None:
        if network is not None and network.n_outputs != len(self._axes):
            raise ValueError(
                f"network has {network.n_outputs} outputs but the estimator maps {len(self._axes)} axes"
            )

    # -- the step -----------------------------------------------------------------
    def reset(self, meas: StateMeasurement, thrust_n: float) -> None:
        self.eso.reset(meas.pos_enu_m, meas.vel_enu_mps)
        self._offset = np.zeros(3)
        z = self._features.reset(meas, thrust_n) if self._features is not None else _NO_Z
        self._prior_in_observer = self._observer_prior(self._prior(z))

    def _prior(self, z: np.ndarray) -> np.ndarray:
        f_n = np.zeros(3)
        if self.network is not None:
            f_n[self._axes] = self.network.predict(z)
        return f_n

    def _observer_prior(self, f_n_all: np.ndarray) -> np.ndarray:
        """The prior the observer runs around: f_N on the network axes under ``neural_eso``
        and ``nn`` (the latter in the background), nothing otherwise."""
        prior = np.zeros(3)
        if self.pathway in ("neural_eso", "nn"):
            prior[self._axes] = f_n_all[self._axes]
        return prior

    def _compose(self, f_n_all: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f_N used, Δf̂) under the current pathway; planar axes always use the ESO."""
        f_n = np.zeros(3)
        delta = self.eso.state[2].copy()
        axes = self._axes
        if _USES_PRIOR[self.pathway]:
            f_n[axes] = f_n_all[axes]
        if not _USES_ESO[self.pathway]:
            delta[axes] = self._offset[axes]
        return f_n, delta

    def update(self, meas: StateMeasurement, applied: AppliedControl) -> DisturbanceEstimate:
        self.eso.update(meas.pos_enu_m, applied.acc_cmd_enu_mps2 + self._prior_in_observer)
        self._offset *= self._decay
        z = self._features.build(meas, applied.thrust_n) if self._features is not None else _NO_Z
        f_n_all = self._prior(z)
        f_n, delta = self._compose(f_n_all)
        if self._pending_pathway is not None or self._pending_network is not None:
            f_n, delta, f_n_all, z = self._apply_pending(meas, applied, z, f_n + delta)
        self._prior_in_observer = self._observer_prior(f_n_all)
        return DisturbanceEstimate(f_hat=f_n + delta, f_n=f_n, delta_f_hat=delta, pathway=self.pathway, z=z)

    def _apply_pending(self, meas: StateMeasurement, applied: AppliedControl, z: np.ndarray,
                       f_hat_before: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Switch pathway and/or network so that f̂ at this sample equals ``f_hat_before``."""
        if self._pending_network is not None:
            (self.network,) = self._pending_network
            self._features = _builder(self.network, self.config.eso.dt_s)
            if self._features is not None:  # its own inputs, the applied-thrust model started where it stands
                self._features.reset(meas, applied.thrust_n)
                z = self._features.build(meas, applied.thrust_n)
            else:
                z = _NO_Z
        if self._pending_pathway is not None:
            self.pathway = self._pending_pathway
        self._pending_network = None
        self._pending_pathway = None
        f_n_all = self._prior(z)
        axes = self._axes
        self.eso.state[2, axes] = f_hat_before[axes] - self._observer_prior(f_n_all)[axes]
        used_prior = f_n_all[axes] if _USES_PRIOR[self.pathway] else 0.0
        self._offset[axes] = 0.0 if _USES_ESO[self.pathway] else f_hat_before[axes] - used_prior
        f_n, delta = self._compose(f_n_all)
        return f_n, delta, f_n_all, z


_NO_Z = np.zeros(0)


def _builder(network: LipschitzMLP | None, dt_s: float) -> FeatureBuilder | None:
    """The features ``network`` was trained on (its file's feature set and thrust lag)."""
    if network is None:
        return None
    return FeatureBuilder(network.feature_set, network.thrust_lag, dt_s)


class NeuralObserver:
    """Single-pathway neural observer (Liu et al. 2023): a network replaces the ESO's extended state.

    On the network axes a second-order observer x̂̇1 = x̂2 + l1·ỹ, x̂̇2 = b + h(ẑ) + l2·ỹ runs
    with the network evaluated on the *observer's* states (its feature set with x̂1, x̂2 for p_z, v_z) and
    f̂ = h(ẑ): no extended state, so no online correction of the network's error. Discrete
    like the ESO: ZOH prediction and a current-observer correction with the double pole at
    e^{−ω_o Δ}. The planar axes run the plain ESO as for every other method.
    """

    def __init__(self, config: NeuralEsoConfig, network: LipschitzMLP) -> None:
        self.config = config
        self.network = network
        self.planar = NeuralESO(NeuralEsoConfig(eso=config.eso, pathway="eso", network_axes=config.network_axes), None)
        dt = config.eso.dt_s
        beta = math.exp(-config.eso.omega_o_rps * dt)
        self._gains = np.array([1.0 - beta * beta, (1.0 - beta) ** 2 / dt])
        self._phi = transition_matrix(dt)[:2, :2]
        self._gamma = np.array([0.5 * dt * dt, dt])
        self._axes = list(config.network_axes)
        self._x = np.zeros((2, len(self._axes)))
        self._f_n = np.zeros(len(self._axes))
        self._features = _builder(network, dt)
        columns = network.feature_set.columns
        self._observed = [(columns.index(c), row) for row, c in enumerate(("pos_z_m", "vel_z_mps")) if c in columns]

    def reset(self, meas: StateMeasurement, thrust_n: float) -> None:
        self.planar.reset(meas, thrust_n)
        self._features.reset(meas, thrust_n)
        self._x = np.vstack((meas.pos_enu_m[self._axes], meas.vel_enu_mps[self._axes]))
        self._f_n = np.zeros(len(self._axes))

    def update(self, meas: StateMeasurement, applied: AppliedControl) -> DisturbanceEstimate:
        planar = self.planar.update(meas, applied)
        b = applied.acc_cmd_enu_mps2[self._axes] + self._f_n
        predicted = self._phi @ self._x + np.outer(self._gamma, b)
        innovation = meas.pos_enu_m[self._axes] - predicted[0]
        self._x = predicted + np.outer(self._gains, innovation)
        z = self._features.build(meas, applied.thrust_n)
        z_obs = z.copy()
        for column, row in self._observed:
            z_obs[column] = self._x[row, -1]
        self._f_n = np.atleast_1d(self.network.predict(z_obs))
        f_n = np.zeros(3)
        f_n[self._axes] = self._f_n
        delta = planar.delta_f_hat.copy()
        delta[self._axes] = 0.0
        return DisturbanceEstimate(f_hat=f_n + delta, f_n=f_n, delta_f_hat=delta, pathway="neural_observer", z=z)
