"""Terrain: flat ground at z = 0, and a slope (inclined ramp) beside the landing spot.

World frame ENU, metres. ``height_m(x, y)`` is the terrain height under a point;
``distance_m(x, y, z)`` is the perpendicular distance from a point to the nearest terrain
surface (negative if the point is inside the terrain). Rotor heights for the ground-effect
models are these distances evaluated at each rotor hub.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable


class Terrain:
    """Template. ``height_fn`` / ``distance_fn`` return closures for the simulator's hot path."""

    def height_fn(self) -> Callable[[float, float], float]:
        return self.height_m

    def distance_fn(self) -> Callable[[float, float, float], float]:
        return self.distance_m

    def height_m(self, x_m: float, y_m: float) -> float:
        raise NotImplementedError

    def distance_m(self, x_m: float, y_m: float, z_m: float) -> float:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class FlatGround(Terrain):
    """The floor z = 0."""

    def height_m(self, x_m: float, y_m: float) -> float:
        return 0.0

    def distance_m(self, x_m: float, y_m: float, z_m: float) -> float:
        return z_m


@dataclass(frozen=True, slots=True)
class SlopeTerrain(Terrain):
    """Flat floor plus a ramp rising at ``slope_deg`` from a straight edge.

    The edge is the line at horizontal distance ``edge_offset_m`` from the landing point
    (``landing_x_m``, ``landing_y_m``) along the azimuth ``azimuth_rad`` (0 = +x, ENU); beyond
    the edge the surface is ``z = tan(slope) * u`` with ``u`` the horizontal distance past the
    edge. Defaults (30 deg, 0.10 m) put two rotor hubs of the default vehicle (hubs at +-0.127 m)
    over the ramp when it hovers above the landing point (at 0.1 m they are 0.073 m from the
    ramp instead of 0.1 m: total ground-effect ratio 1.139 instead of 1.129, plus a pitch
    torque away from the ramp). The paper's
    Experiment 2 places "an inclined slope near the landing zone" without dimensions, so these
    are assumed. The ramp is unbounded (no plateau).
    """

    slope_deg: float = 30.0
    edge_offset_m: float = 0.10
    azimuth_rad: float = 0.0
    landing_x_m: float = 0.0
    landing_y_m: float = 0.0

    def height_fn(self) -> Callable[[float, float], float]:
        """A closure (x, y) -> terrain height (m) with the trigonometry precomputed (hot path)."""
        ca, sa = math.cos(self.azimuth_rad), math.sin(self.azimuth_rad)
        x0 = self.landing_x_m * ca + self.landing_y_m * sa + self.edge_offset_m
        tan_s = math.tan(math.radians(self.slope_deg))

        def height(x_m: float, y_m: float) -> float:
            u = x_m * ca + y_m * sa - x0
            return tan_s * u if u > 0.0 else 0.0

        return height

    def distance_fn(self) -> Callable[[float, float, float], float]:
        """A closure (x, y, z) -> perpendicular distance (m) to the nearest surface (hot path)."""
        ca, sa = math.cos(self.azimuth_rad), math.sin(self.azimuth_rad)
        x0 = self.landing_x_m * ca + self.landing_y_m * sa + self.edge_offset_m
        th = math.radians(self.slope_deg)
        c, s, tan_s = math.cos(th), math.sin(th), math.tan(th)
        hypot = math.hypot

        def distance(x_m: float, y_m: float, z_m: float) -> float:
            u = x_m * ca + y_m * sa - x0  # horizontal distance past the edge
            if u <= 0.0:
                d_flat = z_m
            else:
                d_flat = hypot(u, z_m)
            # ramp half-plane: the ray from the edge along (cos, sin) in the (u, z) plane
            if u * c + z_m * s >= 0.0:
                d_ramp = z_m * c - u * s
            else:
                d_ramp = hypot(u, z_m)
            if u > 0.0 and z_m < tan_s * u:  # inside the ramp: negative distance
                return d_ramp
            return d_flat if d_flat < d_ramp else d_ramp

        return distance

    def height_m(self, x_m: float, y_m: float) -> float:
        return self.height_fn()(x_m, y_m)

    def distance_m(self, x_m: float, y_m: float, z_m: float) -> float:
        return self.distance_fn()(x_m, y_m, z_m)


TERRAINS = {"flat": FlatGround, "slope": SlopeTerrain}
