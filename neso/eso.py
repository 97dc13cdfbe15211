"""Third-order extended state observer, one per axis, vectorised over x, y, z.

Model per axis (paper eq. 5-6): x1 = position, x2 = velocity, x3 = the extended state
(the disturbance, or under Neural-ESO the residual Δf), with

    ẋ1 = x2,   ẋ2 = b + x3,   ẋ3 = ḟ

where ``b`` is the known acceleration input (commanded acceleration plus the network
prior f_N under Neural-ESO).

Discretisation ("exact", the default): zero-order hold of ``b`` over the sample period
Δ and a *current* observer (predict with Φ = e^{AΔ}, then correct with the new
measurement), with the gains that place all three poles of the discrete error
dynamics (I − L C) Φ at β = e^{−ω_o Δ} — the triple pole the continuous design puts at
−ω_o (Miklosovic, Radke & Gao 2006; the pyadrc ``StateSpace`` form):

    L = [1 − β³,  3(1 − β)²(1 + β) / (2Δ),  (1 − β)³ / Δ²]

"euler" keeps the paper's continuous gains (3ω, 3ω², ω³) with a forward-Euler step; its
poles are not at e^{−ω_o Δ} (kept for comparison and tests).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from neso.types import LOOP_PERIOD_S, OMEGA_O_RPS

DISCRETISATIONS = ("exact", "euler")


def transition_matrix(dt_s: float) -> np.ndarray:
    """Φ = e^{AΔ} (3, 3) of the chain of integrators x1 ← x2 ← x3."""
    return np.array([[1.0, dt_s, 0.5 * dt_s * dt_s], [0.0, 1.0, dt_s], [0.0, 0.0, 1.0]])


def input_matrix(dt_s: float) -> np.ndarray:
    """Γ (3,): zero-order-hold response of the state to a unit acceleration over Δ."""
    return np.array([0.5 * dt_s * dt_s, dt_s, 0.0])


def exact_gains(omega_o_rps: float, dt_s: float) -> np.ndarray:
    """Current-observer gains (3,) placing the discrete triple pole at e^{−ω_o Δ}."""
    beta = math.exp(-omega_o_rps * dt_s)
    return np.array(
        [
            1.0 - beta**3,
            1.5 * (1.0 - beta) ** 2 * (1.0 + beta) / dt_s,
            (1.0 - beta) ** 3 / (dt_s * dt_s),
        ]
    )


def continuous_gains(omega_o_rps: float) -> np.ndarray:
    """Bandwidth-parameterised continuous gains (β1, β2, β3) = (3ω, 3ω², ω³)."""
    w = omega_o_rps
    return np.array([3.0 * w, 3.0 * w * w, w**3])


def error_dynamics(omega_o_rps: float, dt_s: float, discretisation: str = "exact") -> np.ndarray:
    """The (3, 3) matrix mapping the estimation error from one sample to the next."""
    phi = transition_matrix(dt_s)
    c = np.array([[1.0, 0.0, 0.0]])
    if discretisation == "exact":
        gains = exact_gains(omega_o_rps, dt_s).reshape(3, 1)
        return (np.eye(3) - gains @ c) @ phi
    if discretisation == "euler":
        a = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
        gains = continuous_gains(omega_o_rps).reshape(3, 1)
        return np.eye(3) + dt_s * (a - gains @ c)
    raise ValueError(f"unknown discretisation {discretisation!r}; choose one of {DISCRETISATIONS}")


@dataclass(frozen=True, slots=True)
class EsoConfig:
    """``omega_o_rps`` observer bandwidth (rad/s); ``dt_s`` sample period (s)."""

    omega_o_rps: float = OMEGA_O_RPS
    dt_s: float = LOOP_PERIOD_S
    discretisation: str = "exact"

    def __post_init__(self) -> None:
        if not (self.omega_o_rps > 0 and math.isfinite(self.omega_o_rps)):
            raise ValueError(f"omega_o_rps must be positive and finite, got {self.omega_o_rps}")
        if not self.dt_s > 0:
            raise ValueError(f"dt_s must be positive, got {self.dt_s}")
        if self.discretisation not in DISCRETISATIONS:
            raise ValueError(f"discretisation must be one of {DISCRETISATIONS}, got {self.discretisation!r}")


class ExtendedStateObserver:
    """Three axes of the third-order ESO. ``state`` is (3, 3): rows x1, x2, x3; columns x, y, z.

    Call :meth:`update` once per sample with the position measured at that sample and the
    acceleration input ``b`` (3,) that acted over the *previous* period.
    """

    def __init__(self, config: EsoConfig = EsoConfig()) -> None:
        self.config = config
        self._phi = transition_matrix(config.dt_s)
        self._gamma = input_matrix(config.dt_s).reshape(3, 1)
        if config.discretisation == "exact":
            self._gains = exact_gains(config.omega_o_rps, config.dt_s).reshape(3, 1)
        else:
            self._gains = continuous_gains(config.omega_o_rps).reshape(3, 1)
        self.state = np.zeros((3, 3))

    def reset(self, pos_m: np.ndarray, vel_mps: np.ndarray | None = None, extended: np.ndarray | None = None) -> None:
        """Start from a known position (3,), velocity (3,) and extended state (3,)."""
        self.state = np.zeros((3, 3))
        self.state[0] = pos_m
        if vel_mps is not None:
            self.state[1] = vel_mps
        if extended is not None:
            self.state[2] = extended

    def update(self, pos_meas_m: np.ndarray, input_acc_mps2: np.ndarray) -> np.ndarray:
        """Advance one sample; returns the new state (3, 3) (a view: copy to keep it)."""
        if self.config.discretisation == "exact":
            predicted = self._phi @ self.state + self._gamma * input_acc_mps2
            self.state = predicted + self._gains * (pos_meas_m - predicted[0])
        else:
            x = self.state
            innovation = pos_meas_m - x[0]
            dt = self.config.dt_s
            g = self._gains
            self.state = np.vstack(
                (
                    x[0] + dt * (x[1] + g[0] * innovation),
                    x[1] + dt * (input_acc_mps2 + x[2] + g[1] * innovation),
                    x[2] + dt * (g[2] * innovation),
                )
            )
        return self.state

    @property
    def extended(self) -> np.ndarray:
        """x̂3 (3,): the disturbance (or residual) estimate in m/s²."""
        return self.state[2]
