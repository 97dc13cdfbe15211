"""The verdict for what flies: a network's slopes in each of its inputs' roles, the vehicle it flies on, and the
role certificate (:mod:`neso.certificate.roles`) turned into what an operator reads — does the loop hold, and how
far can the height error go, in centimetres, against the observer alone.

**What the certificate assumes of the flight** (:class:`CertificatePolicy`, the one place these live): the true
disturbance's rate ``|ḟ| ≤ L_1``; the z reference's speed, acceleration and jerk (the envelope every mission stays
in, ``flight.mission`` checks it); the vertical specific force ``T_z/m`` between ``min_specific_force`` and
``max_specific_force``; body rates within the inner loop's limit (PX4's ``MC_ROLLRATE_MAX`` /
``MC_PITCHRATE_MAX``, 220 °/s by default, ``src/modules/mc_rate_control/mc_rate_control_params.c``; the built-in
world's inner loop has the same limits); the measured velocity's lag (:func:`neso.types.velocity_lag_s`).

**Rates from what the vehicle can do** (:func:`exogenous_rates`): the controller saturates each component of the
force's increment at ``F'`` (``ControlConfig.force_rate_limit_nps``) and its tilt at ``θ_max``. The thrust
``T = ‖F‖`` moves at ``F̂·Ḟ``: its vertical part is ``m ĉ u̇_z`` (the loop, ``ĉ ≤ 1``), its horizontal part at most
``√2 F' sin θ_max``. The body z axis moves at ``‖Ḟ_⊥‖/‖F‖``, and ``‖(φ̇, θ̇)‖ ≤ ‖ż_b‖/cos φ`` (the ZYX derivatives
of the z axis along φ and θ are orthogonal, of lengths 1 and cos φ): the vertical force's share is
``tan θ_max / a_min`` per unit of ``u̇_z`` (the loop, ``k_att``), the horizontal force's at most
``√2 F'/(m a_min cos θ_max)``, and never more than the body-rate limit ``/ cos θ_max``. The horizontal speed
changes at most at ``a_max sin θ_max``.

**The verdict** (:func:`flight_certificate`) holds when (1) the loop through the controller's output is closed,
``K = m L_T + k_att L_att < 1``; (2) the role certificate verifies for ``L_s`` at that ``K``; (3) its eventual
bound on ``|e_z|`` over the envelope is at most ``max_bound_ratio`` × PD+ESO's (the same certificate with no
network): a network may make the worst case at most that much worse, or it is not said to fly well; (4) the
network was made for this vehicle's mass, when its inputs are in newtons (a thrust input's meaning is
``T/m``; a network without one takes nothing that scales with mass).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

from neso.certificate.core import L1_MPS3, MISSION_ACC_MAX_MPS2, MISSION_JERK_MAX_MPS3, MISSION_VEL_MAX_MPS
from neso.certificate.roles import (RoleCertificate, RoleInputs, certify_roles, error_bound_under,
                                    max_certified_state_lipschitz_verified)
from neso.types import GRAVITY_MPS2, velocity_lag_s


@dataclass(frozen=True)
class CertificatePolicy:
    """What the certificate assumes and demands (module docstring); every service and the trainer use this one.

    ``disturbance_rate_max_mps3`` ``L_1``; ``ref_*``: the z reference's envelope (m/s, m/s², m/s³);
    ``min_specific_force_mps2``/``max_specific_force_mps2``: ``T_z/m`` stays between them; ``body_rate_max_rps``:
    the inner loop's roll/pitch rate limit; ``velocity_lag_s``: the measured velocity's lag (0: exact);
    ``max_bound_ratio``: a network's eventual ``|e_z|`` bound may be at most this × PD+ESO's;
    ``mass_tolerance``: the relative mass difference a thrust-input network may be flown at."""

    disturbance_rate_max_mps3: float = L1_MPS3
    ref_vel_max_mps: float = MISSION_VEL_MAX_MPS
    ref_acc_max_mps2: float = MISSION_ACC_MAX_MPS2
    ref_jerk_max_mps3: float = MISSION_JERK_MAX_MPS3
    min_specific_force_mps2: float = 0.5 * GRAVITY_MPS2
    max_specific_force_mps2: float = 2.0 * GRAVITY_MPS2
    body_rate_max_rps: float = math.radians(220.0)
    velocity_lag_s: float = velocity_lag_s()
    max_bound_ratio: float = 2.0
    mass_tolerance: float = 0.05


POLICY = CertificatePolicy()


@dataclass(frozen=True)
class ReferenceBounds:
    """Bounds on the z reference's derivatives: ``vel_mps``, ``acc_mps2``, ``jerk_mps3``."""

    vel_mps: float = 0.0
    acc_mps2: float = 0.0
    jerk_mps3: float = 0.0

    @staticmethod
    def envelope(policy: CertificatePolicy = POLICY) -> "ReferenceBounds":
        return ReferenceBounds(policy.ref_vel_max_mps, policy.ref_acc_max_mps2, policy.ref_jerk_max_mps3)


HOVER = ReferenceBounds()


@dataclass(frozen=True)
class LoopPlant:
    """What the certificate takes of the vehicle and the controller: ``mass_kg`` (the controller's model),
    ``force_rate_limit_nps`` (per component of F, N/s), ``max_tilt_rad``."""

    mass_kg: float
    force_rate_limit_nps: float
    max_tilt_rad: float

    @staticmethod
    def of(control) -> "LoopPlant":
        """From a :class:`neso.control.ControlConfig`."""
        return LoopPlant(float(control.vehicle.mass_kg), float(control.force_rate_limit_nps), float(control.max_tilt_rad))


@dataclass(frozen=True)
class ExogenousRates:
    """``thrust_nps`` (N/s), ``attitude_rps`` (rad/s of (roll, pitch)), ``speed_mps2`` (m/s²): the most the
    exogenous parts of those inputs can move; ``attitude_per_uz`` (rad per (m/s²)): the attitude's share of the loop
    through ``u_z``."""

    thrust_nps: float
    attitude_rps: float
    speed_mps2: float
    attitude_per_uz: float


def exogenous_rates(plant: LoopPlant, policy: CertificatePolicy = POLICY) -> ExogenousRates:
    """The rate bounds of the module docstring."""
    s, c = math.sin(plant.max_tilt_rad), math.cos(plant.max_tilt_rad)
    f_xy = math.sqrt(2.0) * plant.force_rate_limit_nps
    a_min = policy.min_specific_force_mps2
    attitude = min(f_xy / (plant.mass_kg * a_min * c), policy.body_rate_max_rps / c)
    return ExogenousRates(thrust_nps=f_xy * s, attitude_rps=attitude, speed_mps2=policy.max_specific_force_mps2 * s,
                          attitude_per_uz=math.tan(plant.max_tilt_rad) / a_min)


@dataclass(frozen=True)
class NetworkSlopes:
    """A network's physical Lipschitz constants by input role, (m/s²) per unit: ``state`` (p_z m, v_z m/s jointly),
    ``thrust`` (N), ``attitude`` (rad), ``speed`` (m/s); ``mass_kg``: the vehicle mass it was made for (NaN:
    unknown); ``thrust_inputs``: whether it takes a thrust (in newtons)."""

    state: float
    thrust: float = 0.0
    attitude: float = 0.0
    speed: float = 0.0
    mass_kg: float = math.nan
    thrust_inputs: bool = False

    @staticmethod
    def of(net) -> "NetworkSlopes":
        """From a :class:`neso.network.LipschitzMLP` (exact SVD products per role; an unknown feature set counts
        every input as state)."""
        by_role = net.role_columns()
        lip = {role: (net.certified_lipschitz_columns(cols) if cols else 0.0) for role, cols in by_role.items()}
        try:
            mass = float(net.metadata.get("mass_kg", "nan"))
        except ValueError:
            mass = math.nan
        return NetworkSlopes(lip.get("state", 0.0), lip.get("thrust", 0.0), lip.get("attitude", 0.0),
                             lip.get("speed", 0.0), mass, bool(by_role.get("thrust")))

    def scaled(self, factor: float) -> "NetworkSlopes":
        return replace(self, state=self.state * factor, thrust=self.thrust * factor,
                       attitude=self.attitude * factor, speed=self.speed * factor)

    def to_dict(self) -> dict:
        return {"state": self.state, "thrust": self.thrust, "attitude": self.attitude, "speed": self.speed,
                "mass_kg": self.mass_kg if math.isfinite(self.mass_kg) else None, "thrust_inputs": self.thrust_inputs}

    @staticmethod
    def from_dict(d: dict) -> "NetworkSlopes":
        """From :meth:`to_dict` (ValueError/KeyError/TypeError on a malformed one)."""
        mass = d.get("mass_kg")
        return NetworkSlopes(float(d["state"]), float(d.get("thrust", 0.0)), float(d.get("attitude", 0.0)),
                             float(d.get("speed", 0.0)), math.nan if mass is None else float(mass),
                             bool(d.get("thrust_inputs", False)))


@dataclass(frozen=True)
class FlightCertificate:
    """The verdict for flying a network (or none: all slopes 0) with z gains ``kp`` (1/s²), ``kd`` (1/s) and
    ``omega_o`` (rad/s) on ``plant``.

    ``loop_gain`` K (< 1 needed); ``exogenous_rate_mps3`` X; ``max_certified`` the largest state slope the role
    certificate verified at this K and ``margin`` = it − ``lipschitz_phys`` (the state slope), (m/s²)/unit z: the one
    margin the services act on (> 0 iff the loop is certified). ``bound_cm``/``pdeso_bound_cm``: eventual |e_z| over
    the envelope, the network's and PD+ESO's (inf: no bound); ``bound_ratio`` their ratio. ``holds``: every condition
    (module docstring); ``reasons``: why not, one line each."""

    holds: bool
    slopes: NetworkSlopes
    kp: float
    kd: float
    omega_o: float
    plant: LoopPlant
    loop_gain: float
    exogenous_rate_mps3: float
    max_certified: float
    bound_cm: float
    pdeso_bound_cm: float
    policy: CertificatePolicy
    reasons: tuple[str, ...]
    role: RoleCertificate
    pdeso: RoleCertificate

    @property
    def lipschitz_phys(self) -> float:
        return self.slopes.state

    @property
    def margin(self) -> float:
        return self.max_certified - self.slopes.state

    @property
    def stable(self) -> bool:
        return self.role.holds

    @property
    def bound_ratio(self) -> float:
        return self.bound_cm / self.pdeso_bound_cm if self.pdeso_bound_cm > 0 else math.inf

    def bound_for_cm(self, reference: ReferenceBounds) -> tuple[float, float]:
        """(network's, PD+ESO's) eventual |e_z| bound in cm for another reference, from the same two certificates
        (valid for any reference; tuned for the envelope)."""
        net = role_inputs(self.slopes, self.kp, self.kd, self.omega_o, self.plant, reference, self.policy)
        none = role_inputs(NetworkSlopes(0.0), self.kp, self.kd, self.omega_o, self.plant, reference, self.policy)
        return _bound_cm(self.role, net), _bound_cm(self.pdeso, none)

    def text(self) -> str:
        verdict = "holds" if self.holds else "FAILS"
        parts = [f"certificate {verdict}: state slope {self.slopes.state:.3g} of {self.max_certified:.3g} "
                 f"(m/s²)/unit z certified (margin {self.margin:+.3g})"]
        if self.loop_gain > 0:
            parts.append(f"loop gain through the thrust/attitude {self.loop_gain:.2g} (< 1)")
        if math.isfinite(self.bound_cm):
            parts.append(f"|e_z| ≤ {self.bound_cm:.3g} cm (PD+ESO {self.pdeso_bound_cm:.3g} cm, ×{self.bound_ratio:.2g}"
                         f" ≤ ×{self.policy.max_bound_ratio:g})")
        else:
            parts.append(f"|e_z| unbounded (PD+ESO {self.pdeso_bound_cm:.3g} cm)")
        parts.append(f"kp {self.kp:g}, kd {self.kd:g}, ω_o {self.omega_o:g}")
        out = "; ".join(parts)
        return out + (" — " + "; ".join(self.reasons) if self.reasons else "")

    def to_dict(self) -> dict:
        return {"holds": self.holds, "stable": self.stable, "lipschitz_phys": self.slopes.state,
                "max_certified": self.max_certified, "margin": self.margin, "loop_gain": self.loop_gain,
                "exogenous_rate_mps3": self.exogenous_rate_mps3, "bound_cm": _finite(self.bound_cm),
                "pdeso_bound_cm": _finite(self.pdeso_bound_cm), "bound_ratio": _finite(self.bound_ratio),
                "max_bound_ratio": self.policy.max_bound_ratio, "slopes": self.slopes.to_dict(), "kp": self.kp,
                "kd": self.kd, "omega_o": self.omega_o, "vehicle_mass_kg": self.plant.mass_kg,
                "reasons": list(self.reasons), "text": self.text()}


def _finite(v: float) -> float | None:
    return v if math.isfinite(v) else None


def _bound_cm(cert: RoleCertificate, inputs: RoleInputs) -> float:
    """|e_z| bound (cm) of ``cert``'s V under ``inputs``' C_f and reference (inf without a bound certificate)."""
    return 100.0 * error_bound_under(cert, inputs)


def loop_figures(slopes: NetworkSlopes, plant: LoopPlant, policy: CertificatePolicy = POLICY) -> tuple[float, float]:
    """``(K, X)``: the loop gain through ``u_z`` (dimensionless) and the exogenous share of ``ḟ_N`` (m/s³)."""
    r = exogenous_rates(plant, policy)
    k = plant.mass_kg * slopes.thrust + r.attitude_per_uz * slopes.attitude
    x = slopes.thrust * r.thrust_nps + slopes.attitude * r.attitude_rps + slopes.speed * r.speed_mps2
    return k, x


def role_inputs(slopes: NetworkSlopes, kp: float, kd: float, omega_o: float, plant: LoopPlant,
                reference: ReferenceBounds, policy: CertificatePolicy = POLICY) -> RoleInputs:
    """The role certificate's question for a network with ``slopes`` (module docstring)."""
    k, x = loop_figures(slopes, plant, policy)
    return RoleInputs(float(kp), float(kd), float(omega_o), lipschitz_state=slopes.state, loop_gain=k,
                      exogenous_rate_mps3=x, velocity_lag_s=policy.velocity_lag_s,
                      L_1=policy.disturbance_rate_max_mps3, ref_vel_max=reference.vel_mps,
                      ref_acc_max=reference.acc_mps2, ref_jerk_max=reference.jerk_mps3)


@functools.lru_cache(maxsize=1024)
def flight_certificate(slopes: NetworkSlopes, *, kp: float, kd: float, omega_o: float, plant: LoopPlant,
                       policy: CertificatePolicy = POLICY) -> FlightCertificate:
    """The verdict (module docstring) for a network with ``slopes`` (``NetworkSlopes(0.0)``: none) flown with these
    z gains and ``omega_o`` on ``plant``. Cached; what the estimator, its hot-swap gate, the controller's gain check,
    the trainer and ``neso certify`` all call."""
    envelope = ReferenceBounds.envelope(policy)
    inputs = role_inputs(slopes, kp, kd, omega_o, plant, envelope, policy)
    role = certify_roles(inputs)
    pdeso = certify_roles(role_inputs(NetworkSlopes(0.0), kp, kd, omega_o, plant, envelope, policy))
    bound, pdeso_bound = 100.0 * role.error_bound_m, 100.0 * pdeso.error_bound_m
    reasons = []
    if not role.holds:
        reasons.append(role.notes[0] if role.notes else "the role certificate does not verify")
    elif not math.isfinite(bound):
        reasons.append("no eventual bound verified for it")
    elif bound > policy.max_bound_ratio * pdeso_bound:
        reasons.append(f"its eventual |e_z| bound {bound:.3g} cm is ×{bound / pdeso_bound:.2g} PD+ESO's "
                       f"{pdeso_bound:.3g} cm (at most ×{policy.max_bound_ratio:g}): certified stable, not to fly well")
    if slopes.thrust_inputs:
        if not math.isfinite(slopes.mass_kg):
            reasons.append(f"its thrust input is in newtons and its file states no mass: made for an unknown "
                           f"vehicle, flown on {plant.mass_kg:g} kg")
        elif abs(slopes.mass_kg - plant.mass_kg) > policy.mass_tolerance * plant.mass_kg:
            reasons.append(f"its thrust input is in newtons for a {slopes.mass_kg:g} kg vehicle, flown on "
                           f"{plant.mass_kg:g} kg (beyond ±{policy.mass_tolerance * 100:g} %)")
    return FlightCertificate(not reasons, slopes, float(kp), float(kd), float(omega_o), plant, inputs.loop_gain,
                             inputs.exogenous_rate_mps3, role.max_certified, bound, pdeso_bound, policy,
                             tuple(reasons), role, pdeso)


#: Budgets found before, by :func:`budget_key` (:func:`adopt_budget`): each is verified again before it is used.
_KNOWN_BUDGETS: dict[str, float] = {}
#: Budgets this process found (bisected, or adopted and verified), by :func:`budget_key`: for a cache to keep.
FOUND_BUDGETS: dict[str, float] = {}


def budget_key(kp: float, kd: float, omega_o: float, plant: LoopPlant, exogenous_fraction: float,
               exogenous_roles: tuple[str, ...], policy: CertificatePolicy) -> str:
    """The question :func:`flight_budget` answers, as one string (every figure it depends on, at full precision)."""
    return repr((float(kp), float(kd), float(omega_o), plant, float(exogenous_fraction), tuple(exogenous_roles),
                 policy))


def adopt_budget(key: str, value) -> bool:
    """A budget :func:`flight_budget` found before for the question ``key``, to be verified — its certificate at
    that slope solved and holding — instead of bisected again when the question is asked. Only that it holds is
    checked, not that it is the largest that does: a smaller budget than the bisection's is a safe one. False (and
    nothing adopted) for a value that is not a positive finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return False
    if not (math.isfinite(v) and v > 0.0):
        return False
    _KNOWN_BUDGETS[key] = v
    return True


def flight_budget(kp: float, kd: float, omega_o: float, *, plant: LoopPlant | None = None,
                  exogenous_fraction: float = 0.0, exogenous_roles: tuple[str, ...] = ("attitude",),
                  policy: CertificatePolicy = POLICY) -> float:
    """The largest state slope ``L_s`` ((m/s²) per unit z) a network may have and still be certified to fly well with
    these gains (1/s², 1/s, rad/s) on ``plant`` (default: the controller's defaults) when its inputs of each of
    ``exogenous_roles`` (``thrust``, ``attitude``, ``speed``) have slopes ``exogenous_fraction × L_s``: a bisection
    on :func:`flight_certificate`'s verdict (stability and the bound ratio; both monotone in the slopes). What the
    trainer spends. A budget adopted for this question (:func:`adopt_budget`) is verified instead: two role
    certificates (~0.6 s) for the bisection's ~17 (~10 s)."""
    if plant is None:
        from neso.control import ControlConfig

        plant = LoopPlant.of(ControlConfig())
    unknown = set(exogenous_roles) - {"thrust", "attitude", "speed"}
    if unknown:
        raise ValueError(f"exogenous roles are thrust, attitude, speed; got {sorted(unknown)}")

    def slopes(ls: float) -> NetworkSlopes:
        x = exogenous_fraction * ls
        return NetworkSlopes(ls, x if "thrust" in exogenous_roles else 0.0, x if "attitude" in exogenous_roles else 0.0,
                             x if "speed" in exogenous_roles else 0.0, plant.mass_kg, "thrust" in exogenous_roles)

    def ok(ls: float) -> bool:
        return flight_certificate(slopes(ls), kp=kp, kd=kd, omega_o=omega_o, plant=plant, policy=policy).holds

    key = budget_key(kp, kd, omega_o, plant, exogenous_fraction, exogenous_roles, policy)
    hi = max_certified_state_lipschitz_verified(float(kp), float(kd), float(omega_o), policy.velocity_lag_s)
    known = _KNOWN_BUDGETS.get(key)
    if known is not None and known <= hi and ok(known):
        FOUND_BUDGETS[key] = known
        return known
    lo = 0.0
    if ok(hi):
        lo = hi
    else:
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if ok(mid) else (lo, mid)
            if hi - lo <= 1e-4 * hi:
                break
    if lo > 0.0:
        FOUND_BUDGETS[key] = lo
    return lo
