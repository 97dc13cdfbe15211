"""Thrust-lag identification (neso.learning.identify_thrust_lag) on flights whose thrust response is known: the fit,
and a fit at the edge of its grid that is said and not flown (issue 32: 150 ms, the grid's top, on gusty hovers of a
vehicle whose motors lag 5 ms, and predictions of +878 % from it)."""
from __future__ import annotations

import numpy as np
import pytest

from neso.features import ThrustLag, applied_thrust_series
from neso.learning import FALLBACK_THRUST_LAG, LAG_TIME_CONSTANTS_S, FlightSeries, identify_thrust_lag
from neso.types import GRAVITY_MPS2

DT = 0.02


def flight(lag: ThrustLag, seconds: float = 40.0, seed: int = 3, mass_kg: float = 1.0) -> FlightSeries:
    """A vertical flight whose acceleration is exactly the commanded thrust through ``lag`` (no disturbance): the
    command a hover thrust plus steps every 0.1–0.5 s (the excitation a closed loop under gusts gives)."""
    rng = np.random.default_rng(seed)
    n = int(seconds / DT)
    cmd = np.empty(n)
    i = 0
    while i < n:
        k = int(rng.integers(5, 25))
        cmd[i:i + k] = mass_kg * GRAVITY_MPS2 * (1.0 + rng.uniform(-0.15, 0.15))
        i += k
    acc = applied_thrust_series(cmd, lag, DT) / mass_kg - GRAVITY_MPS2
    vel = np.r_[0.0, np.cumsum(0.5 * (acc[1:] + acc[:-1]))] * DT  # trapezoidal: no shift of half a sample
    pos = 1.0 + np.cumsum(vel) * DT
    zeros = np.zeros(n)
    return FlightSeries(t_s=np.arange(n) * DT, pos_enu_m=np.column_stack([zeros, zeros, pos]),
                        vel_enu_mps=np.column_stack([zeros, zeros, vel]), roll_rad=zeros, pitch_rad=zeros,
                        thrust_prev_n=cmd, f_hat_mps2=np.full((n, 3), np.nan), mass_kg=mass_kg)


def test_a_lag_inside_the_grid_is_found_and_flown():
    true = ThrustLag(0.045, 0.010)
    fit = identify_thrust_lag(flight(true))
    assert not fit.at_edge and fit.note == "" and fit.lag == fit.fitted
    assert fit.lag.time_constant_s + fit.lag.delay_s == pytest.approx(0.055, abs=0.006), fit


def test_a_fit_at_the_top_of_the_grid_is_said_and_the_fallback_is_flown():
    true = ThrustLag(0.40, 0.0)  # longer than the grid reaches: the least-variance candidate is its top
    fit = identify_thrust_lag(flight(true))
    assert fit.fitted.time_constant_s == pytest.approx(LAG_TIME_CONSTANTS_S.max())
    assert fit.at_edge and fit.lag == FALLBACK_THRUST_LAG != fit.fitted
    assert "top of its grid" in fit.note and "150.0 ms" in fit.note and "fallback" in fit.note
    short = identify_thrust_lag(flight(true), time_constants_s=np.arange(0.0, 0.5001, 0.01))
    assert not short.at_edge and short.lag.time_constant_s == pytest.approx(0.40, abs=0.02)  # a grid that reaches it
