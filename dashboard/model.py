"""What the dashboard knows, per vehicle, fed by decoded bus messages (pure: no I/O, no viser).

:class:`FleetModel` routes each message by the vehicle in its key to a :class:`VehicleModel`.
A vehicle model keeps one row per sample (``seq``) in a ring: the state, the reference, the
estimate, the setpoint and the truth that belong to the same sample land in the same row,
whatever order they arrive in. The figures are derived from the rows of the last
``window_s`` seconds of the source's clock:

- tracking error RMS (z and 3D, m): ``state − reference`` over the rows that have both;
- loop rate (Hz): setpoints per second of their publication stamps;
- loop latency (ms): setpoint ``stamp_s − state_stamp_s`` (state published → setpoint published),
  p50/p99; bus → dashboard (ms): arrival here − the state's ``stamp_s`` (same machine only);
- deadline misses and local-ESO fall-backs in the last minute (the services' health ``counters``);
- the stability certificate as the estimator reports it (``NetworkMsg.certificate``: the verdict of the
  process that applies changes; the page computes none, :meth:`VehicleModel.certificate`), and
  :func:`certificate_shown`, the one place that says what the page shows for it;
- the status line (:func:`status_line`): source, armed/mode, segment, pathway, network,
  certificate, recording, link, each with a level the page colours.

Events are grouped: repeats of one message (numbers aside) are one line with a count.

Times: ``stamp_s`` and arrival times are ``time.monotonic()`` seconds; ``t_s`` is the source's clock.
"""
from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from runtime.schema import EstimateMsg, EventMsg, HealthMsg, NetworkMsg, ReferenceMsg, SetpointMsg, StateMsg, TruthMsg

# one row per sample: these columns, NaN until the message that fills them arrives (angles in rad)
COLUMNS = ("t", "x", "y", "z", "ref_x", "ref_y", "ref_z", "f_n_z", "df_hat_z", "f_hat_z", "truth_dist_z", "thrust_n",
           "roll", "pitch", "roll_sp", "pitch_sp")
_COL = {name: i for i, name in enumerate(COLUMNS)}
RING_ROWS = 8192  # 164 s at 50 Hz, 16 s at 500 Hz
AHEAD_SAMPLES = 50  # a sample's estimate/setpoint/reference/truth may come before its state, by less than this
STALE_HEALTH_S = 3.0  # a service whose last health report is older than this is shown stale
COUNTER_WINDOW_S = 60.0  # misses and fall-backs are counted over the last minute
EVENT_GROUPS = 40  # distinct event messages kept
LEVELS = ("ok", "info", "warn", "bad", "off")  # of a status item: green, blue, amber, red, grey


@dataclass(frozen=True)
class Certificate:
    """The stability certificate the estimator reports for what flies (see :mod:`neso.certificate`).
    ``lipschitz_phys`` and ``max_lipschitz_phys`` in (m/s²) per unit z; ``margin`` their difference;
    ``bound_cm``/``pdeso_bound_cm``: the eventual |e_z| bound for the segment being flown, the network's and
    PD+ESO's (NaN when the estimator states none); ``segment``: which."""

    holds: bool
    margin: float
    max_lipschitz_phys: float
    lipschitz_phys: float
    text: str
    bound_cm: float = math.nan
    pdeso_bound_cm: float = math.nan
    segment: str = ""

    @staticmethod
    def of(report: dict) -> "Certificate | None":
        """From ``NetworkMsg.certificate`` (None when it is not a complete verdict)."""
        try:
            return Certificate(bool(report["holds"]), float(report["margin"]), float(report["max_certified"]),
                               float(report["lipschitz_phys"]), str(report["text"]),
                               _number(report.get("segment_bound_cm")), _number(report.get("segment_pdeso_bound_cm")),
                               str(report.get("segment", "")))
        except (KeyError, TypeError, ValueError):
            return None

    @property
    def bound_text(self) -> str:
        """``|e_z| ≤ 2.1 cm (PD+ESO 1.4, hover)``, or "" without a bound."""
        if not math.isfinite(self.bound_cm):
            return ""
        where = f", {self.segment}" if self.segment else ""
        return f"|e_z| ≤ {self.bound_cm:.3g} cm (PD+ESO {self.pdeso_bound_cm:.3g}{where})"


def _number(v) -> float:
    return float(v) if isinstance(v, (int, float)) else math.nan


@dataclass(frozen=True)
class CertificateShown:
    """What the status line and the figures show for the certificate: ``word`` (HOLDS, FAILS,
    computing…, unknown), ``text`` (the detail) and ``level`` (see :data:`LEVELS`)."""

    word: str
    text: str
    level: str
    certificate: Certificate | None = None


def certificate_shown(v: "VehicleModel") -> CertificateShown:
    """The one answer to "is the flight certified?" the page shows (status line and panel): the
    estimator's verdict, never one computed here."""
    cert = v.certificate()
    if cert is None:
        return CertificateShown("waiting…", "waiting for the estimator's network report", "off")
    text = f"{cert.bound_text} — {cert.text}" if cert.bound_text else cert.text
    return CertificateShown("HOLDS" if cert.holds else "FAILS", text, "ok" if cert.holds else "bad", cert)


@dataclass
class ServiceHealth:
    alive: bool = False
    health: HealthMsg | None = None
    received_s: float = -1.0

    def stale(self, now_s: float) -> bool:
        return self.health is None or now_s - self.received_s > STALE_HEALTH_S


@dataclass
class EventGroup:
    """Repeats of one event message (numbers aside): the newest text, how many, first/last arrival."""

    service: str
    level: str
    text: str
    count: int
    first_s: float
    last_s: float


_NUMBER = re.compile(r"[-+]?\d+(\.\d+)?")


def event_key(msg: EventMsg) -> tuple[str, str, str]:
    """Events that differ only in their numbers (sample, ms, count) are repeats of one message."""
    return msg.service, msg.level, _NUMBER.sub("#", msg.text)


@dataclass
class VehicleModel:
    """One vehicle's samples, figures and status (see module docstring)."""

    name: str
    window_s: float = 10.0
    rows: np.ndarray = field(default_factory=lambda: np.full((RING_ROWS, len(COLUMNS)), np.nan))
    row_seq: np.ndarray = field(default_factory=lambda: np.full(RING_ROWS, -1, dtype=np.int64))
    last_seq: int = -1
    flights: int = 0
    latest: dict = field(default_factory=dict)  # topic → newest message
    received: dict = field(default_factory=dict)  # topic → arrival time of the newest
    setpoint_stamps_s: deque = field(default_factory=lambda: deque(maxlen=2000))
    loop_latency_s: deque = field(default_factory=lambda: deque(maxlen=1000))
    bus_latency_s: deque = field(default_factory=lambda: deque(maxlen=1000))
    params: dict = field(default_factory=dict)  # service → values
    param_notes: dict = field(default_factory=dict)  # service → last note
    services: dict = field(default_factory=dict)  # service → ServiceHealth
    events: dict = field(default_factory=dict)  # event_key → EventGroup, oldest first
    counters: dict = field(default_factory=dict)  # (service, counter) → deque of (arrival s, value)
    trail: deque = field(default_factory=lambda: deque(maxlen=1500))
    ref_trail: deque = field(default_factory=lambda: deque(maxlen=1500))

    # -- ingest ----------------------------------------------------------------------------
    def _row(self, seq: int) -> np.ndarray:
        i = seq % RING_ROWS
        if self.row_seq[i] != seq:
            self.row_seq[i] = seq
            self.rows[i] = np.nan
        return self.rows[i]

    def _new_flight_if(self, seq: int) -> None:
        """A state ``seq`` far below the newest means the source started a new flight."""
        if self.last_seq >= 0 and seq < self.last_seq - 5:
            self.flights += 1
            self.rows[:] = np.nan
            self.row_seq[:] = -1
            self.trail.clear()
            self.ref_trail.clear()
            self.setpoint_stamps_s.clear()
            self.last_seq = -1

    def _of_an_older_flight(self, seq: int) -> bool:
        """A sample's non-state message far ahead of every state of this flight: it answers a state
        of the flight before a restart (arriving late), and its row would hold that flight's clock."""
        return seq > self.last_seq + AHEAD_SAMPLES

    def ingest(self, topic: str, msg, received_s: float) -> None:
        self.latest[topic] = msg
        self.received[topic] = received_s
        if not isinstance(msg, StateMsg) and isinstance(getattr(msg, "seq", None), int) and \
                self._of_an_older_flight(msg.seq):
            return
        if isinstance(msg, StateMsg):
            self._new_flight_if(msg.seq)
            self.last_seq = max(self.last_seq, msg.seq)
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["x"]], r[_COL["y"]], r[_COL["z"]] = msg.pos_enu_m
            r[_COL["roll"]], r[_COL["pitch"]] = msg.roll_rad, msg.pitch_rad
            self.trail.append(msg.pos_enu_m)
            self.bus_latency_s.append(received_s - msg.stamp_s)
        elif isinstance(msg, ReferenceMsg):
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["ref_x"]], r[_COL["ref_y"]], r[_COL["ref_z"]] = msg.pos_enu_m
            self.ref_trail.append(msg.pos_enu_m)
        elif isinstance(msg, EstimateMsg):
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["f_n_z"]], r[_COL["df_hat_z"]], r[_COL["f_hat_z"]] = (
                msg.f_n_mps2[2], msg.delta_f_hat_mps2[2], msg.f_hat_mps2[2])
        elif isinstance(msg, SetpointMsg):
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["thrust_n"]] = msg.thrust_n
            r[_COL["roll_sp"]], r[_COL["pitch_sp"]] = msg.roll_rad, msg.pitch_rad
            self.setpoint_stamps_s.append(msg.stamp_s)
            self.loop_latency_s.append(msg.stamp_s - msg.state_stamp_s)
        elif isinstance(msg, TruthMsg):
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["truth_dist_z"]] = msg.disturbance_acc_enu_mps2[2]

    def ingest_health(self, msg: HealthMsg, received_s: float) -> None:
        self.services.setdefault(msg.service, ServiceHealth()).health = msg
        self.services[msg.service].received_s = received_s
        for name, value in msg.counters.items():
            history = self.counters.setdefault((msg.service, name), deque())
            history.append((received_s, value))
            while len(history) > 2 and history[1][0] <= received_s - COUNTER_WINDOW_S:
                history.popleft()  # keep one report at or before the window's start as its baseline

    def ingest_alive(self, service: str, alive: bool) -> None:
        self.services.setdefault(service, ServiceHealth()).alive = alive

    def ingest_params(self, service: str, values: dict, note: str = "") -> None:
        self.params[service] = dict(values)
        if note:
            self.param_notes[service] = note

    def ingest_event(self, msg: EventMsg, received_s: float = 0.0) -> None:
        key = event_key(msg)
        group = self.events.pop(key, None)
        if group is None:
            group = EventGroup(msg.service, msg.level, msg.text, 0, received_s, received_s)
            while len(self.events) >= EVENT_GROUPS:
                self.events.pop(next(iter(self.events)))
        group.text, group.count, group.last_s = msg.text, group.count + 1, received_s
        self.events[key] = group  # newest last

    def recent_events(self, n: int) -> list[EventGroup]:
        """The ``n`` most recently repeated event groups, newest first."""
        return list(self.events.values())[::-1][:n]

    def per_minute(self, service: str, counter: str, now_s: float) -> tuple[float, float]:
        """(how many, over how many seconds ≤ 60) of ``service``'s ``counter`` lately; (NaN, 0)
        without two reports. A restarted service's counter starts again from 0."""
        history = self.counters.get((service, counter))
        if not history or len(history) < 2:
            return math.nan, 0.0
        base_s, base = history[0]
        for t, value in history:
            if t <= now_s - COUNTER_WINDOW_S:
                base_s, base = t, value
        newest_s, newest = history[-1]
        return (newest - base if newest >= base else newest), min(COUNTER_WINDOW_S, newest_s - base_s)

    # -- figures ---------------------------------------------------------------------------
    def window(self) -> dict[str, np.ndarray]:
        """The rows of the last ``window_s`` seconds of source time, ordered by ``seq``,
        as column name → array (NaN where a message is missing)."""
        if self.last_seq < 0:
            return {name: np.zeros(0) for name in COLUMNS}
        valid = self.row_seq >= 0
        order = np.argsort(self.row_seq[valid])
        rows = self.rows[valid][order]
        t = rows[:, _COL["t"]]
        newest = np.nanmax(t) if np.isfinite(t).any() else 0.0
        keep = np.isfinite(t) & (t >= newest - self.window_s)
        rows = rows[keep]
        return {name: rows[:, i] for i, name in enumerate(COLUMNS)}

    def tracking_rms_m(self) -> tuple[float, float]:
        """(z, 3D) RMS of state − reference over the window (NaN without both)."""
        w = self.window()
        both = np.isfinite(w["z"]) & np.isfinite(w["ref_z"])
        if not both.any():
            return math.nan, math.nan
        ez = w["z"][both] - w["ref_z"][both]
        e3 = np.stack([w[c][both] - w["ref_" + c][both] for c in ("x", "y", "z")])
        return float(np.sqrt(np.mean(ez**2))), float(np.sqrt(np.mean(np.sum(e3**2, axis=0))))

    def loop_rate_hz(self, span_s: float = 2.0) -> float:
        """Setpoints per second over the last ``span_s`` seconds of their stamps."""
        stamps = np.array(self.setpoint_stamps_s)
        if len(stamps) < 2:
            return 0.0
        recent = stamps[stamps >= stamps[-1] - span_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return float((len(recent) - 1) / (recent[-1] - recent[0]))

    @staticmethod
    def _percentiles_ms(values) -> tuple[float, float]:
        if not values:
            return math.nan, math.nan
        a = np.array(values) * 1e3
        return float(np.percentile(a, 50)), float(np.percentile(a, 99))

    def loop_latency_ms(self) -> tuple[float, float]:
        return self._percentiles_ms(self.loop_latency_s)

    def bus_latency_ms(self) -> tuple[float, float]:
        return self._percentiles_ms(self.bus_latency_s)

    def airborne(self, now_s: float) -> bool:
        """The controller is tracking a reference (it publishes none while idle on the ground)."""
        truth = self.latest.get("truth")
        if truth is not None and now_s - self.received.get("truth", -1e9) < 1.0 and truth.on_ground:
            return False
        return now_s - self.received.get("reference", -1e9) < 1.0

    def lipschitz(self) -> tuple[float, float]:
        """(L_N physical, L_N normalised) certified of the estimator's active network (NaN if unknown)."""
        net = self.latest.get("network")
        if not isinstance(net, NetworkMsg):
            return math.nan, math.nan
        return float(net.active.get("lipschitz_phys", math.nan)), float(net.active.get("lipschitz_norm", math.nan))

    def certificate(self) -> Certificate | None:
        """The estimator's verdict for what flies now (None before its first network report)."""
        net = self.latest.get("network")
        return Certificate.of(net.certificate) if isinstance(net, NetworkMsg) else None

    def gains(self) -> dict[str, float] | None:
        c = self.params.get("controller", {})
        need = ("kp_xy", "kd_xy", "kp_z", "kd_z")
        return {k: float(c[k]) for k in need} if all(k in c for k in need) else None

    def omega_o_rps(self) -> float:
        return float(self.params.get("estimator", {}).get("omega_o_rps", math.nan))


class FleetModel:
    """Every vehicle on the bus: :meth:`ingest` takes (kind, key, message, arrival time)."""

    def __init__(self, window_s: float = 10.0) -> None:
        self.window_s = window_s
        self.vehicles: dict[str, VehicleModel] = {}
        self.rejected = 0
        self.dropped = 0  # samples the watcher's inbox let go (it was full)
        self.last_rejection = ""

    def vehicle(self, name: str) -> VehicleModel:
        if name not in self.vehicles:
            self.vehicles[name] = VehicleModel(name, window_s=self.window_s)
        return self.vehicles[name]

    def reject(self, key: str, reason: str) -> None:
        self.rejected += 1
        self.last_rejection = f"{key}: {reason}"

    def ingest(self, vehicle: str, kind: str, msg, received_s: float, service: str = "") -> None:
        v = self.vehicle(vehicle)
        if kind == "health":
            v.ingest_health(msg, received_s)
        elif kind == "params":
            v.ingest_params(msg.service, msg.values, msg.note)
        elif kind == "event":
            v.ingest_event(msg, received_s)
        elif kind == "alive":
            v.ingest_alive(service, bool(msg))
        else:
            v.ingest(kind, msg, received_s)


# -- the status line ------------------------------------------------------------------------------
STATUS_SLOTS = ("source", "armed", "segment", "pathway", "network", "certificate", "recording", "link")
FRESH_S = 1.0  # a stream whose newest message is older than this has stopped
TELEMETRY_FRESH_S = 2.0


@dataclass(frozen=True)
class StatusItem:
    """One slot of the status line: ``text`` and its ``level`` (see :data:`LEVELS`), ``detail``
    for a tooltip."""

    slot: str
    text: str
    level: str
    detail: str = ""


def _fresh(v: VehicleModel, topic: str, now_s: float, within_s: float = FRESH_S) -> bool:
    return topic in v.latest and now_s - v.received.get(topic, -1e9) < within_s


def status_line(v: VehicleModel, now_s: float, cert: CertificateShown, *, dashboard_dropped: int = 0) -> list[StatusItem]:
    """The flight at a glance, in :data:`STATUS_SLOTS` order (pure)."""
    state, est, ref = v.latest.get("state"), v.latest.get("estimate"), v.latest.get("reference")
    sp, tel, rec, net = (v.latest.get(k) for k in ("setpoint", "telemetry", "recording", "network"))
    items = []
    # source: live (sim / mocap) or a replayed flight
    if state is None:
        items.append(StatusItem("source", "NO DATA", "bad", "no state sample from this vehicle yet"))
    elif not _fresh(v, "state", now_s):
        items.append(StatusItem("source", f"NO DATA {now_s - v.received['state']:.0f} s", "bad",
                                "the state stream stopped"))
    elif state.source == "replay":
        items.append(StatusItem("source", "REPLAY", "info", "a recorded flight published again (neso replay --to-bus)"))
    else:
        items.append(StatusItem("source", f"LIVE · {state.source}", "ok", f"state samples from the {state.source}"))
    # armed / mode: the vehicle's own word (PX4 telemetry) when there is one, else the controller's
    flying = _fresh(v, "reference", now_s)
    if tel is not None and _fresh(v, "telemetry", now_s, TELEMETRY_FRESH_S):
        mode = tel.flight_mode.upper()
        if tel.failsafe:
            items.append(StatusItem("armed", f"FAILSAFE {tel.failsafe.upper()} · {mode}", "bad",
                                    "the PX4 gateway acted on its own (stale setpoints)"))
        elif tel.armed:
            items.append(StatusItem("armed", f"ARMED · {mode}{' · in air' if tel.in_air else ''}", "info",
                                    "PX4 telemetry"))
        else:
            items.append(StatusItem("armed", f"disarmed · {mode}", "off", "PX4 telemetry"))
    elif tel is not None and v.services.get("px4_gateway", ServiceHealth()).alive:
        items.append(StatusItem("armed", "PX4 SILENT", "bad", "the gateway runs, but no telemetry for 2 s"))
    else:
        items.append(StatusItem("armed", "flying (sim)" if flying else "idle (sim)", "info" if flying else "off",
                                "no PX4 on the bus: the controller's state"))
    # mission segment
    segment = ref.segment if ref is not None and flying else "idle"
    items.append(StatusItem("segment", segment, {"hold": "warn", "idle": "off"}.get(segment, "info"),
                            "the controller's mission segment"))
    # pathway, and who flies f̂
    if est is None or not _fresh(v, "estimate", now_s):
        items.append(StatusItem("pathway", "NO ESTIMATES", "bad" if state is not None else "off",
                                "the estimator publishes nothing"))
    elif sp is not None and sp.estimate_source == "local_eso" and _fresh(v, "setpoint", now_s):
        items.append(StatusItem("pathway", "LOCAL ESO", "bad", "the controller flies its own ESO: estimates late"))
    else:
        items.append(StatusItem("pathway", est.pathway, "warn" if est.pathway in ("nn", "none") else "ok",
                                "nn / none: no online correction of the network"))
    # network
    active = net.active.get("id") if net is not None else (est.network_id if est is not None else None)
    if active is None:
        items.append(StatusItem("network", "network –", "off", "no network report yet"))
    else:
        shadow = net is not None and bool(net.candidate)
        items.append(StatusItem("network", f"{active}{' + candidate' if shadow else ''}", "info" if shadow else "ok",
                                "candidate in shadow" if shadow else "the network the estimator flies"))
    # certificate
    bound = cert.certificate.bound_cm if cert.certificate is not None else math.nan
    items.append(StatusItem("certificate", f"cert {cert.word}" + (f" ≤{bound:.2g} cm" if math.isfinite(bound) else ""),
                            cert.level, cert.text))
    # recording
    if rec is None:
        items.append(StatusItem("recording", "no recorder", "warn", "nothing records this vehicle"))
    elif now_s - v.received.get("recording", -1e9) > STALE_HEALTH_S:
        items.append(StatusItem("recording", "recorder silent", "bad", "no recorder status for 3 s"))
    elif rec.recording:
        items.append(StatusItem("recording", f"● REC {rec.duration_s:.0f} s", "warn" if rec.dropped else "ok",
                                f"{rec.path}, dropped {rec.dropped}"))
    else:
        items.append(StatusItem("recording", "not recording", "off", "records from take-off to landing"))
    # link: services alive and reporting, loop rate, deadline misses and local-ESO fall-backs lately
    down = sorted(n for n, sh in v.services.items() if not sh.alive)
    stale = sorted(n for n, sh in v.services.items() if sh.alive and sh.stale(now_s))
    misses, span = v.per_minute("source", "deadline_misses", now_s)
    falls, _ = v.per_minute("controller", "local_eso_fallbacks", now_s)
    rate = v.loop_rate_hz()
    text = f"{rate:.0f} Hz" + (f" · {misses:.0f} miss/min" if math.isfinite(misses) else "")
    detail = (f"deadline misses in the last {span:.0f} s: {misses:.0f}; local-ESO fall-backs: "
              f"{falls:.0f}; dashboard inbox dropped {dashboard_dropped}" if math.isfinite(misses) else
              "no miss counts from the source yet")
    if down or stale:
        items.append(StatusItem("link", f"{', '.join(down + stale)} {'DOWN' if down else 'SILENT'}", "bad", detail))
    elif state is None or not _fresh(v, "setpoint", now_s):
        items.append(StatusItem("link", "no loop", "off" if state is None else "bad", "no setpoints"))
    elif (math.isfinite(misses) and misses > 0) or (math.isfinite(falls) and falls > 0) or dashboard_dropped:
        items.append(StatusItem("link", text, "warn", detail))
    else:
        items.append(StatusItem("link", text, "ok", detail))
    return items
