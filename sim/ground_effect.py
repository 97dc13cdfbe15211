"""Ground-effect models: per-rotor thrust ratio T_IGE / T_OGE as a function of the rotor's height.

Every model is a small frozen dataclass with ``thrust_ratio(height_m, rotor_radius_m,
arm_length_m) -> float`` (>= 1, -> 1 far from the ground, finite down to the ground). ``height_m``
is the ROTOR's perpendicular distance (m) to the terrain surface below it (``sim.terrain``), so
a vehicle partly over a slope gets different ratios on different rotors: the total thrust changes
and a torque appears (``sim.quadrotor`` applies the ratios per rotor). ``GROUND_EFFECT_MODELS``
is the registry by name; ``make_ground_effect(name, **kwargs)`` builds one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable


class GroundEffectModel:
    """Template: a per-rotor thrust ratio T_IGE/T_OGE (dimensionless, >= 1)."""

    name = "template"

    def thrust_ratio(self, height_m: float, rotor_radius_m: float, arm_length_m: float) -> float:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class NoGroundEffect(GroundEffectModel):
    """Out of ground effect everywhere (ratio 1)."""

    name = "none"

    def thrust_ratio(self, height_m: float, rotor_radius_m: float, arm_length_m: float) -> float:
        return 1.0


@dataclass(frozen=True, slots=True)
class ExponentialGroundEffect(GroundEffectModel):
    """Default: ``1 + gain * exp(-h / length_m)``.

    Source: DESIGN.md's fit to Neural-Lander's (Shi et al., ICRA 2019) real-flight ground-effect
    network, ``Delta T / (m g) ~ 0.215 exp(-h / 0.195 m)``; it reaches ~0.5 m, unlike
    Cheeseman-Bennett which decays within ~2 rotor radii. Applied per rotor with the rotor's
    height. Heights below ``min_height_m`` (1 cm) are clamped.
    """

    name = "exponential"
    gain: float = 0.215
    length_m: float = 0.195
    min_height_m: float = 0.01

    def thrust_ratio(self, height_m: float, rotor_radius_m: float, arm_length_m: float) -> float:
        h = height_m if height_m > self.min_height_m else self.min_height_m
        return 1.0 + self.gain * math.exp(-h / self.length_m)


@dataclass(frozen=True, slots=True)
class CheesemanBennettGroundEffect(GroundEffectModel):
    """Single-rotor image model ``1 / (1 - (R / 4h)^2)``.

    Source: Cheeseman & Bennett, ARC R&M 3021 (1955). Singular at h = R/4; experimentally valid
    for h/R >= 0.5, so heights are clamped to ``min_height_over_radius * R`` (0.5: ratio <= 4/3).
    """

    name = "cheeseman_bennett"
    min_height_over_radius: float = 0.5

    def thrust_ratio(self, height_m: float, rotor_radius_m: float, arm_length_m: float) -> float:
        h_min = self.min_height_over_radius * rotor_radius_m
        h = height_m if height_m > h_min else h_min
        q = rotor_radius_m / (4.0 * h)
        return 1.0 / (1.0 - q * q)


@dataclass(frozen=True, slots=True)
class SanchezCuevasGroundEffect(GroundEffectModel):
    """Multirotor ground effect with neighbouring-rotor images and body lift (fountain effect).

    Source: Sanchez-Cuevas, Heredia, Ollero, "Characterization of the Aerodynamic Ground Effect
    and Its Influence in Multirotor Control", Int. J. Aerospace Eng. 2017, eq. (4)::

        T_IGE/T_OGE = 1 / (1 - (R/4z)^2 - R^2 z / (d^2 + 4z^2)^{3/2}
                             - (R^2/2) z / (2 d^2 + 4z^2)^{3/2}
                             - 2 R^2 z / (b^2 + 4z^2)^{3/2} * K_b)

    with R the rotor radius, d the distance between adjacent rotors (= sqrt(2) * arm for an X
    quad), b the rotor-to-body-centre distance (= arm) and K_b ~ 2 the empirical body-lift
    coefficient identified in the paper. Applied per rotor with that rotor's own height ``z``
    (partial ground effect approximated by evaluating all image terms at the rotor's height).
    Heights are clamped to ``min_height_over_radius * R`` (0.5) and the denominator to >= 0.2
    (ratio <= 5) so the model stays finite at touchdown.
    """

    name = "sanchez_cuevas"
    k_b: float = 2.0
    min_height_over_radius: float = 0.5
    min_denominator: float = 0.2

    def thrust_ratio(self, height_m: float, rotor_radius_m: float, arm_length_m: float) -> float:
        r = rotor_radius_m
        h_min = self.min_height_over_radius * r
        z = height_m if height_m > h_min else h_min
        b = arm_length_m
        d2 = 2.0 * b * b
        z4 = 4.0 * z * z
        q = r / (4.0 * z)
        den = (
            1.0
            - q * q
            - r * r * z / (d2 + z4) ** 1.5
            - 0.5 * r * r * z / (2.0 * d2 + z4) ** 1.5
            - 2.0 * r * r * z / (b * b + z4) ** 1.5 * self.k_b
        )
        if den < self.min_denominator:
            den = self.min_denominator
        return 1.0 / den


GROUND_EFFECT_MODELS: dict[str, Callable[..., GroundEffectModel]] = {
    "exponential": ExponentialGroundEffect,
    "cheeseman_bennett": CheesemanBennettGroundEffect,
    "sanchez_cuevas": SanchezCuevasGroundEffect,
    "none": NoGroundEffect,
}


def make_ground_effect(name: str, **kwargs: float) -> GroundEffectModel:
    """Build a registered ground-effect model by name; unknown names raise ``KeyError``."""
    try:
        factory = GROUND_EFFECT_MODELS[name]
    except KeyError:
        raise KeyError(f"unknown ground-effect model {name!r}; known: {sorted(GROUND_EFFECT_MODELS)}") from None
    return factory(**kwargs)
