"""Missions: operator commands turned into a continuous reference (ENU, m, s).

Commands: ``takeoff`` (straight up to ``takeoff_height_m``), ``hover`` (hold the current
reference), ``landing_test`` (the paper's Experiment 1 at the arena origin: from
``landing_start_height_m`` descend to ``landing_end_height_m`` and hold), ``lemniscate``
(Experiment 3's figure eight around the origin at ``lemniscate_height_m``), ``land`` (down to
the ground, then idle). A segment that starts away from where the reference is goes there
first with a quintic transit, so the reference never jumps. Time is the state source's
clock; a command takes effect at the sample it is applied to.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from neso.certificate import ReferenceBounds
from neso.trajectories import Landing, Lemniscate
from neso.types import Reference

COMMANDS = ("takeoff", "hover", "landing_test", "lemniscate", "land")


@dataclass(frozen=True, slots=True)
class MissionConfig:
    """Where missions fly. ``origin_xy_m``: the arena point the tests happen over."""

    origin_xy_m: tuple[float, float] = (0.0, 0.0)
    takeoff_height_m: float = 1.0
    landing_start_height_m: float = 1.0
    landing_end_height_m: float = 0.1
    lemniscate_height_m: float = 0.25
    lemniscate_cycles: int = 5
    transit_speed_mps: float = 0.4  # mean speed of a transit or take-off
    land_speed_mps: float = 0.3
    min_transit_s: float = 1.0  # a transit, take-off or land never takes less
    at_point_tol_m: float = 0.02  # closer than this, no transit is flown
    landed_height_m: float = 0.04  # measured height under which a landing is complete
    # ... or: the land reference has been on the floor this long and the vehicle is this low (a vehicle
    # rests on its feet: the simulated one's body origin at 0.05 m, above landed_height_m)
    landed_settle_s: float = 1.0
    landed_max_height_m: float = 0.15


@dataclass(frozen=True, slots=True)
class _Transit:
    """Quintic straight line from ``a`` to ``b`` over ``duration_s``, then hold ``b``."""

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    duration_s: float

    def sample(self, t_s: float) -> Reference:
        s = min(1.0, max(0.0, t_s / self.duration_s))
        p = s**3 * (10 - 15 * s + 6 * s * s)
        dp = 30 * s * s * (1 - s) ** 2 / self.duration_s
        ddp = 60 * s * (1 - s) * (1 - 2 * s) / self.duration_s**2
        a, d = np.array(self.a), np.array(self.b) - np.array(self.a)
        return Reference(pos_enu_m=a + d * p, vel_enu_mps=d * dp, acc_enu_mps2=d * ddp)


@dataclass(frozen=True, slots=True)
class _Offset:
    """``trajectory`` translated by ``offset_m`` (its sample at time 0 sits there)."""

    trajectory: object
    offset_m: tuple[float, float, float]

    def sample(self, t_s: float) -> Reference:
        r = self.trajectory.sample(t_s)
        return Reference(pos_enu_m=r.pos_enu_m + np.array(self.offset_m), vel_enu_mps=r.vel_enu_mps,
                         acc_enu_mps2=r.acc_enu_mps2, yaw_rad=r.yaw_rad)


@dataclass(frozen=True, slots=True)
class _Hold:
    pos_enu_m: tuple[float, float, float]

    def sample(self, t_s: float) -> Reference:
        return Reference(pos_enu_m=np.array(self.pos_enu_m))


@dataclass(slots=True)
class _Segment:
    name: str
    trajectory: object
    start_s: float
    duration_s: float  # math.inf: holds until replaced


@dataclass
class Mission:
    """The reference generator: :meth:`command` queues segments, :meth:`reference` samples."""

    config: MissionConfig = field(default_factory=MissionConfig)
    idle: bool = True  # on the ground, motors idle: no reference to track
    _segments: list[_Segment] = field(default_factory=list)
    _last: Reference | None = None
    segment: str = "idle"

    def start(self, name: str, t_s: float, pos_enu_m: np.ndarray, *, from_position: bool = False,
              cycles: int | None = None) -> None:
        """Begin command ``name`` at ``t_s`` from the current reference, or from the vehicle's
        position ``pos_enu_m`` when nothing was tracked yet or ``from_position``. ``cycles``: the lemniscate's
        (None: ``lemniscate_cycles``)."""
        if name not in COMMANDS:
            raise ValueError(f"unknown mission command {name!r}; choose one of {COMMANDS}")
        c = self.config
        tracked = self._last is not None and not self.idle and not from_position
        here = tuple(float(v) for v in (self._last.pos_enu_m if tracked else pos_enu_m))
        ox, oy = c.origin_xy_m
        self._segments = []
        self.idle = False
        if name == "hover":
            self._append("hover", _Hold(here), t_s, math.inf)
        elif name == "takeoff":
            top = (here[0], here[1], c.takeoff_height_m)
            t = self._transit("takeoff", here, top, t_s)
            self._append("hover", _Hold(top), t, math.inf)
        elif name == "landing_test":
            start = (ox, oy, c.landing_start_height_m)
            t = self._transit("transit", here, start, t_s)
            landing = Landing(start_height_m=c.landing_start_height_m, end_height_m=c.landing_end_height_m,
                              xy_m=(ox, oy))
            self._append("landing_test", landing, t, landing.duration_s)
            self._append("hover", _Hold((ox, oy, c.landing_end_height_m)), t + landing.duration_s, math.inf)
        elif name == "lemniscate":
            start = (ox, oy, c.lemniscate_height_m)
            t = self._transit("transit", here, start, t_s)
            lem = Lemniscate(height_m=c.lemniscate_height_m, cycles=c.lemniscate_cycles if cycles is None else cycles)
            self._append("lemniscate", _Offset(lem, (ox, oy, 0.0)), t, lem.duration_s)
            self._append("hover", _Hold(start), t + lem.duration_s, math.inf)
        elif name == "land":
            ground = (here[0], here[1], -0.05)  # a little below the floor so contact is certain
            duration = max(c.min_transit_s, (here[2] - ground[2]) / c.land_speed_mps)
            self._append("land", _Transit(here, ground, duration), t_s, math.inf)

    def hold(self, t_s: float, pos_enu_m: np.ndarray) -> bool:
        """Stop where the vehicle is: from ``t_s`` the reference holds the measured ``pos_enu_m``
        (segment ``hold``), forgetting the old reference. False (nothing done) while idle."""
        if self.idle:
            return False
        self._segments = []
        self._append("hold", _Hold(tuple(float(v) for v in pos_enu_m)), t_s, math.inf)
        return True

    def abort(self, t_s: float, pos_enu_m: np.ndarray) -> bool:
        """Land now from where the vehicle is (``pos_enu_m``), not from the reference. False while idle."""
        if self.idle:
            return False
        self.start("land", t_s, pos_enu_m, from_position=True)
        return True

    def _append(self, name: str, trajectory, start_s: float, duration_s: float) -> None:
        self._segments.append(_Segment(name, trajectory, start_s, duration_s))

    def _transit(self, name: str, a: tuple, b: tuple, t_s: float) -> float:
        """Queue a transit a → b if they differ; the time it ends."""
        distance = math.dist(a, b)
        if distance <= self.config.at_point_tol_m:
            return t_s
        duration = max(self.config.min_transit_s, distance / self.config.transit_speed_mps)
        self._append(name, _Transit(a, b, duration), t_s, duration)
        return t_s + duration

    def reference(self, t_s: float) -> Reference | None:
        """The reference at ``t_s``; ``None`` while idle."""
        if self.idle or not self._segments:
            self.segment = "idle"
            return None
        current = self._segments[0]
        for seg in self._segments:
            if seg.start_s <= t_s:
                current = seg
        self.segment = current.name
        self._last = current.trajectory.sample(t_s - current.start_s)
        return self._last

    def landed(self, measured_height_m: float, t_s: float = -math.inf) -> bool:
        """True once a ``land`` reached the floor: the measured height (m) is below
        ``landed_height_m``, or at ``t_s`` the land reference has been on the floor for
        ``landed_settle_s`` and the vehicle is below ``landed_max_height_m`` (resting on its
        feet). The caller idles the motors."""
        if self.segment != "land":
            return False
        c, seg = self.config, self._segments[0]
        settled = t_s >= seg.start_s + seg.trajectory.duration_s + c.landed_settle_s
        if measured_height_m < c.landed_height_m or (settled and measured_height_m < c.landed_max_height_m):
            self.idle, self._segments, self.segment = True, [], "idle"
            return True
        return False


# The quintic 0→1 over unit time (neso.trajectories' smoothstep and the transits'): its largest speed, acceleration
# and jerk are 15/8, 10/√3 and 60 (at s = 1/2, s = 1/2 ∓ √3/6, and the ends)
_QUINTIC_PEAKS = (15.0 / 8.0, 10.0 / math.sqrt(3.0), 60.0)


def _quintic_bounds(distance_m: float, duration_s: float) -> ReferenceBounds:
    v, a, j = _QUINTIC_PEAKS
    return ReferenceBounds(v * distance_m / duration_s, a * distance_m / duration_s ** 2, j * distance_m / duration_s ** 3)


def _steepest_transit(speed_mps: float, min_duration_s: float) -> ReferenceBounds:
    """The largest z derivatives of any transit at ``speed_mps`` mean speed over at least ``min_duration_s`` (the
    distance ``speed × min_duration`` is the steepest: shorter ones are slower, longer ones take longer)."""
    return _quintic_bounds(speed_mps * min_duration_s, min_duration_s)


def segment_reference_bounds(config: MissionConfig = MissionConfig()) -> dict[str, ReferenceBounds]:
    """Bounds on the z reference's speed (m/s), acceleration (m/s²) and jerk (m/s³) in each mission segment flown
    with ``config`` (the names :attr:`Mission.segment` reports): the stability certificate states its |e_z| bound
    for the segment being flown (:meth:`neso.certificate.FlightCertificate.bound_for_cm`)."""
    c = config
    landing = Landing(start_height_m=c.landing_start_height_m, end_height_m=c.landing_end_height_m)
    still = ReferenceBounds()
    transit = _steepest_transit(c.transit_speed_mps, c.min_transit_s)
    return {"idle": still, "hover": still, "hold": still, "lemniscate": still,  # the figure eight is flat in z
            "takeoff": transit, "transit": transit,
            "landing_test": _quintic_bounds(abs(landing.start_height_m - landing.end_height_m), landing.descent_s),
            "land": _steepest_transit(c.land_speed_mps, c.min_transit_s)}
