"""The loop's step objects flown in one process, for the hot-path exactness test (tests/unit/test_hotpath_exact.py).

:func:`messages` runs the simulator source, the estimator and the controller exactly as the bus wires them
(state k → estimate k → setpoint k → the estimator's control for k+1 and the vehicle's next period);
:func:`fly` returns every estimate's and setpoint's numbers as arrays (``bench.steps`` times the cores on
:func:`messages`). ``tests/data/loop-golden.npz`` holds what the
code produced before the per-sample work of issue 16 (written by ``python -m tests.loop_replay OUT``)."""
from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np


def estimator_core(rate_hz: float, clock):
    """The estimator's step object as the service builds it (the network it flies by default)."""
    from flight.estimator import EstimatorConfig, EstimatorCore, NetworkChoice, load_flown_network

    config = EstimatorConfig(dt_s=1.0 / rate_hz)
    network, path = load_flown_network(config.network)
    return EstimatorCore(config, network, NetworkChoice(network, path, None), clock=clock)


def controller_core(rate_hz: float, mission: str, clock):
    """The controller's step object flying ``mission`` at ``rate_hz``."""
    from flight.controller import ControllerConfig, ControllerCore
    from neso.control import ControlConfig

    return ControllerCore(replace(ControllerConfig(mission=mission), control=ControlConfig(dt_s=1.0 / rate_hz)),
                          clock=clock)


def messages(rate_hz: float, n: int, scenario: str = "lemniscate_near_ground",
             mission: str = "lemniscate") -> list[tuple]:
    """(state, estimate, setpoint) of each of ``n`` samples, flown as the bus wires the loop."""
    from flight.source import SimSource, SourceConfig

    clock = lambda: 0.0  # noqa: E731 - stamps are not compared
    source = SimSource(SourceConfig(rate_hz=rate_hz, scenario=scenario, seed=3), clock=clock)
    estimator, controller = estimator_core(rate_hz, clock), controller_core(rate_hz, mission, clock)
    out = []
    for _ in range(n):
        state, _truth = source.step()
        estimate = estimator.on_state(state, 0.0)[0]
        controller.on_state(state, 0.0)
        setpoint, _ref = controller.on_estimate(estimate, 0.0)[0]
        estimator.on_setpoint(setpoint, 0.0)
        source.take(setpoint)
        out.append((state, estimate, setpoint))
    return out


def fly(rate_hz: float, n: int, scenario: str = "lemniscate_near_ground", mission: str = "lemniscate") -> dict:
    """Every estimate's and setpoint's numbers of :func:`messages`, as arrays (n, 12) and (n, 8)."""
    flown = messages(rate_hz, n, scenario, mission)
    est_rows = [e.f_hat_mps2 + e.f_n_mps2 + e.delta_f_hat_mps2 + e.z for _s, e, _p in flown]
    sp_rows = [(p.roll_rad, p.pitch_rad, p.yaw_rad, p.thrust_norm, p.thrust_n) + p.acc_cmd_enu_mps2
               for _s, _e, p in flown]
    return {"estimates": np.array(est_rows), "setpoints": np.array(sp_rows)}


CASES = {"500hz": (500.0, 1500), "50hz": (50.0, 600)}


if __name__ == "__main__":
    out = {}
    for name, (rate, n) in CASES.items():
        for key, value in fly(rate, n).items():
            out[f"{name}_{key}"] = value
    np.savez_compressed(sys.argv[1], **out)
