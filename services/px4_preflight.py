"""The px4_gateway's preflight, the I/O side (the verdict itself is :mod:`flight.preflight`; :class:`GatewayPreflight`
judges every second, publishes and gates ``arm``): the vehicle's
parameters read over MAVLink (MAVSDK's Param plugin, one ``PARAM_REQUEST_READ`` each), what the bus shows (every
service's health and liveliness, the estimator's network), the certificate recomputed through its public API, and
PX4's time sync with the gateway (TIMESYNC), which lets PX4 use the capture time the gateway stamps ODOMETRY with.

**Time sync** (PX4 v1.16: ``src/lib/timesync/Timesync.cpp``, ``src/modules/mavlink/mavlink_timesync.cpp``): PX4
sends TIMESYNC requests (``tc1`` 0, ``ts1`` its time in ns) and converts a received ``time_usec`` into its own clock
(``sync_stamp``) only once its offset estimate has converged: 500 answers with a round trip under 10 ms
(``CONVERGENCE_WINDOW``, ``MAX_RTT_SAMPLE``); before that it stamps ODOMETRY on arrival; a time jump (its clock
moved against ours by over 100 ms, as a stall of PX4 SITL in lockstep does) resets it to no samples
(:mod:`flight.px4_timesync` follows all of that from PX4's requests). MAVSDK answers them only when its timesync is
enabled, which MAVSDK-Python 4.1 does not do, so the gateway answers them here with ``time.monotonic_ns()`` — the
clock of ``time_usec`` — and asks PX4 for them at 50 Hz until PX4 has converged (10 s instead of the onboard link's
10 Hz, 50 s) and again after a reset, else at its own rate. Its own TIMESYNC requests to PX4 measure the link's round
trip (half of it is the link's share of the motion capture's delay to PX4).
"""
from __future__ import annotations

import json
import math
import threading
import time
from collections import deque

from flight.preflight import PreflightConfig, PreflightInputs, ServiceSeen, Verdict, preflight
from flight.px4_params import checked
from flight.px4_timesync import CONVERGENCE_WINDOW, MAX_RTT_US, Px4Timesync
from runtime.schema import PreflightMsg

FAST_TIMESYNC_HZ = 50.0
MAV_CMD_SET_MESSAGE_INTERVAL, MAVLINK_MSG_ID_TIMESYNC = 511, 111
MAV_CMD_REQUEST_MESSAGE, MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN = 512, 49


def read_parameters(param) -> tuple[dict[str, float | None], str]:
    """Every checked parameter of :mod:`flight.px4_params` from the vehicle (MAVSDK ``Param``): ({name: value,
    None when the vehicle has no such parameter}, "") or ({}, why none could be read)."""
    from mavsdk.plugins.param import ParamError, ParamResult

    values: dict[str, float | None] = {}
    for p in checked():
        try:
            values[p.name] = float(param.get_param_int(p.name) if p.kind == "int32" else param.get_param_float(p.name))
        except ParamError as exc:
            if exc.result in (ParamResult.DOES_NOT_EXIST, ParamResult.TIMEOUT, ParamResult.WRONG_TYPE,
                              ParamResult.TYPE_MISMATCH):
                values[p.name] = None  # PX4 does not answer PARAM_REQUEST_READ for a name it does not have
            else:
                return {}, f"{p.name}: {exc.result.name}"
    if values and all(v is None for v in values.values()):
        return {}, "the vehicle answered none of them"
    return values, ""


class BusWatch:
    """What the bus shows the gateway: each service's last health report (service → (received s, HealthMsg)) and
    the estimator's newest network report. Fed under the node lock."""

    def __init__(self) -> None:
        self.health: dict[str, tuple[float, object]] = {}
        self.network = None

    def on_health(self, service: str, msg, received_s: float) -> None:
        self.health[service] = (received_s, msg)

    def on_network(self, msg, _received_s: float) -> None:
        self.network = msg

    def services(self, alive: set[str], now_s: float, recent_s: float = 3.0) -> dict[str, ServiceSeen]:
        """Each service seen: alive when its liveliness token answered or its health came within ``recent_s``
        (a liveliness query can come back empty while the bus is busy; a health report cannot be faked)."""
        names = set(alive) | set(self.health)
        age = {n: now_s - self.health[n][0] if n in self.health else math.inf for n in names}
        return {n: ServiceSeen(n in alive or age[n] <= recent_s, age[n],
                               self.health[n][1].status if n in self.health else "") for n in names}

    def source_counters(self) -> dict[str, float]:
        got = self.health.get("source")
        return dict(got[1].counters) if got is not None else {}


class CertificateCheck:
    """The certificate of what the estimator flies, recomputed here through its public API
    (:func:`neso.certificate.flight_certificate`, the function the estimator uses) from the network report's
    slopes, gains, ω_o and vehicle mass, on the controller's model of the loop (:class:`neso.certificate.LoopPlant`
    of :class:`neso.control.ControlConfig` at that mass, as the estimator builds it); the SDPs adopted from the
    cross-process cache when they verify (:func:`services.certificate_cache.warm_flight`), else solved once per
    report (seconds: on the preflight thread, off the flight loop's). A report this code cannot read (another
    version of the certificate) is judged by the estimator's own verdict, and the item says so."""

    def __init__(self) -> None:
        self._done: dict[str, dict] = {}

    def verdict(self, network) -> dict | None:
        if network is None or not network.certificate:
            return None
        c = network.certificate
        key = repr(sorted((k, repr(v)) for k, v in c.items() if k in ("slopes", "kp", "kd", "omega_o",
                                                                        "vehicle_mass_kg")))
        if key not in self._done:
            try:
                self._done[key] = self._recompute(c)
            except (KeyError, TypeError, ValueError) as exc:
                self._done[key] = dict(c, text=f"{c.get('text', '')} (the estimator's verdict: its report could not "
                                                f"be recomputed here: {type(exc).__name__}: {exc})")
        return self._done[key]

    @staticmethod
    def _recompute(c: dict) -> dict:
        from neso.certificate import LoopPlant, NetworkSlopes, flight_certificate
        from neso.control import ControlConfig
        from neso.types import VehicleModel
        from services.certificate_cache import warm_flight

        slopes = NetworkSlopes.from_dict(c["slopes"])
        kp, kd, omega_o = float(c["kp"]), float(c["kd"]), float(c["omega_o"])
        plant = LoopPlant.of(ControlConfig(vehicle=VehicleModel(mass_kg=float(c["vehicle_mass_kg"]))))
        warm_flight(slopes, kp, kd, omega_o, plant)
        return flight_certificate(slopes, kp=kp, kd=kd, omega_o=omega_o, plant=plant).to_dict()


class TimeSync:
    """Answers PX4's TIMESYNC requests with this machine's monotonic clock, measures the link's round trip with
    requests of its own, and follows PX4's time sync from its requests (``px4``: :class:`flight.px4_timesync.
    Px4Timesync`; module docstring)."""

    def __init__(self, direct, system_id: int, log) -> None:
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        self._message, self._direct, self._system_id, self._log = MavlinkMessage, direct, system_id, log
        self._lock = threading.Lock()
        self.px4 = Px4Timesync()
        self._fast = False
        self.rtt_s: deque[float] = deque(maxlen=50)
        self._handle = direct.subscribe_message("TIMESYNC", self._on_timesync)

    def _send(self, name: str, fields: dict) -> None:
        try:
            self._direct.send_message(self._message(name, target_system_id=self._system_id,
                                                    fields_json=json.dumps(fields)))
        except Exception as exc:  # MavlinkDirectError: the link is going; the next one may pass
            self._log(f"{name} not sent: {exc}")

    def _on_timesync(self, message, _user) -> None:
        now_ns = time.monotonic_ns()
        fields = json.loads(message.fields_json)
        tc1, ts1 = int(fields.get("tc1", 0)), int(fields.get("ts1", 0))
        if tc1 == 0:  # PX4 asks: answer at once with our clock (its offset estimate is PX4 - ours)
            self._send("TIMESYNC", {"tc1": now_ns, "ts1": ts1, "target_system": message.system_id,
                                    "target_component": message.component_id})
            rtt = self.rtt_p50_s()
            with self._lock:
                reset = self.px4.request(ts1 / 1e3, now_ns / 1e3, rtt_ok=rtt is not None and rtt * 1e6 < MAX_RTT_US)
                slow_down = self._fast and self.px4.samples >= CONVERGENCE_WINDOW + 100
                self._fast = (self._fast and not slow_down) or reset
                jump_ms = self.px4.last_jump_us / 1e3
            if reset:
                self._log(f"PX4's clock jumped {jump_ms:+.0f} ms against ours (a stall): PX4 resets its time sync and "
                          f"dates vision on arrival until {CONVERGENCE_WINDOW} more answers; asking for them at "
                          f"{FAST_TIMESYNC_HZ:g} Hz")
                self.request_rate(FAST_TIMESYNC_HZ)
            elif slow_down:
                self.request_rate(0.0)
        elif 0 < now_ns - ts1 < 5_000_000_000:  # PX4's answer to one of ours (ts1: our clock when we asked)
            with self._lock:
                self.rtt_s.append((now_ns - ts1) / 1e9)

    def ask(self) -> None:
        """One request of our own (PX4 answers it with its time): a round-trip sample."""
        self._send("TIMESYNC", {"tc1": 0, "ts1": time.monotonic_ns(), "target_system": self._system_id,
                                "target_component": 1})

    def request_rate(self, rate_hz: float) -> None:
        """Ask PX4 to send TIMESYNC requests at ``rate_hz`` (0: its default for the link; SET_MESSAGE_INTERVAL)."""
        with self._lock:
            self._fast = rate_hz > 0
        self._send("COMMAND_LONG", {"target_system": self._system_id, "target_component": 1,
                                    "command": MAV_CMD_SET_MESSAGE_INTERVAL, "confirmation": 0,
                                    "param1": MAVLINK_MSG_ID_TIMESYNC, "param2": 1e6 / rate_hz if rate_hz else 0.0,
                                    "param3": 0.0, "param4": 0.0, "param5": 0.0, "param6": 0.0, "param7": 0.0})

    def rtt_p50_s(self) -> float | None:
        with self._lock:
            rtts = sorted(self.rtt_s)
        return rtts[len(rtts) // 2] if rtts else None

    def px4_converged(self) -> bool:
        """Whether PX4 dates vision by the capture time now, as PX4's Timesync counts (:mod:`flight.px4_timesync`)."""
        with self._lock:
            return self.px4.converged

    def px4_samples(self) -> int:
        """PX4's time-sync samples since it last (re)started counting (it converges at 500)."""
        with self._lock:
            return self.px4.samples

    def close(self) -> None:
        self._direct.unsubscribe_message(self._handle)


class GatewayPreflight:
    """The gateway's preflight: every ``preflight_period_s`` it judges whether the vehicle may arm from what the
    gateway (``link``: :class:`services.px4_gateway.Px4Link`) knows and what the bus shows, reads the vehicle's
    parameters again every ``preflight_params_s`` while it is disarmed, publishes the verdict
    (:class:`runtime.schema.PreflightMsg`) and is the arm command's gate."""

    def __init__(self, link) -> None:
        self.link = link
        self.watch, self.certificate = BusWatch(), CertificateCheck()
        self.params: tuple[dict, str] = ({}, "not read yet")
        self.params_read_s = -math.inf
        self.verdict: Verdict | None = None
        self.verdict_s = -math.inf
        self.lock = threading.Lock()  # one check at a time (the 1 Hz loop, a command)
        self.override, self.override_s = "", -math.inf  # an operator's arm on a no-go, carried while it flies

    def param_set(self, args: dict) -> tuple[bool, str]:
        """``param_set {name, value}``: one parameter of the table (flight/px4_params.py) set on the vehicle over
        MAVLink (MAVSDK's Param, PARAM_SET), disarmed only; the next preflight reads it back."""
        from mavsdk.plugins.param import ParamError

        from flight.px4_params import row

        link = self.link
        name, value = args.get("name"), args.get("value")
        try:
            p = row(str(name))
        except KeyError:
            return False, f"param_set: {name!r} is not in the parameter table (flight/px4_params.py; others: QGroundControl)"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return False, f"param_set: value must be a number, got {value!r}"
        if p.kind == "int32" and value != int(value):
            return False, f"param_set: {p.name} is an integer, got {value!r}"
        if link.tele["armed"]:
            return False, "param_set: the vehicle is armed (disarm first)"
        try:
            if p.kind == "int32":
                link.param.set_param_int(p.name, int(value))
            else:
                link.param.set_param_float(p.name, float(value))
        except ParamError as exc:
            return False, f"param_set {p.name} {value:g}: refused by the vehicle: {exc.result.name}"
        self.params_read_s = -math.inf  # the next check reads them all again
        link.node.event("info", f"param_set {p.name} {value:g} (operator)")
        return True, f"{p.name} set to {value:g} on the vehicle"

    def arm_gate(self, override: bool) -> str:
        """Why an arm command is refused ("" when it may go on): the newest preflight verdict (a fresh check if it
        is older than ``preflight_fresh_s``, or if it says no-go: what failed may have passed since, as PX4's own
        checks do ~2 s after the motion capture starts) says no-go and the operator did not override it. An
        override is an event and goes into the published verdict (both recorded)."""
        link = self.link
        verdict = self.verdict
        fresh = verdict is not None and time.monotonic() - self.verdict_s <= link.config.preflight_fresh_s
        if override and not fresh:  # no verdict to override yet: said so, not waited for
            link.node.event("warning", "armed by the operator's override before preflight had judged the vehicle")
            return ""
        if not fresh or not verdict.go:
            verdict = self.check()
        if verdict.go:
            return ""
        bad = verdict.no_go()
        items = ("; ".join(f"{i.name}: {i.found}" + (f" → {i.fix}" if i.fix else "") for i in bad) if len(bad) <= 2
                 else ", ".join(i.name for i in bad))
        if override:
            note = f"armed on a preflight NO-GO by the operator's override: {items}"
            link.node.event("warning", note)
            self.override, self.override_s = note, time.monotonic()
            self._publish(verdict, self.verdict_s)
            return ""
        return (f"arm refused: preflight NO-GO: {items} (`neso preflight` prints every item; `neso cmd px4_gateway "
                "arm override=true` arms anyway, logged and recorded)")

    def check(self, *, read_params: bool = False) -> Verdict:
        """Judge now (:func:`flight.preflight.preflight`) from what the gateway knows, reading the vehicle's
        parameters first when asked or when the last read is older than ``preflight_params_s`` and it is
        disarmed; publish the verdict."""
        link = self.link
        with self.lock:
            now = time.monotonic()
            stale = now - self.params_read_s > link.config.preflight_params_s and link.tele["armed"] is not True
            if link.param is not None and (read_params or stale):
                self.params = read_parameters(link.param)
                self.params_read_s = time.monotonic()
            verdict = preflight(self._inputs(), PreflightConfig(pose_lost_after_s=link.config.pose_lost_after_s))
            self.verdict, self.verdict_s = verdict, time.monotonic()
            self._publish(verdict, self.verdict_s)
            return verdict

    def _inputs(self) -> PreflightInputs:
        link = self.link
        t, now = link.tele, time.monotonic()
        connected = link.system is not None and link.system.is_connected()
        ts = link.timesync
        rtt = ts.rtt_p50_s() if ts is not None else None
        with link.node.lock:
            pose, pose_s = link.last_pose, link.core.last_pose_s
            delay = link.core.delay_to_vehicle_ms((rtt or 0.0) / 2)
            mocap = self.watch.source_counters()
            network = self.watch.network
        offset = height = None
        if pose is not None and pose_s is not None and now - pose_s < 0.5 and t.get("local_position_ok"):
            x, y, z = pose.pos_enu_m
            n, e, d = t["pos_ned"]
            offset, height = math.dist((n, e), (y, x)), -d - z
        params, error = self.params
        return PreflightInputs(
            connected=connected, autopilot=t["autopilot"], armable=t.get("armable"),
            armable_why=link.px4_warning() if t.get("armable") is False else "", params=params,
            params_error=error if connected else "", local_position_ok=t.get("local_position_ok"),
            ev_offset_m=offset, ev_height_offset_m=height, origin_alt_m=t.get("origin_alt_m"), mocap=mocap,
            state_age_s=now - pose_s if pose_s is not None else math.inf,
            services=self.watch.services(link.node.alive_services(), now), delay_ms=delay,
            px4_uses_capture_time=ts is not None and ts.px4_converged(), time_sync_answers=ts.px4_samples() if ts else 0,
            certificate=self.certificate.verdict(network),
            battery_remaining=t["battery"] if math.isfinite(t["battery"]) else -1.0,
            battery_v=t["battery_v"] if math.isfinite(t["battery_v"]) else 0.0)

    def _publish(self, verdict: Verdict, checked_s: float) -> None:
        """The verdict on the bus; an override goes with every one until the vehicle is disarmed again (10 s after it
        at the least), so a flight's recording has it however long after the arm the vehicle took off."""
        now = time.monotonic()
        if self.override and self.link.tele["armed"] is False and now - self.override_s > 10.0:
            self.override = ""
        self.link.node.publisher("preflight")(PreflightMsg(stamp_s=now, checked_s=checked_s, go=verdict.go,
                                                           items=verdict.as_items(), override=self.override[:512]))

    def loop(self) -> None:
        link = self.link
        while not link.node.wait(link.config.preflight_period_s):
            if link.timesync is not None:
                link.timesync.ask()
            try:
                self.check()
            except Exception as exc:  # a check must never stop the gateway: reported, tried again next second
                link.node.event("error", f"preflight check failed: {type(exc).__name__}: {exc}")
