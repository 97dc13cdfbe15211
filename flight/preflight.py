"""May the vehicle arm? The preflight verdict, one item per check, each with what was found and its fix.

What is checked (the px4_gateway gathers the inputs: :class:`PreflightInputs`; this module only judges):

- **the PX4 parameters** of :mod:`flight.px4_params`, read from the vehicle over MAVLink, each against its
  requirement (no-go, or a warning where the table says so), and ``EKF2_EV_DELAY`` against the delay measured;
- **the autopilot**: connected, its version (the table was read from PX4 v1.16.0's sources), PX4's own pre-arm
  checks (MAVSDK's ``health.is_armable``);
- **EKF2 fusing the motion capture**: PX4 reports a valid local position and it agrees with the motion capture's
  (what no parameter shows: a frame or axis mix-up, a heading not aligned, a height off by the origin's altitude);
- **the global origin**: PX4's Hold (the offboard-loss action) needs one indoors, and with vision height it must be
  at 0 m (:func:`_origin`);
- **the motion capture**: the rigid body tracked now, states arriving, the stream's rate, latency and jitter from
  Motive's own timestamps (:mod:`flight.mocap_time`, the source's health), its longest gap;
- **the bus and every service**: each of the loop's services alive and reporting health;
- **the network's certificate**: the estimator's network certified for the controller's gains
  (:func:`neso.certificate.flight_certificate`, recomputed by the gateway);
- **the battery**.

A no-go item stops arming (the gateway refuses ``arm`` unless the operator overrides it, which is logged and
recorded); a warning is shown and arming goes on. Pure: inputs in, a :class:`Verdict` out; no clock.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from flight.px4_params import PX4_SOURCE, checked, judge

GO, NO_GO, WARNING = "go", "no-go", "warning"
LOOP_SERVICES = ("source", "estimator", "controller")  # what the flight needs besides the gateway itself


@dataclass(frozen=True)
class PreflightConfig:
    """Thresholds, each with its reason. Rates in Hz, times in s unless named ms, distances in m."""

    control_rate_hz: float = 50.0  # one state per control period: the loop's rate (neso.types.LOOP_RATE_HZ)
    ev_agreement_m: float = 0.05  # PX4's position vs the motion capture's: EKF2 fusing it agrees to mm-cm
    origin_alt_max_m: float = 0.5  # |the global origin's altitude| with vision height (see _origin)
    mocap_latency_warn_ms: float = 30.0  # the world's mocap latency is 10 ms; a lab's Motive ~5-15 ms
    mocap_jitter_warn_ms: float = 10.0  # p99 - p50 of capture → arrival: a fifth of a control period
    state_age_max_s: float = 0.5  # no state for this long: the source's stream-stopped threshold
    health_age_max_s: float = 3.0  # services report health at 1 Hz: three missed reports
    battery_no_go: float = 0.30  # below this share no flight starts (PX4's own BAT_LOW_THR is 0.15, in the air)
    battery_warn: float = 0.50
    ev_delay_tolerance_ms: float = 5.0  # a quarter of a 50 Hz period
    pose_lost_after_s: float = 0.3  # the gateway's: a longer gap in the stream makes it tell PX4 the mocap failed


@dataclass(frozen=True)
class ServiceSeen:
    """A service as the bus shows it: ``alive`` (liveliness token), ``health_age_s`` since its last health report
    (inf: none), its ``status`` line."""

    alive: bool
    health_age_s: float = math.inf
    status: str = ""


@dataclass(frozen=True)
class PreflightInputs:
    """What the gateway gathered. ``params``: the checked parameters read from the vehicle (None: the vehicle has
    no such parameter); ``params_error``: why they could not be read ("" when they were). ``ev_offset_m``: PX4's
    horizontal position minus the motion capture's, norm, and ``ev_height_offset_m`` its height minus the motion
    capture's (None: unknown). ``origin_alt_m``: the altitude of the global origin the vehicle reported (None: none
    reported). ``mocap``: the source's health counters
    (:class:`flight.mocap_time.StreamStats` figures, ``rigid_body_tracked``); ``state_age_s``: since the last
    state reached the gateway. ``delay_ms``: motion capture → PX4 (p50, p99; None: not measured);
    ``px4_uses_capture_time``: PX4's time sync with the gateway has converged, so it takes ODOMETRY's
    ``time_usec``; ``time_sync_answers``: its time-sync requests the gateway answered (converging while some
    came and it has not converged). ``certificate``: :meth:`neso.certificate.FlightCertificate.to_dict` of what flies (None: the
    estimator published no network). ``battery_remaining``: 0-1, negative unknown."""

    connected: bool
    autopilot: str = ""
    armable: bool | None = None
    armable_why: str = ""
    params: dict[str, float | None] = field(default_factory=dict)
    params_error: str = ""
    local_position_ok: bool | None = None
    ev_offset_m: float | None = None
    ev_height_offset_m: float | None = None
    origin_alt_m: float | None = None
    mocap: dict[str, float] = field(default_factory=dict)
    state_age_s: float = math.inf
    services: dict[str, ServiceSeen] = field(default_factory=dict)
    delay_ms: tuple[float, float] | None = None
    px4_uses_capture_time: bool = False
    time_sync_answers: int = 0
    certificate: dict | None = None
    battery_remaining: float = -1.0
    battery_v: float = 0.0


@dataclass(frozen=True)
class Item:
    name: str
    verdict: str
    found: str
    fix: str = ""


@dataclass(frozen=True)
class Verdict:
    items: tuple[Item, ...]

    @property
    def go(self) -> bool:
        return not any(i.verdict == NO_GO for i in self.items)

    def no_go(self) -> tuple[Item, ...]:
        return tuple(i for i in self.items if i.verdict == NO_GO)

    def as_items(self) -> dict[str, list[str]]:
        """What :class:`runtime.schema.PreflightMsg` carries."""
        return {i.name: [i.verdict, i.found[:512], i.fix[:512]] for i in self.items}

    def table(self) -> str:
        """One line per item: verdict, item, what was found, the fix; then the verdict in one line."""
        width = max((len(i.name) for i in self.items), default=4)
        lines = [f"{i.verdict.upper():8} {i.name:{width}}  {i.found}" + (f"  → {i.fix}" if i.fix else "")
                 for i in self.items]
        bad = self.no_go()
        lines.append(f"GO: {len(self.items)} items checked" + (
            f", {sum(i.verdict == WARNING for i in self.items)} warnings" if any(i.verdict == WARNING for i in
                                                                                self.items) else "")
                     if not bad else f"NO-GO: {', '.join(i.name for i in bad)}")
        return "\n".join(lines)


def table_from_items(items: dict[str, list[str]]) -> str:
    """:meth:`Verdict.table` of a verdict received as :class:`runtime.schema.PreflightMsg` items."""
    return Verdict(tuple(Item(name, *entry) for name, entry in items.items())).table()


def preflight(inputs: PreflightInputs, config: PreflightConfig = PreflightConfig()) -> Verdict:
    """The verdict (module docstring)."""
    items: list[Item] = [*_autopilot(inputs), *_parameters(inputs, config), *_estimator(inputs, config),
                         *_origin(inputs, config), *_mocap(inputs, config), *_services(inputs, config),
                         _certificate(inputs), _battery(inputs, config)]
    return Verdict(tuple(items))


def _autopilot(i: PreflightInputs) -> list[Item]:
    if not i.connected:
        return [Item("autopilot", NO_GO, "no vehicle connected", "check the MAVLink link (--mavlink) and that the "
                                                                   "vehicle is powered")]
    version = i.autopilot or "version not reported"
    same = PX4_SOURCE.split()[-1] in version
    out = [Item("autopilot", GO if same else WARNING, version,
                "" if same else f"the parameter table was read from {PX4_SOURCE}'s sources: check the names and "
                                "values of this version")]
    if i.armable is not None:
        out.append(Item("PX4 pre-arm checks", GO if i.armable else NO_GO,
                        "pass" if i.armable else f"fail{': ' + i.armable_why if i.armable_why else ''}",
                        "" if i.armable else "read PX4's own words above (QGroundControl's arming checks list them); "
                                             "EKF2 settles ~2 s after the motion capture starts"))
    return out


def _parameters(i: PreflightInputs, c: PreflightConfig) -> list[Item]:
    if i.params_error:
        return [Item("PX4 parameters", NO_GO, f"not read: {i.params_error}", "check the MAVLink link; then "
                                                                              "`neso preflight` again")]
    out = []
    for p in checked():
        if p.name not in i.params:
            continue
        value = i.params[p.name]
        if p.required.measured:
            out.append(_ev_delay(p.name, value, i, c))
            continue
        ok, fix = judge(p, value)
        found = "missing" if value is None else f"{value:g}"
        out.append(Item(p.name, GO if ok else p.required.severity, found,
                        "" if ok else f"{fix} (required {p.required.text()})"))
    return out


def ev_delay_to_set_ms(i: PreflightInputs) -> float | None:
    """``EKF2_EV_DELAY`` for this setup (ms): 0 when PX4 takes (or, its time sync converging, is about to take) the
    capture time the gateway sends (PX4's docs: 0 with correct timestamps and time sync), else the delay measured
    from capture to PX4 (p50); None unmeasured."""
    if i.px4_uses_capture_time or i.time_sync_answers > 0:
        return 0.0
    return None if i.delay_ms is None else i.delay_ms[0]


def _ev_delay(name: str, value: float | None, i: PreflightInputs, c: PreflightConfig) -> Item:
    measured = ("not measured yet" if i.delay_ms is None else
                f"motion capture → PX4 {i.delay_ms[0]:.1f} ms (p99 {i.delay_ms[1]:.1f})")
    how = ("PX4 takes the capture time" if i.px4_uses_capture_time else
           f"PX4's time sync converging ({i.time_sync_answers} of 500 answers): it will take the capture time"
           if i.time_sync_answers > 0 else "PX4 stamps it on arrival")
    want = ev_delay_to_set_ms(i)
    found = f"{'missing' if value is None else f'{value:g} ms'}; {measured}; {how}"
    if value is None:
        return Item(name, NO_GO, found, f"{name} does not exist on this vehicle: PX4 v1.14 or later has it")
    if want is None or abs(value - want) <= c.ev_delay_tolerance_ms:
        return Item(name, GO, found)
    return Item(name, WARNING, found, f"param set {name} {round(want)} (the delay EKF2 must still allow for; a "
                                      "reboot applies it)")


def _estimator(i: PreflightInputs, c: PreflightConfig) -> list[Item]:
    if not i.connected:
        return []
    if i.local_position_ok is False:
        return [Item("EKF2 fuses the motion capture", NO_GO, "PX4 has no valid local position",
                     "EKF2_EV_CTRL and EKF2_HGT_REF as above, motion capture streaming; EKF2 needs ~2 s of it")]
    if i.ev_offset_m is None:
        return [Item("EKF2 fuses the motion capture", NO_GO, "no PX4 position or no motion capture to compare",
                     "wait for the motion capture and PX4's telemetry")]
    if i.ev_offset_m > c.ev_agreement_m:
        return [Item("EKF2 fuses the motion capture", NO_GO,
                     f"PX4's horizontal position is {i.ev_offset_m * 100:.1f} cm from the motion capture's",
                     "the rigid body's axes (--frame, Motive's up axis) or EKF2's heading: restart PX4 with the "
                     "vehicle still and the motion capture streaming")]
    height = i.ev_height_offset_m
    if height is not None and abs(height) > c.ev_agreement_m:
        return [Item("EKF2 fuses the motion capture", NO_GO,
                     f"PX4's height is {height:+.2f} m from the motion capture's (horizontal within "
                     f"{i.ev_offset_m * 100:.1f} cm)",
                     "a global origin above 0 m (see the global origin's item) or the rigid body's up axis; restart "
                     "PX4 with the vehicle still and the motion capture streaming")]
    vertical = "its height valid" if height is None else f"its height within {abs(height) * 100:.1f} cm"
    return [Item("EKF2 fuses the motion capture", GO, f"PX4's horizontal position within {i.ev_offset_m * 100:.1f} cm "
                                                      f"of the motion capture's; {vertical}")]


def _origin(i: PreflightInputs, c: PreflightConfig) -> list[Item]:
    """PX4 v1.16's EKF2 (re)starts vision height fusion as an altitude above sea level (ev_height_control.cpp:
    ``resetAltitudeTo(-measurement)``, without the origin's altitude): with vision height (EKF2_HGT_REF 3) and an
    origin at A m, its local height is A m off after every restart of it — at boot, and after each motion-capture
    gap longer than EKF2's vision timeout. A Hold entered before such a gap then climbs at full speed to the
    altitude it held (measured in SITL: origin 488 m, a 1.9 s gap, 2.8 m/s up to 8.8 m). At 0 m the two agree."""
    if not i.connected:
        return []
    if i.origin_alt_m is None:
        return [Item("global origin", WARNING, "the vehicle reported none yet",
                     "the gateway sends --global-origin once EKF2 has a local position; without one PX4 refuses Hold, "
                     "its offboard-loss action (COM_OBL_RC_ACT)")]
    vision_height = i.params.get("EKF2_HGT_REF") == 3
    if vision_height and abs(i.origin_alt_m) > c.origin_alt_max_m:
        return [Item("global origin", NO_GO,
                     f"at {i.origin_alt_m:g} m with vision height: PX4 v1.16 restarts vision height without the "
                     f"origin's altitude, so after a motion-capture gap its height is {i.origin_alt_m:g} m off and "
                     "Hold climbs at full speed",
                     "an origin at 0 m: reboot PX4 and let the gateway give it (--global-origin lat,lon,0, the "
                     "default)")]
    return [Item("global origin", GO, f"at {i.origin_alt_m:g} m")]


def _mocap(i: PreflightInputs, c: PreflightConfig) -> list[Item]:
    m = i.mocap
    out = []
    tracked = m.get("rigid_body_tracked")
    if i.state_age_s > c.state_age_max_s or tracked == 0.0:
        why = "not tracked (markers occluded, outside the volume)" if tracked == 0.0 else \
            ("no state has reached the gateway" if math.isinf(i.state_age_s) else f"no state for {i.state_age_s:.1f} s")
        out.append(Item("rigid body seen", NO_GO, why, "Motive's rigid body tracked and streaming; the source running "
                                                      "with its name (--rigid-body)"))
    else:
        out.append(Item("rigid body seen", GO, f"states arriving (the last {i.state_age_s * 1e3:.0f} ms ago)"))
    if "mocap_rate_hz" not in m:
        return out  # a simulated world without a stream, or the source has not reported yet
    rate = m["mocap_rate_hz"]
    out.append(Item("motion capture rate", GO if rate >= c.control_rate_hz else NO_GO, f"{rate:.0f} Hz",
                    "" if rate >= c.control_rate_hz else f"at least {c.control_rate_hz:g} Hz (one frame per control "
                                                         "period): Motive's camera frame rate and streaming"))
    p50, p99, jitter = m.get("mocap_latency_p50_ms", math.nan), m.get("mocap_latency_p99_ms", math.nan), \
        m.get("mocap_jitter_ms", math.nan)
    motive = m.get("motive_latency_ms", math.nan)
    found = f"capture → here p50 {p50:.1f} ms, p99 {p99:.1f} ms (Motive's own {motive:.1f} ms)"
    late = p99 > c.mocap_latency_warn_ms
    out.append(Item("motion capture latency", WARNING if late else GO, found,
                    "a wired link from the Motive PC; fewer cameras or a lower resolution in Motive" if late else ""))
    shaky = jitter > c.mocap_jitter_warn_ms
    share = m.get("mocap_in_order_share", 1.0)
    out.append(Item("motion capture jitter", WARNING if shaky else GO,
                    f"{jitter:.1f} ms (p99 − p50)" + (f"; {100 * (1 - share):.0f} % of the frames overtaken by a newer "
                                                      "one (not used)" if share < 0.999 else ""),
                    "states keep their capture time, so the flight goes on; look for Wi-Fi or a busy network "
                    "between the Motive PC and here" if shaky else ""))
    gap = m.get("mocap_gap_max_ms", 0.0)
    long_gap = gap > c.pose_lost_after_s * 1e3
    out.append(Item("motion capture gaps", WARNING if long_gap else GO, f"longest {gap:.0f} ms in the last 5 s",
                    f"longer than {c.pose_lost_after_s * 1e3:.0f} ms: the gateway tells PX4 the motion capture "
                    "failed; check occlusions and the network" if long_gap else ""))
    return out


def _services(i: PreflightInputs, c: PreflightConfig) -> list[Item]:
    out = []
    for name in LOOP_SERVICES:
        seen = i.services.get(name)
        if seen is None or not seen.alive:
            out.append(Item(f"service {name}", NO_GO, "not on the bus", f"start it (`neso run {name} …`) on this "
                                                                         "bus, or check the hub"))
        elif seen.health_age_s > c.health_age_max_s:
            out.append(Item(f"service {name}", NO_GO, f"alive, no health report for {seen.health_age_s:.1f} s",
                            "it is stuck or the bus drops its reports: restart it"))
        else:
            out.append(Item(f"service {name}", GO, seen.status[:120] or "healthy"))
    recorder = i.services.get("recorder")
    out.append(Item("service recorder", GO if recorder is not None and recorder.alive else WARNING,
                    "recording" if recorder is not None and recorder.alive else "not on the bus: this flight will "
                                                                               "not be recorded",
                    "" if recorder is not None and recorder.alive else "`neso run recorder` to keep the flight"))
    return out


def _certificate(i: PreflightInputs) -> Item:
    cert = i.certificate
    if cert is None:
        return Item("certificate", NO_GO, "the estimator published no network", "start the estimator (`neso run "
                                                                                 "estimator`)")
    text = cert.get("text", "")
    if cert.get("holds"):
        return Item("certificate", GO, text)
    return Item("certificate", NO_GO, text, "a certified network or a lower L_N (`neso params set estimator "
                                            "lipschitz_bound=…`), or the controller's z gains the certificate allows")


def _battery(i: PreflightInputs, c: PreflightConfig) -> Item:
    if i.battery_remaining < 0:
        return Item("battery", WARNING, f"{i.battery_v:.2f} V, charge not reported", "check the battery's voltage "
                                                                                   "by hand; BAT1_* calibration")
    share = i.battery_remaining
    found = f"{share * 100:.0f} % ({i.battery_v:.2f} V)"
    if share < c.battery_no_go:
        return Item("battery", NO_GO, found, f"charge it (at least {c.battery_no_go * 100:.0f} % to take off)")
    if share < c.battery_warn:
        return Item("battery", WARNING, found, "a short flight only")
    return Item("battery", GO, found)
