"""The network's inputs: feature sets built alike for one sample and for a series, and the applied-thrust model."""
from __future__ import annotations

import math

import numpy as np
import pytest

from neso.features import (FEATURE_SETS, AppliedThrust, FeatureBuilder, FeatureSetError, FeatureSignals, ThrustLag,
                           applied_thrust_series, feature_set)
from tests.helpers import measurement


def _continuous(commands: np.ndarray, lag: ThrustLag, dt: float, fine: int = 2000) -> np.ndarray:
    """The same response integrated on a fine grid: each command held for dt, acting from its time + delay."""
    h = dt / fine
    y = commands[0]
    out = []
    n = len(commands)
    for k in range(n):  # sample k is at t = k·dt; the command issued at sample j acts from j·dt + delay
        out.append(y)
        for i in range(fine):
            t = k * dt + i * h
            j = math.floor((t - lag.delay_s) / dt + 1e-12)
            u = commands[min(max(j, 0), n - 1)]
            y += (u - y) * (1.0 - math.exp(-h / lag.time_constant_s)) if lag.time_constant_s > 0 else (u - y)
    return np.array(out)


@pytest.mark.parametrize("lag", [ThrustLag(0.045, 0.01), ThrustLag(0.03, 0.05), ThrustLag(0.08, 0.0)])
def test_the_applied_thrust_is_the_exact_zero_order_hold_response(lag):
    dt = 0.02
    rng = np.random.default_rng(0)
    commands = 9.8 + rng.normal(0, 1.0, 60)
    exact = _continuous(commands, lag, dt)
    # the model is fed the command issued at the sample before (thrust_prev); its sample k is the thrust at k
    prev = np.r_[commands[0], commands[:-1]]
    ours = applied_thrust_series(prev, lag, dt)
    np.testing.assert_allclose(ours[3:], exact[3:], atol=2e-3)
    online = AppliedThrust(lag, dt)
    online.reset(prev[0])
    np.testing.assert_allclose([online.update(u) for u in prev], ours, atol=1e-12)


def test_one_builder_for_one_sample_and_for_a_series():
    rng = np.random.default_rng(1)
    n = 40
    pos, vel = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    roll, pitch, thrust = rng.normal(0, 0.1, n), rng.normal(0, 0.1, n), 9.8 + rng.normal(0, 0.5, n)
    lag = ThrustLag(0.04, 0.01)
    for fs in FEATURE_SETS.values():
        builder = FeatureBuilder(fs, lag, 0.02)
        rows = [builder.reset(measurement(pos[0], vel[0], roll=roll[0], pitch=pitch[0]), thrust[0])]
        rows += [builder.build(measurement(pos[k], vel[k], roll=roll[k], pitch=pitch[k]), thrust[k]) for k in range(1, n)]
        prev = np.r_[thrust[0], thrust[1:]]
        batch = fs.build(FeatureSignals(pos, vel, roll, pitch, prev, applied_thrust_series(prev, lag, 0.02)))
        np.testing.assert_allclose(np.array(rows), batch, atol=1e-12)
        assert batch.shape == (n, fs.size)


def test_which_columns_are_the_tracked_state_and_which_sets_carry_thrust():
    assert feature_set("paper@1").state_columns == (0, 1) and not feature_set("paper@1").uses_applied_thrust
    assert feature_set("state_speed@1").columns[-1] == "speed_xy_mps"
    assert feature_set("applied@1").uses_applied_thrust
    assert "thrust" not in "".join(feature_set("state@1").columns + feature_set("state_speed@1").columns)
    assert feature_set("state") is feature_set("state@1")  # a bare name is its newest version
    with pytest.raises(FeatureSetError, match="unknown feature set 'radar@1'.*paper@1"):
        feature_set("radar@1")


def test_reference_regressors_take_the_tracked_state_from_the_reference_where_it_is_known():
    """Issue 32: trained on the measured state, a network's slopes find the loop (the state answers the
    disturbance); ``regressors="reference"`` builds the tracked state's columns from the reference the
    controller tracked (an instrument the disturbance does not move), the rest as flown; where the reference is
    unknown (NaN: an imported log) the measured state stays."""
    import numpy as np

    from neso.learning import FlightSeries, features

    n = 6
    rng = np.random.default_rng(0)
    ref_pos, ref_vel = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    ref_pos[2] = np.nan
    series = FlightSeries(t_s=np.arange(n) * 0.02, pos_enu_m=rng.normal(size=(n, 3)), vel_enu_mps=rng.normal(size=(n, 3)),
                          roll_rad=rng.normal(size=n), pitch_rad=rng.normal(size=n), thrust_prev_n=np.full(n, 9.8),
                          f_hat_mps2=np.zeros((n, 3)), ref_pos_enu_m=ref_pos, ref_vel_enu_mps=ref_vel)
    fset = feature_set("state@1")
    state, ref = features(series, fset), features(series, fset, regressors="reference")
    known = np.arange(n) != 2
    assert np.array_equal(ref[known, 0], ref_pos[known, 2]) and np.array_equal(ref[known, 1], ref_vel[known, 2])
    assert np.array_equal(ref[2], state[2]) and np.array_equal(ref[:, 2:], state[:, 2:])  # attitude as flown
    assert np.array_equal(state[:, 0], series.pos_enu_m[:, 2])
    with pytest.raises(ValueError, match="regressors"):
        features(series, fset, regressors="instrument")


def test_a_recordings_training_set_reads_the_recorded_reference(tmp_path):
    import numpy as np

    from recordings.dataset import load_training_set
    from tests.helpers import flight_messages, write_recording

    import dataclasses

    msgs = [(t, dataclasses.replace(m, pos_enu_m=(m.pos_enu_m[0], m.pos_enu_m[1], m.pos_enu_m[2] + 1.0))
             if t == "reference" else m) for t, m in flight_messages(300)]  # a reference 1 m off the state
    path = tmp_path / "f.rrd"
    write_recording(path, msgs)
    refs = {m.seq: m for t, m in msgs if t == "reference"}
    state = load_training_set(path, "eso", feature_set_key="state@1")
    ref = load_training_set(path, "eso", feature_set_key="state@1", regressors="reference")
    assert len(ref.y_mps2) == len(state.y_mps2) > 0
    assert not np.allclose(ref.z[:, :2], state.z[:, :2]) and np.array_equal(ref.z[:, 2:], state.z[:, 2:])
    assert set(np.round(ref.z[:, 0], 12)) <= {round(m.pos_enu_m[2], 12) for m in refs.values()}
