"""Value types shared by the method, the simulator and (later) the bus schemas.

Frames: world ENU (z up), body FLU (x forward, y left, z up). Euler angles are ZYX
(yaw about world z, then pitch about y, then roll about x), so with ENU/FLU a positive
pitch tilts the thrust towards +x. The PX4 gateway converts to NED/FRD at its boundary.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

GRAVITY_MPS2 = 9.81
# The loop the paper flies, and every service's default: each config takes these, nothing restates them.
LOOP_RATE_HZ = 50.0  # control and estimation rate
LOOP_PERIOD_S = 1.0 / LOOP_RATE_HZ
OMEGA_O_RPS = 15.0  # the ESO's bandwidth (rad/s)
VEL_CUTOFF_HZ = 15.0  # the motion-capture velocity's low-pass (finite difference, then first order)
PATHWAYS = ("neural_eso", "eso", "nn", "none")  # which parts make f̂ (neso.estimator)


def velocity_lag_s(sample_rate_hz: float = LOOP_RATE_HZ, cutoff_hz: float = VEL_CUTOFF_HZ) -> float:
    """The lag (s) of a velocity taken as the finite difference of positions sampled at ``sample_rate_hz`` and
    low-passed at ``cutoff_hz`` (first order): half a sample of the difference plus the filter's time constant, the
    first-order lag the stability certificate carries (:mod:`neso.certificate.roles`). 20.6 ms at 50 Hz, 15 Hz."""
    return 0.5 / sample_rate_hz + 1.0 / (2.0 * math.pi * cutoff_hz)


@dataclass(frozen=True, slots=True)
class AttitudeSetpoint:
    """The outer loop's command to the vehicle, as PX4 offboard attitude control takes it.

    ``thrust_norm`` in [0, 1] is what the vehicle acts on. ``thrust_n`` is the force the
    controller intended (its model's Newtons); it is for logging and for the estimator's
    input, and a vehicle must never act on it.
    """

    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    thrust_norm: float
    thrust_n: float


@dataclass(frozen=True, slots=True)
class StateMeasurement:
    """What the state source reports at one sample (motion capture or estimate).

    ``pos_enu_m`` and ``vel_enu_mps`` have shape (3,). ``t_s`` is the time the sample
    describes (simulation or monotonic seconds).
    """

    t_s: float
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class VehicleModel:
    """The controller's nominal model of the vehicle (not the truth the simulator uses).

    ``hover_thrust_norm`` is the normalised thrust believed to hold ``mass_kg`` in hover;
    normalised thrust is taken as linear in force: ``thrust_norm = T / (m g) * hover``.
    """

    mass_kg: float = 1.0
    gravity_mps2: float = GRAVITY_MPS2
    hover_thrust_norm: float = 0.5

    @property
    def hover_thrust_n(self) -> float:
        return self.mass_kg * self.gravity_mps2


@dataclass(frozen=True, slots=True)
class Reference:
    """A reference sample: position, velocity, acceleration (each shape (3,), ENU) and yaw."""

    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_enu_mps2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
