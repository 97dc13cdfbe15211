"""A recorded flight flown again by another estimator: the closed-loop evaluation of a candidate network.

The world here is the recording itself. Its reference is flown again, and the disturbance the
vehicle met — reconstructed from the recording as ``f = a − (R e₃ T_applied / m − g)`` per axis with
the controller's nominal model (:mod:`recordings.conditions`) — is injected as a function of time
into a plant that is exactly that nominal model plus the identified thrust response (delay and
first-order lag, also applied to the attitude). Two estimators flown on the same conditions see
the same gusts, the same ground effect along the same path, the same model mismatch; the
difference of their tracking errors is what the networks change. What this world does not have:
disturbances that react to a different path (the injected f is the recorded one even where the
counterfactual flight strays from the recorded one — by millimetres to centimetres here) and
measurement noise (the plant is measured exactly, so both sides are judged on the same footing).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from neso.control import ControlConfig
from neso.features import ThrustLag
from neso.rotations import world_from_body_zyx
from neso.types import LOOP_PERIOD_S, AttitudeSetpoint, Reference, StateMeasurement, VehicleModel
from sim.runner import FlightLog, fly


@dataclass(frozen=True)
class RecordedConditions:
    """One recorded stretch of flight, sampled at ``dt_s``: ``t_s`` (N,), the reference flown
    (``ref_pos_enu_m``, ``ref_vel_enu_mps``, ``ref_acc_enu_mps2`` (N, 3), ``ref_yaw_rad`` (N,)), the
    reconstructed disturbance ``disturbance_enu_mps2`` (N, 3), the measured start
    (``pos0_enu_m``, ``vel0_enu_mps``, ``thrust0_n``), the vehicle's thrust response ``lag`` and its mass
    ``mass_kg`` (the controller and the plant fly it again with that mass)."""

    t_s: np.ndarray
    ref_pos_enu_m: np.ndarray
    ref_vel_enu_mps: np.ndarray
    ref_acc_enu_mps2: np.ndarray
    ref_yaw_rad: np.ndarray
    disturbance_enu_mps2: np.ndarray
    pos0_enu_m: np.ndarray
    vel0_enu_mps: np.ndarray
    thrust0_n: float
    lag: ThrustLag
    dt_s: float = LOOP_PERIOD_S
    mass_kg: float = VehicleModel().mass_kg

    @property
    def duration_s(self) -> float:
        return len(self.t_s) * self.dt_s


class RecordedReference:
    """The recorded reference as a trajectory (sample and hold at the recorded rate), time from 0."""

    def __init__(self, c: RecordedConditions) -> None:
        self.c = c
        self.duration_s = c.duration_s

    def sample(self, t_s: float) -> Reference:
        c = self.c
        k = min(max(int(round(t_s / c.dt_s)) - 1, 0), len(c.t_s) - 1)
        return Reference(c.ref_pos_enu_m[k], c.ref_vel_enu_mps[k], c.ref_acc_enu_mps2[k], float(c.ref_yaw_rad[k]))


@dataclass(frozen=True)
class _Truth:
    t_s: float
    pos_enu_m: np.ndarray
    vel_enu_mps: np.ndarray
    disturbance_acc_enu_mps2: np.ndarray


class RecordedWorld:
    """The nominal vehicle with the recorded disturbance injected (see the module docstring).
    Same interface as :class:`sim.quadrotor.QuadrotorSim` as far as :func:`sim.runner.fly` uses it."""

    substep_s = 0.002

    def __init__(self, conditions: RecordedConditions, vehicle: VehicleModel = VehicleModel()) -> None:
        self.c = conditions
        self.vehicle = vehicle
        self._n_sub = max(1, int(round(conditions.dt_s / self.substep_s)))
        self._h = conditions.dt_s / self._n_sub
        self._delay = int(round(conditions.lag.delay_s / self._h))
        tau = conditions.lag.time_constant_s
        self._alpha = 1.0 - math.exp(-self._h / tau) if tau > 0 else 1.0
        self.crashed = False
        self.diverged = False

    def reset(self, *, pos_enu_m, yaw_rad: float = 0.0) -> StateMeasurement:
        c = self.c
        self._t = 0.0
        self._k = 0
        self._pos = np.array(c.pos0_enu_m, dtype=float)
        self._vel = np.array(c.vel0_enu_mps, dtype=float)
        self._att = np.array([0.0, 0.0, float(yaw_rad)])
        self._thrust = float(c.thrust0_n)
        self._cmd = (0.0, 0.0, float(yaw_rad), float(c.thrust0_n))
        self._queue: deque = deque([self._cmd] * (self._delay + 1), maxlen=self._delay + 1)
        self._dist = np.zeros(3)
        return self._measurement()

    @property
    def applied_thrust_nominal_n(self) -> float:
        return self._thrust

    @property
    def truth(self) -> _Truth:
        return _Truth(self._t, self._pos.copy(), self._vel.copy(), self._dist.copy())

    def step(self, setpoint: AttitudeSetpoint) -> StateMeasurement:
        v = self.vehicle
        thrust_cmd = setpoint.thrust_norm / v.hover_thrust_norm * v.hover_thrust_n
        cmd = (setpoint.roll_rad, setpoint.pitch_rad, setpoint.yaw_rad, thrust_cmd)
        k = min(self._k, len(self.c.t_s) - 1)
        self._dist = np.asarray(self.c.disturbance_enu_mps2[k], dtype=float)
        g = np.array([0.0, 0.0, v.gravity_mps2])
        for _ in range(self._n_sub):
            self._queue.append(cmd)
            roll, pitch, yaw, thrust = self._queue[0]
            self._att += self._alpha * (np.array([roll, pitch, yaw]) - self._att)
            self._thrust += self._alpha * (thrust - self._thrust)
            acc = world_from_body_zyx(*self._att)[:, 2] * (self._thrust / v.mass_kg) - g + self._dist
            self._vel = self._vel + acc * self._h
            self._pos = self._pos + self._vel * self._h
        self._t += self.c.dt_s
        self._k += 1
        if not (np.all(np.isfinite(self._pos)) and np.linalg.norm(self._pos) < 1e3):
            self.diverged = True
        return self._measurement()

    def _measurement(self) -> StateMeasurement:
        return StateMeasurement(self._t, self._pos.copy(), self._vel.copy(), float(self._att[0]), float(self._att[1]),
                                float(self._att[2]))


def fly_recorded(conditions: RecordedConditions, estimator, control: ControlConfig = ControlConfig()) -> FlightLog:
    """Fly the recorded reference with ``estimator`` in the recorded world, the controller's model and the
    plant at the recorded vehicle's mass."""
    reference = RecordedReference(conditions)
    control = replace(control, vehicle=replace(control.vehicle, mass_kg=conditions.mass_kg))
    return fly(plant=RecordedWorld(conditions, control.vehicle), estimator=estimator, trajectory=reference,
               seed=0, control=control)


def z_rmse_cm(log: FlightLog, skip_s: float = 1.0) -> tuple[float, int]:
    """(z RMSE of truth against reference in cm, samples) after the first ``skip_s``."""
    ok = np.isfinite(log.t_s) & (log.t_s >= skip_s)
    err = log.pos_true_m[ok, 2] - log.pos_ref_m[ok, 2]
    return (float(np.sqrt(np.mean(err ** 2))) * 100 if err.size else float("nan")), int(err.size)


def predict_change(conditions: list[RecordedConditions], make_estimator, networks: dict,
                   control: ControlConfig = ControlConfig()) -> dict:
    """Fly every recorded stretch with each network (``networks``: name → network; ``make_estimator(net)``
    builds the estimator) and report each one's z RMSE in cm over all of them (``rmse_<name>_cm``),
    ``seconds`` flown and, for names ``active`` and ``candidate``, ``change`` = candidate/active − 1."""
    out: dict = {"seconds": float(sum(c.duration_s for c in conditions))}
    for name, net in networks.items():
        sq, n = 0.0, 0
        for c in conditions:
            log = fly_recorded(c, make_estimator(net), control)
            rmse, count = z_rmse_cm(log)
            if log.diverged or not math.isfinite(rmse):
                sq, n = math.inf, max(n, 1)
                break
            sq += rmse ** 2 * count
            n += count
        out[f"rmse_{name}_cm"] = math.sqrt(sq / n) if n else float("nan")
    if "rmse_active_cm" in out and "rmse_candidate_cm" in out and out["rmse_active_cm"] > 0:
        out["change"] = out["rmse_candidate_cm"] / out["rmse_active_cm"] - 1.0
    return out
