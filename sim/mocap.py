"""Motion-capture model: sampled, noisy, late, with velocity from filtered finite differences.

What an operator's OptiTrack pipeline delivers to the outer loop:

- samples at ``rate_hz`` (100 Hz) of the true pose; position noise ``pos_noise_std_m`` (1 mm,
  per axis; OptiTrack-class systems report sub-millimetre to ~1 mm rigid-body jitter, DESIGN.md
  uses ~1 mm) and attitude noise ``att_noise_std_rad`` (0.1 deg per Euler angle);
- latency ``latency_s`` (10 ms: camera exposure + processing + network; with the simulator's
  10 ms command transport delay this makes the ~20 ms loop delay DESIGN.md mentions): the
  measurement handed over at control time t is the latest sample taken at or before t - latency;
- velocity: finite difference of consecutive noisy positions, then a first-order low-pass with
  cutoff ``vel_cutoff_hz`` (15 Hz), discretised exactly (``a = exp(-2 pi f_c / rate)``).

``MocapFilter`` is the per-sample pipeline (noise + velocity); ``sim.quadrotor`` decides when
samples are taken and which one is handed over. Seeded by the ``numpy.random.Generator`` given.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np

from neso.types import VEL_CUTOFF_HZ

_BUFFER_SIZE = 6 * 1024


@dataclass(frozen=True, slots=True)
class MocapConfig:
    """Motion-capture constants (sources in the module docstring). ``noise=False`` turns the
    noise off (the pipeline, latency and velocity filter stay)."""

    rate_hz: float = 100.0
    latency_s: float = 0.010
    pos_noise_std_m: float = 0.001
    att_noise_std_rad: float = math.radians(0.1)
    vel_cutoff_hz: float = VEL_CUTOFF_HZ
    noise: bool = True


NOISELESS_MOCAP = MocapConfig(noise=False)


@dataclass(frozen=True, slots=True)
class MocapSample:
    """One processed sample: time it describes (s), position (m, ENU), filtered velocity (m/s,
    ENU) and ZYX Euler angles (rad), as plain floats."""

    t_s: float
    pos_enu_m: tuple[float, float, float]
    vel_enu_mps: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


class MocapFilter:
    """Turns true poses at the sample instants into noisy samples with filtered velocity."""

    __slots__ = ("_cfg", "_rng", "_buf", "_i", "_prev_pos", "_vel", "_a", "_period_s")

    def __init__(self, config: MocapConfig, rng: np.random.Generator) -> None:
        self._cfg = config
        self._rng = rng
        self._buf: list[float] = []
        self._i = 0
        self._period_s = 1.0 / config.rate_hz
        self._a = math.exp(-2.0 * math.pi * config.vel_cutoff_hz * self._period_s)
        self._prev_pos: tuple[float, float, float] | None = None
        self._vel = [0.0, 0.0, 0.0]

    def copy(self) -> "MocapFilter":
        """An independent filter in this one's state (same noise stream from here on)."""
        twin = object.__new__(MocapFilter)
        for name in MocapFilter.__slots__:
            setattr(twin, name, getattr(self, name))
        twin._rng = copy.deepcopy(self._rng)
        twin._vel = list(self._vel)
        return twin

    def reset(self, vel_enu_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        """Forget the previous sample; the velocity filter starts at ``vel_enu_mps``."""
        self._prev_pos = None
        self._vel = list(vel_enu_mps)

    def sample(
        self, t_s: float, pos: tuple[float, float, float], rpy: tuple[float, float, float]
    ) -> MocapSample:
        cfg = self._cfg
        if cfg.noise:
            i = self._i
            if i + 6 > len(self._buf):
                self._buf = self._rng.standard_normal(_BUFFER_SIZE).tolist()
                i = 0
            n = self._buf
            sp, sa = cfg.pos_noise_std_m, cfg.att_noise_std_rad
            p = (pos[0] + sp * n[i], pos[1] + sp * n[i + 1], pos[2] + sp * n[i + 2])
            att = (rpy[0] + sa * n[i + 3], rpy[1] + sa * n[i + 4], rpy[2] + sa * n[i + 5])
            self._i = i + 6
        else:
            p = (pos[0], pos[1], pos[2])
            att = (rpy[0], rpy[1], rpy[2])
        v = self._vel
        if self._prev_pos is not None:
            a = self._a
            inv = (1.0 - a) / self._period_s
            q = self._prev_pos
            v[0] = a * v[0] + inv * (p[0] - q[0])
            v[1] = a * v[1] + inv * (p[1] - q[1])
            v[2] = a * v[2] + inv * (p[2] - q[2])
        self._prev_pos = p
        return MocapSample(t_s, p, (v[0], v[1], v[2]), att[0], att[1], att[2])
