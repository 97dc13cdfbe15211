"""Rotor aerodynamics that depend on speed and thrust, beyond the linear rotor drag.

Three kinds of part, each a template with a null implementation and a registry by name (as
``sim.ground_effect``); ``sim.quadrotor`` evaluates them in its sub-step with plain floats:

- ``RotorDragScaling``: factor on the linear rotor-drag coefficients (``QuadrotorParams.
  drag_coeff_per_s``, identified at hover) as the rotors' thrust moves away from hover.
- ``TranslationalLift``: extra thrust along body z from edgewise flow through the rotors.
- ``GroundEffectWashout``: how edgewise flow weakens the ground effect.

Scaling to this vehicle goes through the hover induced velocity of one rotor (momentum theory,
``hover_induced_velocity_mps``): v_h = sqrt(T_h / (2 rho A)) with T_h = m g / 4 and A = pi R^2.
Edgewise effects are functions of V / v_h, so a constant identified on a reference vehicle
(v_h,ref) is carried over at equal V / v_h.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

ISA_SEA_LEVEL_AIR_DENSITY_KGPM3 = 1.225  # ISO 2533:1975


def hover_induced_velocity_mps(mass_kg: float, rotor_radius_m: float, *, rotors: int = 4,
                               gravity_mps2: float = 9.81,
                               air_density_kgpm3: float = ISA_SEA_LEVEL_AIR_DENSITY_KGPM3) -> float:
    """Momentum-theory induced velocity (m/s) of one rotor of a hovering multirotor:
    sqrt(m g / (2 rho n pi R^2)). This vehicle (1.05 kg, R 0.0635 m): 9.11 m/s."""
    return math.sqrt(mass_kg * gravity_mps2 / (2.0 * air_density_kgpm3 * rotors * math.pi * rotor_radius_m**2))


# ---------------------------------------------------------------------------------- rotor drag
class RotorDragScaling:
    """Template: the factor on the hover-identified linear rotor-drag coefficients, from the four
    rotor thrusts ``f0..f3`` (N, out of ground effect: the rotor speed sets the drag) and the
    per-rotor hover thrust ``f_hover_n``. 1 at hover."""

    name = "template"

    def factor(self, f0: float, f1: float, f2: float, f3: float, f_hover_n: float) -> float:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class ConstantRotorDrag(RotorDragScaling):
    """Coefficients independent of thrust: the linear model of Faessler, Franchi, Scaramuzza
    (RA-L 2018, eq. 2), whose coefficients are identified as constants."""

    name = "constant"

    def factor(self, f0: float, f1: float, f2: float, f3: float, f_hover_n: float) -> float:
        return 1.0


@dataclass(frozen=True, slots=True)
class RotorSpeedDrag(RotorDragScaling):
    """Rotor drag (induced drag + blade flapping, the "H force") proportional to each rotor's
    speed: H_i = -omega_i k_d v (Mahony, Kumar, Corke, IEEE RAM 2012; Svacha, Mohta, Kumar,
    ICUAS 2017; RotorPy's ``H = -rotor_speeds * (rotor_drag_matrix @ local_airspeeds)``). With
    T_i = k_eta omega_i^2 the factor is mean_i sqrt(T_i / T_hover). No constant of its own: the
    coefficient at hover stays the identified one."""

    name = "rotor_speed"

    def factor(self, f0: float, f1: float, f2: float, f3: float, f_hover_n: float) -> float:
        s = (math.sqrt(f0 if f0 > 0.0 else 0.0) + math.sqrt(f1 if f1 > 0.0 else 0.0)
             + math.sqrt(f2 if f2 > 0.0 else 0.0) + math.sqrt(f3 if f3 > 0.0 else 0.0))
        return 0.25 * s / math.sqrt(f_hover_n)


@dataclass(frozen=True, slots=True)
class ThrustProportionalDrag(RotorDragScaling):
    """First-order drag proportional to the collective thrust (Kai, Hamel, Samson 2017: the
    drag force is -T D v): factor = sum_i T_i / (4 T_hover). No constant of its own."""

    name = "thrust"

    def factor(self, f0: float, f1: float, f2: float, f3: float, f_hover_n: float) -> float:
        return 0.25 * (f0 + f1 + f2 + f3) / f_hover_n


ROTOR_DRAG_SCALINGS: dict[str, Callable[..., RotorDragScaling]] = {
    "constant": ConstantRotorDrag,
    "rotor_speed": RotorSpeedDrag,
    "thrust": ThrustProportionalDrag,
}


# ---------------------------------------------------------------------------- translational lift
class TranslationalLift:
    """Template: mass-normalised extra thrust (m/s^2, along body z) per (m/s)^2 of body-horizontal
    air speed, ``k_h_per_m(v_h_mps)`` for a vehicle whose rotors' hover induced velocity is
    ``v_h_mps``: a_lift = k_h (v_bx^2 + v_by^2)."""

    name = "template"

    def k_h_per_m(self, v_h_mps: float) -> float:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class NoTranslationalLift(TranslationalLift):
    """Thrust independent of edgewise speed (k_h = 0)."""

    name = "none"

    def k_h_per_m(self, v_h_mps: float) -> float:
        return 0.0


@dataclass(frozen=True, slots=True)
class FaesslerTranslationalLift(TranslationalLift):
    """The thrust model of Faessler, Franchi, Scaramuzza (RA-L 2018, eq. 5): the collective
    mass-normalised thrust exceeds the commanded one by k_h (v.x_B)^2 + (v.y_B)^2, k_h = 0.009
    1/m identified (Sec. VII-C) on their ~0.6 kg quadrotor with 5-inch rotors (``ref_mass_kg``
    0.6, the mass set in their controller's released configuration, 0.592 kg,
    rpg_quadrotor_control sbus_bridge; ``ref_rotor_radius_m`` 0.0635).

    Scaled to another vehicle at equal V / v_h: momentum theory makes the relative thrust change
    a function of V / v_h, so a = g kappa (V / v_h)^2 and k_h = k_h,ref (v_h,ref / v_h)^2.
    """

    name = "faessler"
    k_h_ref_per_m: float = 0.009
    ref_mass_kg: float = 0.6
    ref_rotor_radius_m: float = 0.0635

    def k_h_per_m(self, v_h_mps: float) -> float:
        v_ref = hover_induced_velocity_mps(self.ref_mass_kg, self.ref_rotor_radius_m)
        return self.k_h_ref_per_m * (v_ref / v_h_mps) ** 2


TRANSLATIONAL_LIFT_MODELS: dict[str, Callable[..., TranslationalLift]] = {
    "none": NoTranslationalLift,
    "faessler": FaesslerTranslationalLift,
}


# ------------------------------------------------------------------------ ground-effect washout
class GroundEffectWashout:
    """Template: ``weight(V^2, v_h)``, the weight w in (0, 1] on the ground-effect "image
    strength" at body-horizontal air speed V (m/s) for a rotor of hover induced velocity v_h. A ground-effect ratio r becomes
    1 / (1 - (1 - 1/r) w): w = 1 leaves it unchanged, w -> 0 removes it."""

    name = "template"

    def weight(self, speed_sq_m2ps2: float, v_h_mps: float) -> float:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class NoWashout(GroundEffectWashout):
    """Ground effect independent of forward speed."""

    name = "none"

    def weight(self, speed_sq_m2ps2: float, v_h_mps: float) -> float:
        return 1.0


@dataclass(frozen=True, slots=True)
class CheesemanBennettWashout(GroundEffectWashout):
    """Cheeseman & Bennett (ARC R&M 3021, 1955), forward flight: the image term (R/4z)^2 is
    divided by 1 + (V/v_i)^2, i.e. T/T_inf = 1 / (1 - (R/4z)^2 / (1 + (V/v_i)^2)); here applied
    to any ground-effect model through its image strength 1 - 1/r, with v_i the hover induced
    velocity. Reproduces their formula exactly for the ``cheeseman_bennett`` model."""

    name = "cheeseman_bennett"

    def weight(self, speed_sq_m2ps2: float, v_h_mps: float) -> float:
        return 1.0 / (1.0 + speed_sq_m2ps2 / (v_h_mps * v_h_mps))


GROUND_EFFECT_WASHOUTS: dict[str, Callable[..., GroundEffectWashout]] = {
    "none": NoWashout,
    "cheeseman_bennett": CheesemanBennettWashout,
}


def washed_out_ratio(ratio: float, weight: float) -> float:
    """A ground-effect ratio with its image strength weighted by ``weight``."""
    return 1.0 / (1.0 - (1.0 - 1.0 / ratio) * weight)


def make_rotor_aero(kind: str, name: str, **kwargs: float):
    """Build a registered part: ``kind`` is ``rotor_drag``, ``translational_lift`` or
    ``washout``; unknown names raise ``KeyError`` with the known ones."""
    registries = {"rotor_drag": ROTOR_DRAG_SCALINGS, "translational_lift": TRANSLATIONAL_LIFT_MODELS,
                  "washout": GROUND_EFFECT_WASHOUTS}
    if kind not in registries:
        raise KeyError(f"unknown kind {kind!r}; known: {sorted(registries)}")
    try:
        factory = registries[kind][name]
    except KeyError:
        raise KeyError(f"unknown {kind} model {name!r}; known: {sorted(registries[kind])}") from None
    return factory(**kwargs)
