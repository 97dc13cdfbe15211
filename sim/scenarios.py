"""Scenario registry: name -> function returning a ``SimConfig`` (paper Section V, in simulation).

- ``nominal_landing`` (Experiment 1): flat ground, exponential ground effect, mild turbulence,
  start hovering at (0, 0, 1.0) m; the landing target is 0.1 m (the paper's minimum altitude,
  set by the protective frame).
- ``nominal_landing_noiseless``: the same with noise-free motion capture (the noise-free case).
- ``ood_slope`` (Experiment 2): the same plus a 30 deg ramp whose edge is 0.10 m beside the
  landing point, so two rotors are partly over it at 0.1 m.
- ``lemniscate_near_ground`` (Experiment 3): flat ground, strong speed-dependent near-ground
  turbulence, start hovering at (0, 0, 0.3) m; ``reference_height_m`` 0.25 m (the experiment
  code chooses the actual reference).

``make_scenario(name, **overrides)`` applies ``dataclasses.replace`` overrides to the config.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable

from sim.ground_effect import ExponentialGroundEffect
from sim.mocap import NOISELESS_MOCAP, MocapConfig
from sim.quadrotor import SimConfig
from sim.terrain import FlatGround, SlopeTerrain
from sim.turbulence import MILD_TURBULENCE, STRONG_NEAR_GROUND_TURBULENCE


def nominal_landing() -> SimConfig:
    return SimConfig(
        ground_effect=ExponentialGroundEffect(),
        terrain=FlatGround(),
        turbulence=MILD_TURBULENCE,
        mocap=MocapConfig(),
        initial_pos_enu_m=(0.0, 0.0, 1.0),
        reference_height_m=0.1,
        name="nominal_landing",
    )


def nominal_landing_noiseless() -> SimConfig:
    """Experiment 1 with noise-free motion capture (its latency and velocity filter stay): what is left is
    the method's own behaviour (the paper's input shows a limit cycle here, docs/method.md)."""
    return replace(nominal_landing(), mocap=NOISELESS_MOCAP, name="nominal_landing_noiseless")


def ood_slope() -> SimConfig:
    return replace(nominal_landing(), terrain=SlopeTerrain(), name="ood_slope")


def lemniscate_near_ground() -> SimConfig:
    return SimConfig(
        ground_effect=ExponentialGroundEffect(),
        terrain=FlatGround(),
        turbulence=STRONG_NEAR_GROUND_TURBULENCE,
        mocap=MocapConfig(),
        initial_pos_enu_m=(0.0, 0.0, 0.3),
        reference_height_m=0.25,
        name="lemniscate_near_ground",
    )


SCENARIOS: dict[str, Callable[[], SimConfig]] = {
    "nominal_landing": nominal_landing,
    "nominal_landing_noiseless": nominal_landing_noiseless,
    "ood_slope": ood_slope,
    "lemniscate_near_ground": lemniscate_near_ground,
}


def make_scenario(name: str, **overrides: Any) -> SimConfig:
    """The registered scenario ``name`` with ``SimConfig`` fields replaced by ``overrides``."""
    try:
        factory = SCENARIOS[name]
    except KeyError:
        raise KeyError(f"unknown scenario {name!r}; known: {sorted(SCENARIOS)}") from None
    return replace(factory(), **overrides)
