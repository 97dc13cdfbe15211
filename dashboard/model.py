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
- the stability certificate as the estimator reports it (``NetworkMsg.certificate``: the verdict of the
  process that applies changes; the page computes none, :meth:`VehicleModel.certificate`).

Times: ``stamp_s`` and arrival times are ``time.monotonic()`` seconds; ``t_s`` is the source's clock.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from runtime.schema import EstimateMsg, EventMsg, HealthMsg, NetworkMsg, ReferenceMsg, SetpointMsg, StateMsg, TruthMsg

# one row per sample: these columns, NaN until the message that fills them arrives
COLUMNS = ("t", "x", "y", "z", "ref_x", "ref_y", "ref_z", "f_n_z", "df_hat_z", "f_hat_z", "truth_dist_z", "thrust_n")
_COL = {name: i for i, name in enumerate(COLUMNS)}
RING_ROWS = 8192  # 164 s at 50 Hz, 16 s at 500 Hz
STALE_HEALTH_S = 3.0  # a service whose last health report is older than this is shown stale


@dataclass(frozen=True)
class Certificate:
    """The stability certificate the estimator reports for what flies (see :mod:`neso.certificate`).
    ``lipschitz_phys`` and ``max_lipschitz_phys`` in (m/s²) per unit z; ``margin`` their difference."""

    holds: bool
    margin: float
    max_lipschitz_phys: float
    lipschitz_phys: float
    text: str

    @staticmethod
    def of(report: dict) -> "Certificate | None":
        """From ``NetworkMsg.certificate`` (None when it is not a complete verdict)."""
        try:
            return Certificate(bool(report["holds"]), float(report["margin"]), float(report["max_certified"]),
                               float(report["lipschitz_phys"]), str(report["text"]))
        except (KeyError, TypeError, ValueError):
            return None


@dataclass
class ServiceHealth:
    alive: bool = False
    health: HealthMsg | None = None
    received_s: float = -1.0

    def stale(self, now_s: float) -> bool:
        return self.health is None or now_s - self.received_s > STALE_HEALTH_S


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
    events: deque = field(default_factory=lambda: deque(maxlen=8))
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

    def ingest(self, topic: str, msg, received_s: float) -> None:
        self.latest[topic] = msg
        self.received[topic] = received_s
        if isinstance(msg, StateMsg):
            self._new_flight_if(msg.seq)
            self.last_seq = max(self.last_seq, msg.seq)
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["x"]], r[_COL["y"]], r[_COL["z"]] = msg.pos_enu_m
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
            self.setpoint_stamps_s.append(msg.stamp_s)
            self.loop_latency_s.append(msg.stamp_s - msg.state_stamp_s)
        elif isinstance(msg, TruthMsg):
            r = self._row(msg.seq)
            r[_COL["t"]] = msg.t_s
            r[_COL["truth_dist_z"]] = msg.disturbance_acc_enu_mps2[2]

    def ingest_health(self, msg: HealthMsg, received_s: float) -> None:
        self.services.setdefault(msg.service, ServiceHealth()).health = msg
        self.services[msg.service].received_s = received_s

    def ingest_alive(self, service: str, alive: bool) -> None:
        self.services.setdefault(service, ServiceHealth()).alive = alive

    def ingest_params(self, service: str, values: dict, note: str = "") -> None:
        self.params[service] = dict(values)
        if note:
            self.param_notes[service] = note

    def ingest_event(self, msg: EventMsg) -> None:
        self.events.append(msg)

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
            v.ingest_event(msg)
        elif kind == "alive":
            v.ingest_alive(service, bool(msg))
        else:
            v.ingest(kind, msg, received_s)
