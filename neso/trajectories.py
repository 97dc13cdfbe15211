"""Reference trajectories with their first two derivatives (ENU, metres, seconds).

Each trajectory is a plain object with ``sample(t_s) -> Reference`` and a ``duration_s``
(after which it holds its final value). Registered by name in :data:`TRAJECTORIES`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from neso.types import Reference


def _smoothstep5(s: float) -> tuple[float, float, float]:
    """Quintic 0→1 on s ∈ [0, 1] with zero first and second derivative at both ends: (p, p', p'')."""
    s = min(1.0, max(0.0, s))
    p = s**3 * (10 - 15 * s + 6 * s * s)
    dp = 30 * s * s * (1 - s) ** 2
    ddp = 60 * s * (1 - s) * (1 - 2 * s)
    return p, dp, ddp


@dataclass(frozen=True, slots=True)
class Hover:
    pos_enu_m: tuple[float, float, float] = (0.0, 0.0, 1.0)
    duration_s: float = 10.0

    def sample(self, t_s: float) -> Reference:
        return Reference(pos_enu_m=np.array(self.pos_enu_m, dtype=float))


@dataclass(frozen=True, slots=True)
class Landing:
    """Hold at ``start_height_m`` for ``hold_before_s``, descend smoothly (quintic) to
    ``end_height_m`` over ``descent_s``, then hold for ``hold_after_s`` (paper Exp. 1:
    the protective frame limits the lowest altitude to about 0.1 m)."""

    start_height_m: float = 1.0
    end_height_m: float = 0.1
    hold_before_s: float = 1.0
    descent_s: float = 4.0
    hold_after_s: float = 6.0
    xy_m: tuple[float, float] = (0.0, 0.0)

    @property
    def duration_s(self) -> float:
        return self.hold_before_s + self.descent_s + self.hold_after_s

    @property
    def descent_end_s(self) -> float:
        return self.hold_before_s + self.descent_s

    def sample(self, t_s: float) -> Reference:
        p, dp, ddp = _smoothstep5((t_s - self.hold_before_s) / self.descent_s)
        dz = self.end_height_m - self.start_height_m
        return Reference(
            pos_enu_m=np.array([self.xy_m[0], self.xy_m[1], self.start_height_m + dz * p]),
            vel_enu_mps=np.array([0.0, 0.0, dz * dp / self.descent_s]),
            acc_enu_mps2=np.array([0.0, 0.0, dz * ddp / self.descent_s**2]),
        )


@dataclass(frozen=True, slots=True)
class Lemniscate:
    """Figure-eight x = A_x sin φ, y = A_y sin 2φ at constant ``height_m`` (paper Exp. 3:
    A_x 0.8 m, A_y 1.0 m, period 6 s). The phase rate ramps from 0 to 2π/T over
    ``ramp_s`` with a quintic so the vehicle starts from hover; ``cycles`` full periods
    follow the ramp. ``cycle_start_s`` is when the first full cycle begins."""

    amplitude_x_m: float = 0.8
    amplitude_y_m: float = 1.0
    period_s: float = 6.0
    height_m: float = 0.25
    cycles: int = 5
    ramp_s: float = 3.0

    @property
    def cycle_start_s(self) -> float:
        return self.ramp_s

    @property
    def duration_s(self) -> float:
        return self.ramp_s + self.cycles * self.period_s

    def _phase(self, t_s: float) -> tuple[float, float, float]:
        w = 2 * math.pi / self.period_s
        if t_s >= self.ramp_s:
            # ∫0^1 smoothstep5 = 1/2, so the ramp covers ω·ramp/2 of phase
            return w * self.ramp_s / 2 + w * (t_s - self.ramp_s), w, 0.0
        s = max(0.0, t_s) / self.ramp_s
        p, dp, _ = _smoothstep5(s)
        integral = s**4 * (2.5 - 3 * s + s * s)  # ∫0^s of the quintic
        return w * self.ramp_s * integral, w * p, w * dp / self.ramp_s

    def sample(self, t_s: float) -> Reference:
        phi, dphi, ddphi = self._phase(min(t_s, self.duration_s))
        ax, ay = self.amplitude_x_m, self.amplitude_y_m
        pos = np.array([ax * math.sin(phi), ay * math.sin(2 * phi), self.height_m])
        vel = np.array([ax * math.cos(phi) * dphi, 2 * ay * math.cos(2 * phi) * dphi, 0.0])
        acc = np.array(
            [
                -ax * math.sin(phi) * dphi**2 + ax * math.cos(phi) * ddphi,
                -4 * ay * math.sin(2 * phi) * dphi**2 + 2 * ay * math.cos(2 * phi) * ddphi,
                0.0,
            ]
        )
        return Reference(pos_enu_m=pos, vel_enu_mps=vel, acc_enu_mps2=acc)


@dataclass(frozen=True, slots=True)
class Dithered:
    """``base`` with a small z dither added: a sum of sines of ``amplitude_m`` each at ``frequencies_hz``, faded in
    over ``fade_s`` (smoothly: its speed and acceleration start at 0). An excitation of the height the
    disturbance does not cause, for data-collection flights: a regression on the reference then sees the
    disturbance's dependence on height (issue 32). ``duration_s`` and ``cycle_start_s`` are the base's."""

    base: object
    amplitude_m: float = 0.04
    frequencies_hz: tuple[float, ...] = (0.23, 0.61)
    fade_s: float = 2.0

    @property
    def duration_s(self) -> float:
        return self.base.duration_s

    @property
    def cycle_start_s(self) -> float:
        return getattr(self.base, "cycle_start_s", 0.0)

    def sample(self, t_s: float) -> Reference:
        r = self.base.sample(t_s)
        g, dg, ddg = _smoothstep5(t_s / self.fade_s)
        dg, ddg = dg / self.fade_s, ddg / self.fade_s ** 2
        z = dz = ddz = 0.0
        for f in self.frequencies_hz:
            w = 2 * math.pi * f
            s, c = math.sin(w * t_s), math.cos(w * t_s)
            z += self.amplitude_m * s
            dz += self.amplitude_m * w * c
            ddz -= self.amplitude_m * w * w * s
        pos, vel, acc = r.pos_enu_m.copy(), r.vel_enu_mps.copy(), r.acc_enu_mps2.copy()
        pos[2] += g * z
        vel[2] += g * dz + dg * z
        acc[2] += g * ddz + 2 * dg * dz + ddg * z
        return Reference(pos_enu_m=pos, vel_enu_mps=vel, acc_enu_mps2=acc, yaw_rad=r.yaw_rad)


TRAJECTORIES = {"hover": Hover, "landing": Landing, "lemniscate": Lemniscate}
