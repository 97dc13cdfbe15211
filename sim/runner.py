"""The in-process experiment runner: one flight of sim + estimator + controller at the control rate.

The order of one tick is the contract the distributed lockstep run must reproduce:

    meas_k  = sim.step(setpoint_{k−1})        (the sim advances one control period)
    est_k   = estimator.update(meas_k, applied_{k−1})
    out_k   = controller.step(meas_k, ref(t_k), est_k.f_hat)
    setpoint_k, applied_k = out_k

Tick 0 uses the nominal hover setpoint as setpoint_{−1}.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from neso.control import ControlConfig, PositionController
from neso.estimator import DisturbanceEstimator
from neso.features import N_FEATURES
from sim.quadrotor import QuadrotorSim, SimConfig


@dataclass
class FlightLog:
    """Per-tick arrays of one flight (N ticks). Positions/velocities ENU m, m/s; f in m/s²."""

    t_s: np.ndarray
    pos_true_m: np.ndarray  # (N, 3) truth at the tick
    pos_meas_m: np.ndarray  # (N, 3) what the controller saw
    vel_meas_mps: np.ndarray  # (N, 3)
    pos_ref_m: np.ndarray  # (N, 3)
    f_hat: np.ndarray  # (N, 3)
    f_n: np.ndarray  # (N, 3)
    delta_f_hat: np.ndarray  # (N, 3)
    z: np.ndarray  # (N, 5) network input
    thrust_n: np.ndarray  # (N,) commanded
    acc_cmd_mps2: np.ndarray  # (N, 3) nominal acceleration of the command issued at the tick
    f_true: np.ndarray  # (N, 3) the disturbance the nominal model does not explain (truth)
    diverged: bool = False
    reason: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def z_error_m(self) -> np.ndarray:
        return self.pos_true_m[:, 2] - self.pos_ref_m[:, 2]


def fly(
    *,
    sim_config: SimConfig,
    estimator: DisturbanceEstimator,
    trajectory,
    seed: int,
    control: ControlConfig = ControlConfig(),
    duration_s: float | None = None,
    on_tick=None,
    before_step=None,
) -> FlightLog:
    """Fly ``trajectory`` in a fresh simulator; ``on_tick(k, t_s, estimator)`` may change the
    estimator between ticks (a pathway switch, a network swap); ``before_step(k, sim, setpoint)``
    sees the simulator just before it takes tick k's setpoint (it must not change it)."""
    duration_s = trajectory.duration_s if duration_s is None else duration_s
    dt = control.dt_s
    n = int(round(duration_s / dt))
    sim = QuadrotorSim(sim_config, seed=seed)
    ref0 = trajectory.sample(0.0)
    sim.reset(pos_enu_m=ref0.pos_enu_m, yaw_rad=ref0.yaw_rad)
    controller = PositionController(control)
    out = controller.hover_output(ref0.yaw_rad)
    cols = {name: np.full((n, w), np.nan) for name, w in (
        ("pos_true_m", 3), ("pos_meas_m", 3), ("vel_meas_mps", 3), ("pos_ref_m", 3), ("f_hat", 3),
        ("f_n", 3), ("delta_f_hat", 3), ("z", N_FEATURES), ("acc_cmd_mps2", 3), ("f_true", 3))}
    thrust = np.full(n, np.nan)
    t = np.full(n, np.nan)
    diverged, reason = False, ""
    for k in range(n):
        if before_step is not None:
            before_step(k, sim, out.setpoint)
        meas = sim.step(out.setpoint)
        truth = sim.truth
        t[k] = truth.t_s
        if k == 0:
            estimator.reset(meas, out.applied.thrust_n)
        if on_tick is not None:
            on_tick(k, t[k], estimator)
        est = estimator.update(meas, out.applied)
        ref = trajectory.sample(truth.t_s)
        out = controller.step(meas, ref, est.f_hat)
        row = (truth.pos_enu_m, meas.pos_enu_m, meas.vel_enu_mps, ref.pos_enu_m, est.f_hat, est.f_n,
               est.delta_f_hat, est.z, out.applied.acc_cmd_enu_mps2, truth.disturbance_acc_enu_mps2)
        for name, value in zip(cols, row):
            cols[name][k] = value
        thrust[k] = out.setpoint.thrust_n
        if sim.diverged or sim.crashed:
            diverged, reason = True, ("diverged" if sim.diverged else "crashed")
            break
    return FlightLog(t_s=t, thrust_n=thrust, diverged=diverged, reason=reason, **cols)
