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
from neso.learning import FlightSeries
from neso.types import GRAVITY_MPS2
from sim.quadrotor import NOMINAL_MASS_KG, QuadrotorSim, SimConfig


@dataclass
class FlightLog:
    """Per-tick arrays of one flight (N ticks). Positions/velocities ENU m, m/s; f in m/s²."""

    t_s: np.ndarray
    pos_true_m: np.ndarray  # (N, 3) truth at the tick
    pos_meas_m: np.ndarray  # (N, 3) what the controller saw
    vel_meas_mps: np.ndarray  # (N, 3)
    att_meas_rad: np.ndarray  # (N, 3) roll, pitch, yaw the controller saw
    pos_ref_m: np.ndarray  # (N, 3)
    f_hat: np.ndarray  # (N, 3)
    f_n: np.ndarray  # (N, 3)
    delta_f_hat: np.ndarray  # (N, 3)
    z: np.ndarray  # (N, n) network input (n: its feature set's size; 0 without a network)
    thrust_n: np.ndarray  # (N,) commanded
    thrust_prev_n: np.ndarray  # (N,) the thrust commanded at the tick before (what the estimator was told acted)
    acc_cmd_mps2: np.ndarray  # (N, 3) nominal acceleration of the command issued at the tick
    f_true: np.ndarray  # (N, 3) the disturbance the nominal model does not explain (truth)
    vel_true_mps: np.ndarray  # (N, 3)
    thrust_applied_true_n: np.ndarray  # (N,) the thrust the rotors are driven to after delay and lag (nominal N)
    vel_ref_mps: np.ndarray | None = None  # (N, 3) the reference's velocity (None: not recorded)
    diverged: bool = False
    reason: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def z_error_m(self) -> np.ndarray:
        return self.pos_true_m[:, 2] - self.pos_ref_m[:, 2]

    def applied_disturbance_truth_z(self, dt_s: float) -> np.ndarray:
        """The true z disturbance relative to the *applied* thrust, averaged over each control period
        (N,; NaN at the first tick): (v_k − v_{k−1})/Δ + g − mean over the period of
        (R e₃)_z·T_applied/m, in the controller's nominal model (m/s²). What a label free of the command's
        lag should recover."""
        acc = np.r_[np.nan, np.diff(self.vel_true_mps[:, 2]) / dt_s]
        lift = np.cos(self.att_meas_rad[:, 0]) * np.cos(self.att_meas_rad[:, 1]) * self.thrust_applied_true_n
        mean_lift = 0.5 * (np.r_[np.nan, lift[:-1]] + lift)
        return acc + GRAVITY_MPS2 - mean_lift / NOMINAL_MASS_KG

    def series(self, pathway: str | None = None) -> FlightSeries:
        """The samples as the estimator saw them (ticks up to a divergence)."""
        keep = np.isfinite(self.t_s)
        return FlightSeries(t_s=self.t_s[keep], pos_enu_m=self.pos_meas_m[keep], vel_enu_mps=self.vel_meas_mps[keep],
                            roll_rad=self.att_meas_rad[keep, 0], pitch_rad=self.att_meas_rad[keep, 1],
                            thrust_prev_n=self.thrust_prev_n[keep], f_hat_mps2=self.f_hat[keep],
                            pathway=None if pathway is None else np.full(int(keep.sum()), pathway, dtype=object),
                            ref_pos_enu_m=self.pos_ref_m[keep],
                            ref_vel_enu_mps=None if self.vel_ref_mps is None else self.vel_ref_mps[keep])


def fly(
    *,
    sim_config: SimConfig | None = None,
    estimator: DisturbanceEstimator,
    trajectory,
    seed: int,
    control: ControlConfig = ControlConfig(),
    duration_s: float | None = None,
    on_tick=None,
    plant=None,
    before_step=None,
) -> FlightLog:
    """Fly ``trajectory`` in a fresh simulator of ``sim_config`` (or in ``plant``, any object with the
    simulator's ``reset``/``step``/``truth`` interface, e.g. :class:`sim.counterfactual.RecordedWorld`);
    ``on_tick(k, t_s, estimator)`` may change the estimator between ticks (a pathway switch, a network swap);
    ``before_step(k, sim, setpoint)`` sees the simulator just before it takes tick k's setpoint (it must not
    change it)."""
    duration_s = trajectory.duration_s if duration_s is None else duration_s
    dt = control.dt_s
    n = int(round(duration_s / dt))
    sim = plant if plant is not None else QuadrotorSim(sim_config, seed=seed)
    ref0 = trajectory.sample(0.0)
    sim.reset(pos_enu_m=ref0.pos_enu_m, yaw_rad=ref0.yaw_rad)
    controller = PositionController(control)
    out = controller.hover_output(ref0.yaw_rad)
    cols = {name: np.full((n, w), np.nan) for name, w in (
        ("pos_true_m", 3), ("pos_meas_m", 3), ("vel_meas_mps", 3), ("att_meas_rad", 3), ("pos_ref_m", 3),
        ("f_hat", 3), ("f_n", 3), ("delta_f_hat", 3), ("acc_cmd_mps2", 3), ("f_true", 3), ("vel_true_mps", 3),
        ("vel_ref_mps", 3))}
    scalars = {name: np.full(n, np.nan) for name in ("thrust_n", "thrust_prev_n", "thrust_applied_true_n")}
    zs = []
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
        scalars["thrust_prev_n"][k] = out.applied.thrust_n
        out = controller.step(meas, ref, est.f_hat)
        row = (truth.pos_enu_m, meas.pos_enu_m, meas.vel_enu_mps, (meas.roll_rad, meas.pitch_rad, meas.yaw_rad),
               ref.pos_enu_m, est.f_hat, est.f_n, est.delta_f_hat, out.applied.acc_cmd_enu_mps2,
               truth.disturbance_acc_enu_mps2, truth.vel_enu_mps, ref.vel_enu_mps)
        for name, value in zip(cols, row):
            cols[name][k] = value
        zs.append(est.z)
        scalars["thrust_n"][k] = out.setpoint.thrust_n
        scalars["thrust_applied_true_n"][k] = sim.applied_thrust_nominal_n
        if sim.diverged or sim.crashed:
            diverged, reason = True, ("diverged" if sim.diverged else "crashed")
            break
    n_z = len(zs[0]) if zs else 0
    z = np.full((n, n_z), np.nan)
    z[:len(zs)] = np.array(zs).reshape(len(zs), n_z)
    return FlightLog(t_s=t, z=z, diverged=diverged, reason=reason, **cols, **scalars)
