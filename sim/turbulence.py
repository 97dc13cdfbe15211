"""Dryden-type gusts whose intensity grows near the ground with speed.

Model (a documented simplification of the MIL-F-8785C low-altitude Dryden form): each axis of
the gust velocity (world ENU, m/s) is ``w_i(t) = sigma(h, speed) * xi_i(t)``, where ``xi_i`` is a
unit-variance first-order (Ornstein-Uhlenbeck) process with correlation time ``tau_i``::

    d xi = -xi / tau dt + sqrt(2 / tau) dW

i.e. the first-order Dryden shaping filter ``sqrt(2 tau) / (1 + tau s)`` driven by unit white
noise. It is discretised exactly: ``xi <- a xi + sqrt(1 - a^2) n``, ``a = exp(-dt / tau)``,
``n ~ N(0, 1)``. That is the same as driving the Euler-discretised filter with white noise scaled
by ``1/sqrt(dt)`` (the continuous PSD is kept), so the gust variance does not depend on ``dt``
(RotorPy's Dryden code drives the filter with un-scaled uniform noise, so its intensity does).

Intensity (m/s, per axis)::

    sigma(h, speed) = sigma_0 + k_speed * speed * exp(-h / h_0)

with ``h`` the vehicle height above the terrain (m) and ``speed`` its horizontal ground speed
(m/s): rotor wash reflected from the ground recirculates and is torn up by forward motion
("nonstationary turbulence" of the paper's Experiment 3). The gust acts on the vehicle as a
force through the linear (rotor) drag on the relative air velocity ``v - w`` (see
``sim.quadrotor``). Constants and their sources are on ``TurbulenceConfig``.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

_BUFFER_SIZE = 3 * 4096


@dataclass(frozen=True, slots=True)
class TurbulenceConfig:
    """Gust model constants.

    - ``sigma0_mps`` (0.02): background indoor air motion in a mocap arena. Assumed (no source
      gives a number for a closed flight arena; MIL-F-8785C's low-altitude light turbulence is
      ~1 m/s outdoors, an arena is far calmer).
    - ``k_speed`` (0.1, dimensionless, m/s of sigma per m/s of speed): growth of the near-ground
      gust intensity with speed. Assumed; a 1.2 m/s pass at 0.25 m gives sigma ~0.05 m/s (mild).
      ``STRONG_NEAR_GROUND_TURBULENCE`` (sigma0 0.05, k_speed 1.0) gives ~0.39 m/s there, i.e.
      ~0.2 m/s^2 vertical and ~0.16 m/s^2 horizontal force std through the rotor drag (the
      paper's Experiment 3 "nonstationary turbulence"; magnitude assumed, chosen so PD errs by
      a few cm as in the paper's Table).
    - ``h0_m`` (0.2): e-folding height of the near-ground recirculation, ~3 rotor radii,
      comparable to the reach of the ground effect (Neural-Lander fit's 0.195 m).
    - ``tau_horizontal_s`` (0.2), ``tau_vertical_s`` (0.1): correlation times; MIL-F-8785C's
      low-altitude form has a vertical length scale equal to the height (much shorter than the
      horizontal one), so the vertical gust decorrelates faster. Values assumed, ~L/V with
      L ~ 0.2-0.5 m eddies at 1-2.5 m/s.
    - ``enabled``: False gives zero gusts (and draws no random numbers).
    """

    enabled: bool = True
    sigma0_mps: float = 0.02
    k_speed: float = 0.1
    h0_m: float = 0.2
    tau_horizontal_s: float = 0.2
    tau_vertical_s: float = 0.1


MILD_TURBULENCE = TurbulenceConfig()
STRONG_NEAR_GROUND_TURBULENCE = TurbulenceConfig(sigma0_mps=0.05, k_speed=1.0, h0_m=0.2)
NO_TURBULENCE = TurbulenceConfig(enabled=False)


def gust_sigma_mps(config: TurbulenceConfig, height_m: float, speed_mps: float) -> float:
    """Per-axis gust standard deviation (m/s) at ``height_m`` above terrain and horizontal speed."""
    return config.sigma0_mps + config.k_speed * speed_mps * math.exp(-max(height_m, 0.0) / config.h0_m)


class DrydenGusts:
    """Seeded gust generator. ``step(height_m, speed_mps)`` advances by ``dt_s`` and returns the
    gust velocity (wx, wy, wz) in m/s, world ENU, as plain floats (hot path)."""

    __slots__ = ("_cfg", "_rng", "_buf", "_i", "_a", "_b", "_xi")

    def __init__(self, config: TurbulenceConfig, dt_s: float, rng: np.random.Generator) -> None:
        self._cfg = config
        self._rng = rng
        a_h = math.exp(-dt_s / config.tau_horizontal_s)
        a_v = math.exp(-dt_s / config.tau_vertical_s)
        self._a = (a_h, a_h, a_v)
        self._b = (math.sqrt(1.0 - a_h * a_h), math.sqrt(1.0 - a_h * a_h), math.sqrt(1.0 - a_v * a_v))
        self._buf: list[float] = []
        self._i = 0
        # Start in the stationary distribution so a trial has no warm-up transient.
        if config.enabled:
            self._xi = [float(v) for v in rng.standard_normal(3)]
        else:
            self._xi = [0.0, 0.0, 0.0]

    def reconfigured(self, config: TurbulenceConfig) -> "DrydenGusts":
        """This generator, in its current state, with the intensity of ``config`` (same
        correlation times required; a disabled config gives zero gusts from now on)."""
        if config.enabled and (config.tau_horizontal_s, config.tau_vertical_s) != (
                self._cfg.tau_horizontal_s, self._cfg.tau_vertical_s):
            raise ValueError("reconfigured gusts keep their correlation times")
        twin = object.__new__(DrydenGusts)
        for name in DrydenGusts.__slots__:
            setattr(twin, name, getattr(self, name))
        twin._cfg = config
        twin._xi = list(self._xi)
        twin._rng = copy.deepcopy(self._rng)  # the same stream from here, not shared
        return twin

    def step(self, height_m: float, speed_mps: float) -> tuple[float, float, float]:
        cfg = self._cfg
        if not cfg.enabled:
            return 0.0, 0.0, 0.0
        i = self._i
        if i + 3 > len(self._buf):
            self._buf = self._rng.standard_normal(_BUFFER_SIZE).tolist()
            i = 0
        buf = self._buf
        a, b, xi = self._a, self._b, self._xi
        x0 = a[0] * xi[0] + b[0] * buf[i]
        x1 = a[1] * xi[1] + b[1] * buf[i + 1]
        x2 = a[2] * xi[2] + b[2] * buf[i + 2]
        self._i = i + 3
        xi[0], xi[1], xi[2] = x0, x1, x2
        h = height_m if height_m > 0.0 else 0.0
        sigma = cfg.sigma0_mps + cfg.k_speed * speed_mps * math.exp(-h / cfg.h0_m)
        return sigma * x0, sigma * x1, sigma * x2
