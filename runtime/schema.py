"""Every key expression and every payload on the bus, in one place.

Keys (one vehicle ``<v>``; several vehicles share a bus under their own prefixes):

====================================  ===============  =============================================
``neso/<v>/state``                    StateMsg         source → estimator, controller (each sample)
``neso/<v>/truth``                    TruthMsg         sim source only: the simulated truth
``neso/<v>/estimate``                 EstimateMsg      estimator → controller (answers state ``seq``)
``neso/<v>/setpoint``                 SetpointMsg      controller → source/vehicle, estimator
``neso/<v>/reference``                ReferenceMsg     controller → anyone watching
``neso/<v>/telemetry``                TelemetryMsg     px4_gateway → anyone watching (vehicle's own report)
``neso/<v>/recording``                RecordingMsg     recorder → anyone watching
``neso/<v>/network``                  NetworkMsg       estimator → anyone watching (active/candidate)
``neso/<v>/replay``                   ReplayMsg        ``neso replay --to-bus`` → anyone watching (not live)
``neso/<v>/preflight``                PreflightMsg     px4_gateway → anyone watching: may the vehicle arm
``neso/<v>/event/<service>``          EventMsg         what a service wants an operator to know
``neso/<v>/health/<service>``         HealthMsg        1 Hz: rate, latency, rejected, staleness
``neso/<v>/alive/<service>``          (liveliness)     token while the service runs
``neso/<v>/param/<service>``          (queryable)      ParamRequest → ParamReply
``neso/<v>/params/<service>``         ParamStateMsg    broadcast when parameters take effect; also a
                                                       queryable: ParamRequest get → ParamReply (read only)
``neso/<v>/cmd/<service>``            (queryable)      CommandRequest → CommandReply
``neso/<v>/offer/<service>``          (queryable)      CommandRequest ``offer`` → CommandReply (a network
                                                       offered; its own key so the ACL can tell it apart)
====================================  ===============  =============================================

Payloads are msgpack maps with ``v`` (schema version) and ``type``; every message class is a
frozen dataclass whose fields carry a validator. :func:`decode` rejects, with
:class:`SchemaError` naming the reason, anything that is not exactly a valid message of the
expected type and version: bad msgpack, wrong type or version, missing or unknown fields,
wrong shapes, non-finite or out-of-range numbers. Each validator also states its rule as a
msgspec type (``wire``); a message whose fields all have one is decoded and checked by msgspec's
compiled decoder (the loop's messages: ~1.5 µs instead of ~8), and anything msgspec refuses goes
through the Python validators, which accept or name the reason exactly as before: the Python
rules are the definition, msgspec only a faster way to accept what they accept. Vectors travel
as lists of float64, so a round trip is bit-exact. ``seq`` is the sample number the message belongs to (a setpoint and
an estimate carry the ``seq`` of the state they answer); ``stamp_s`` is ``time.monotonic()`` at
publication (one clock for every process on a machine: latency is measured with it); ``t_s``
is the time the sample describes (simulation or vehicle time).
"""
from __future__ import annotations

import dataclasses
import math
import re
import sys
from dataclasses import dataclass, field
from typing import Annotated, Any, Callable, ClassVar, Literal

import msgpack
import msgspec
import numpy as np

from neso.types import PATHWAYS, StateMeasurement

SCHEMA_VERSION = 1
ROOT = "neso"
MAX_PAYLOAD_BYTES = 1 << 20
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")

# px4: PX4's own controller (a flight imported from its log); crazyflie: the Crazyflie's own (a NanoBench flight)
ESTIMATE_SOURCES = ("estimator", "local_eso", "px4", "crazyflie")
STATE_SOURCES = ("sim", "mocap", "replay", "px4")  # px4: PX4's own estimate (EKF2), imported from its log
EVENT_LEVELS = ("info", "warning", "error")
LIMIT_M = 1.0e4  # positions and distances beyond this are not a vehicle in a room
LIMIT_MPS = 1.0e3
LIMIT_MPS2 = 1.0e4


class SchemaError(ValueError):
    """A payload that is not a valid message; the text says why."""


def valid_name(name: str, what: str = "name") -> str:
    """A vehicle or service name usable as one key chunk (letters, digits, ``_ . -``)."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{what} {name!r} must be 1–64 of [A-Za-z0-9_.-] not starting with '.' or '-'")
    return name


# -- field validators: value from msgpack → value stored (raise SchemaError) ----------------------
# Each also carries ``wire``: the same rule as a msgspec type (no ``wire``: only Python can say it).
_FLOAT_MAX = sys.float_info.max


def _wire(check: Callable, wire: Any) -> Callable:
    check.wire = wire
    return check


def _number(lo: float = -math.inf, hi: float = math.inf) -> Callable[[Any], float]:
    def check(x: Any) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise SchemaError(f"expected a number, got {type(x).__name__}")
        x = float(x)
        if not math.isfinite(x) or not lo <= x <= hi:
            raise SchemaError(f"{x!r} is outside [{lo}, {hi}] or not finite")
        return x
    # the bounds clipped to the largest finite float exclude ±inf; NaN fails any bound
    return _wire(check, Annotated[float, msgspec.Meta(ge=max(lo, -_FLOAT_MAX), le=min(hi, _FLOAT_MAX))])


def _integer(lo: int = 0, hi: int = 2**63 - 1) -> Callable[[Any], int]:
    def check(x: Any) -> int:
        if isinstance(x, bool) or not isinstance(x, int) or not lo <= x <= hi:
            raise SchemaError(f"expected an integer in [{lo}, {hi}], got {x!r}")
        return x
    return _wire(check, Annotated[int, msgspec.Meta(ge=lo, le=hi)])


MAX_FEATURES = 16  # the longest network input a message carries


def _vector_upto(n_max: int, limit: float) -> Callable[[Any], tuple[float, ...]]:
    """A vector of 0 to ``n_max`` finite numbers within ±``limit``."""
    def check(x: Any) -> tuple[float, ...]:
        if not isinstance(x, (list, tuple)) or len(x) > n_max:
            raise SchemaError(f"expected at most {n_max} numbers")
        return _vector(len(x), limit)(x)
    return _wire(check, Annotated[tuple[_number(-limit, limit).wire, ...], msgspec.Meta(max_length=n_max)])


def _vector(n: int, limit: float) -> Callable[[Any], tuple[float, ...]]:
    element = _number(-limit, limit)

    def check(x: Any) -> tuple[float, ...]:
        if not isinstance(x, (list, tuple)) or len(x) != n:
            raise SchemaError(f"expected a list of {n} numbers, got {type(x).__name__} of length "
                              f"{len(x) if isinstance(x, (list, tuple)) else '-'}")
        return tuple(element(v) for v in x)
    return _wire(check, tuple[(element.wire,) * n])


def _text(choices: tuple[str, ...] | None = None, max_len: int = 256) -> Callable[[Any], str]:
    def check(x: Any) -> str:
        if not isinstance(x, str) or len(x) > max_len:
            raise SchemaError(f"expected a string of at most {max_len} characters, got {type(x).__name__}")
        if choices is not None and x not in choices:
            raise SchemaError(f"{x!r} is not one of {choices}")
        return x
    if choices is not None:
        assert all(len(c) <= max_len for c in choices)
        return _wire(check, Literal[tuple(choices)])
    return _wire(check, Annotated[str, msgspec.Meta(max_length=max_len)])


def _flag(x: Any) -> bool:
    if not isinstance(x, bool):
        raise SchemaError(f"expected true/false, got {type(x).__name__}")
    return x


_flag.wire = bool


def _plain(x: Any, depth: int = 0) -> Any:
    """A msgpack value made of str/int/float/bool/None/list/dict with string keys, at most 4 deep."""
    if depth > 4:
        raise SchemaError("value nested too deeply")
    if x is None or isinstance(x, (bool, int, str)):
        return x
    if isinstance(x, float):
        if not math.isfinite(x):
            raise SchemaError(f"non-finite number {x!r}")
        return x
    if isinstance(x, (list, tuple)):
        return [_plain(v, depth + 1) for v in x]
    if isinstance(x, dict):
        if not all(isinstance(k, str) for k in x):
            raise SchemaError("map keys must be strings")
        return {k: _plain(v, depth + 1) for k, v in x.items()}
    raise SchemaError(f"unsupported value type {type(x).__name__}")


def _mapping(x: Any) -> dict:
    if not isinstance(x, dict):
        raise SchemaError(f"expected a map, got {type(x).__name__}")
    return _plain(x)


def _numbers_by_name(x: Any) -> dict[str, float]:
    if not isinstance(x, dict) or len(x) > 256:
        raise SchemaError("expected a map of at most 256 names to numbers")
    out = {}
    for k, v in x.items():
        if not isinstance(k, str):
            raise SchemaError("map keys must be strings")
        out[k] = _number()(v)
    return out


_numbers_by_name.wire = Annotated[dict[str, _number().wire], msgspec.Meta(max_length=256)]


def f(check: Callable[[Any], Any], **kwargs) -> Any:
    """A message field with its validator."""
    return field(metadata={"check": check}, **kwargs)


# -- messages -------------------------------------------------------------------------------------
class Message:
    """Base of every payload: ``to_bytes`` / ``from_bytes`` with validation."""

    TYPE: ClassVar[str]

    def to_bytes(self) -> bytes:
        body = {"v": SCHEMA_VERSION, "type": self.TYPE}
        for fld in dataclasses.fields(self):
            body[fld.name] = getattr(self, fld.name)
        return msgpack.packb(body, use_bin_type=True)

    @classmethod
    def from_bytes(cls, data: bytes):
        return decode(cls, data)

    @classmethod
    def validate(cls, **values):
        """Build a message from Python values through the same checks a payload goes through."""
        return cls.from_bytes(msgpack.packb({"v": SCHEMA_VERSION, "type": cls.TYPE, **values}, use_bin_type=True))


def decode(cls: type[Message], data: bytes) -> Message:
    """The ``cls`` message in ``data``, or :class:`SchemaError` saying what is wrong."""
    if len(data) > MAX_PAYLOAD_BYTES:
        raise SchemaError(f"payload of {len(data)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    compiled = _COMPILED[cls] if cls in _COMPILED else _COMPILED.setdefault(cls, compile_decoder(cls))
    if compiled is not None:
        try:
            return cls(*msgspec.structs.astuple(compiled.decode(data))[2:])  # [2:]: past v and type
        except Exception:  # msgspec's errors, and UnicodeDecodeError for a bad string: the Python rules decide
            pass  # and say why (or accept what msgspec is stricter about, e.g. ``v`` sent as 1.0)
    return decode_python(cls, data)


_COMPILED: dict[type, Any] = {}


def compile_decoder(cls: type[Message]) -> msgspec.msgpack.Decoder | None:
    """A msgspec decoder for ``cls``'s payloads that accepts only what :func:`decode_python` accepts, giving the
    same values (a struct of ``v``, ``type`` and the fields in order); None when a field's rule has no ``wire``."""
    fields: list[tuple] = [("v", Literal[SCHEMA_VERSION]), ("type", Literal[cls.TYPE])]
    for fld in dataclasses.fields(cls):
        wire = getattr(fld.metadata["check"], "wire", None)
        if wire is None:
            return None
        if fld.default is not dataclasses.MISSING:
            fields.append((fld.name, wire, fld.default))
        elif fld.default_factory is not dataclasses.MISSING:
            fields.append((fld.name, wire, msgspec.field(default_factory=fld.default_factory)))
        else:
            fields.append((fld.name, wire))
    struct = msgspec.defstruct(f"{cls.__name__}Wire", fields, kw_only=True, forbid_unknown_fields=True)
    return msgspec.msgpack.Decoder(struct)


def decode_python(cls: type[Message], data: bytes) -> Message:
    """:func:`decode` by the Python validators alone (the definition of the rules; the reason when refused)."""
    if len(data) > MAX_PAYLOAD_BYTES:
        raise SchemaError(f"payload of {len(data)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    try:
        body = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types for bad bytes
        raise SchemaError(f"not msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(body, dict):
        raise SchemaError(f"payload is a {type(body).__name__}, expected a map")
    if body.get("v") != SCHEMA_VERSION:
        raise SchemaError(f"schema version {body.get('v')!r} is not {SCHEMA_VERSION}")
    if body.get("type") != cls.TYPE:
        raise SchemaError(f"message type {body.get('type')!r} where {cls.TYPE!r} was expected")
    fields = dataclasses.fields(cls)
    names = {fld.name for fld in fields}
    unknown = set(body) - names - {"v", "type"}
    if unknown:
        raise SchemaError(f"unknown fields {sorted(map(str, unknown))}")
    values = {}
    for fld in fields:
        if fld.name not in body:
            if fld.default is not dataclasses.MISSING:
                continue
            if fld.default_factory is not dataclasses.MISSING:
                continue
            raise SchemaError(f"missing field {fld.name!r}")
        try:
            values[fld.name] = fld.metadata["check"](body[fld.name])
        except SchemaError as exc:
            raise SchemaError(f"field {fld.name!r}: {exc}") from None
    return cls(**values)


_SEQ = _integer()
_STAMP = _number(0.0)
_TIME = _number(-1e9, 1e9)
_ANGLE = _number(-4.0, 4.0)  # radians, a little beyond ±π for wrap-around slack
_POS = _vector(3, LIMIT_M)
_VEL = _vector(3, LIMIT_MPS)
_ACC = _vector(3, LIMIT_MPS2)


@dataclass(frozen=True, slots=True)
class StateMsg(Message):
    """A state sample (ENU, SI). ``source``: ``sim``, ``mocap``, ``replay`` (published again from a
    recording) or ``px4`` (PX4's own estimate, imported from its flight log). ``t_s``: the source's clock (the
    world's time; a motion-capture frame's own capture time); ``capture_stamp_s``: the pose's capture on the
    source machine's monotonic clock
    (``stamp_s``'s; 0: unknown), so ``stamp_s - capture_stamp_s`` is how old the pose was when published (the
    world's or Motive's exposure to the bus), which the PX4 gateway carries into ODOMETRY's ``time_usec``."""

    TYPE: ClassVar[str] = "state"
    seq: int = f(_SEQ)
    stamp_s: float = f(_STAMP)
    t_s: float = f(_TIME)
    pos_enu_m: tuple = f(_POS)
    vel_enu_mps: tuple = f(_VEL)
    roll_rad: float = f(_ANGLE)
    pitch_rad: float = f(_ANGLE)
    yaw_rad: float = f(_ANGLE)
    source: str = f(_text(STATE_SOURCES))
    capture_stamp_s: float = f(_STAMP, default=0.0)


@dataclass(frozen=True, slots=True)
class TruthMsg(Message):
    """The simulator's truth at state ``seq``: position, velocity, the disturbance the nominal
    model does not explain (m/s²), ground contact."""

    TYPE: ClassVar[str] = "truth"
    seq: int = f(_SEQ)
    stamp_s: float = f(_STAMP)
    t_s: float = f(_TIME)
    pos_enu_m: tuple = f(_POS)
    vel_enu_mps: tuple = f(_VEL)
    disturbance_acc_enu_mps2: tuple = f(_ACC)
    on_ground: bool = f(_flag)
    crashed: bool = f(_flag)
    scenario: str = f(_text())


@dataclass(frozen=True, slots=True)
class EstimateMsg(Message):
    """f̂ = f_N + Δf̂ (m/s², ENU) for state ``seq``; ``z`` the network input (its feature set's size;
    empty without a network).
    ``warm_ticks``: samples since the estimator (re)started (its observer converges over the
    first ones)."""

    TYPE: ClassVar[str] = "estimate"
    seq: int = f(_SEQ)
    stamp_s: float = f(_STAMP)
    t_s: float = f(_TIME)
    f_hat_mps2: tuple = f(_ACC)
    f_n_mps2: tuple = f(_ACC)
    delta_f_hat_mps2: tuple = f(_ACC)
    z: tuple = f(_vector_upto(MAX_FEATURES, 1e6))
    pathway: str = f(_text(PATHWAYS))
    network_id: str = f(_text())
    warm_ticks: int = f(_SEQ)


@dataclass(frozen=True, slots=True)
class SetpointMsg(Message):
    """The attitude setpoint answering state ``seq`` (ENU/FLU, ZYX Euler, rad), with what the
    estimator must be told acted over the next period: the nominal acceleration it produces
    (m/s²) and the commanded thrust (N). ``estimate_source`` says which f̂ the controller used
    (``px4``: none of ours, PX4's own controller commanded it: a flight imported from its log; ``crazyflie``:
    the Crazyflie firmware's own, a NanoBench flight imported from its CSV).
    ``state_stamp_s`` echoes the state's ``stamp_s`` (end-to-end latency); ``estimate_stamp_s``
    the used estimate's ``stamp_s`` (0: none, the local ESO flew), so a late setpoint tells
    which process took the time."""

    TYPE: ClassVar[str] = "setpoint"
    seq: int = f(_SEQ)
    stamp_s: float = f(_STAMP)
    state_stamp_s: float = f(_STAMP)
    t_s: float = f(_TIME)
    roll_rad: float = f(_ANGLE)
    pitch_rad: float = f(_ANGLE)
    yaw_rad: float = f(_ANGLE)
    thrust_norm: float = f(_number(0.0, 1.0))
    thrust_n: float = f(_number(0.0, 1e4))
    acc_cmd_enu_mps2: tuple = f(_ACC)
    estimate_source: str = f(_text(ESTIMATE_SOURCES))
    estimate_stamp_s: float = f(_STAMP, default=0.0)


@dataclass(frozen=True, slots=True)
class ReferenceMsg(Message):
    """The reference the controller tracked at state ``seq``; ``segment`` names the mission step."""

    TYPE: ClassVar[str] = "reference"
    seq: int = f(_SEQ)
    stamp_s: float = f(_STAMP)
    t_s: float = f(_TIME)
    pos_enu_m: tuple = f(_POS)
    vel_enu_mps: tuple = f(_VEL)
    acc_enu_mps2: tuple = f(_ACC)
    yaw_rad: float = f(_ANGLE)
    segment: str = f(_text())


@dataclass(frozen=True, slots=True)
class EventMsg(Message):
    TYPE: ClassVar[str] = "event"
    stamp_s: float = f(_STAMP)
    service: str = f(_text())
    level: str = f(_text(EVENT_LEVELS))
    text: str = f(_text(max_len=4096))


@dataclass(frozen=True, slots=True)
class HealthMsg(Message):
    """Once a second. ``rate_hz``: outputs per second; ``latency_*_ms``: input received → output
    published inside the service; ``rejected``: malformed payloads per input key since start;
    ``staleness_s``: seconds since the last valid message per input (−1: none yet); ``counters``:
    what the service counts since it started (``deadline_misses``, ``local_eso_fallbacks``, …)."""

    TYPE: ClassVar[str] = "health"
    stamp_s: float = f(_STAMP)
    service: str = f(_text())
    pid: int = f(_SEQ)
    uptime_s: float = f(_number(0.0))
    ticks: int = f(_SEQ)
    rate_hz: float = f(_number(0.0))
    latency_p50_ms: float = f(_number(0.0))
    latency_p99_ms: float = f(_number(0.0))
    rejected: dict = f(_numbers_by_name)
    staleness_s: dict = f(_numbers_by_name)
    status: str = f(_text(max_len=1024))
    counters: dict = f(_numbers_by_name, default_factory=dict)


@dataclass(frozen=True, slots=True)
class ParamRequest(Message):
    """``op`` ``get`` (``values`` ignored) or ``set`` (``values``: name → new value, all or nothing)."""

    TYPE: ClassVar[str] = "param_request"
    op: str = f(_text(("get", "set")))
    values: dict = f(_mapping, default_factory=dict)


@dataclass(frozen=True, slots=True)
class ParamReply(Message):
    """``ok``: accepted (a set takes effect at the service's next tick boundary). ``values``:
    every parameter's current value (after a set: the values that will be in effect);
    ``error``: why a set was refused (nothing changed)."""

    TYPE: ClassVar[str] = "param_reply"
    ok: bool = f(_flag)
    service: str = f(_text())
    values: dict = f(_mapping)
    error: str = f(_text(max_len=4096), default="")


@dataclass(frozen=True, slots=True)
class ParamStateMsg(Message):
    """Broadcast when parameters take effect: all values, the first ``seq`` they apply to, and
    what the service did to apply them (``note``)."""

    TYPE: ClassVar[str] = "param_state"
    stamp_s: float = f(_STAMP)
    service: str = f(_text())
    seq: int = f(_SEQ)
    values: dict = f(_mapping)
    note: str = f(_text(max_len=4096), default="")


@dataclass(frozen=True, slots=True)
class CommandRequest(Message):
    TYPE: ClassVar[str] = "command"
    name: str = f(_text(max_len=64))
    args: dict = f(_mapping, default_factory=dict)


@dataclass(frozen=True, slots=True)
class CommandReply(Message):
    TYPE: ClassVar[str] = "command_reply"
    ok: bool = f(_flag)
    service: str = f(_text())
    message: str = f(_text(max_len=4096), default="")


@dataclass(frozen=True, slots=True)
class TelemetryMsg(Message):
    """What a real (or MAVLink-simulated) vehicle reports through the PX4 gateway, about 10 Hz.
    Attitude in ENU/FLU like every other message (the gateway converts from PX4's NED/FRD);
    ``pos_enu_m``/``vel_enu_mps``: PX4's own position estimate; ``battery_remaining``: 0–1, −1
    unknown; ``hover_thrust_norm``: the gateway's learned hover thrust (0–1); ``setpoint_age_s``:
    seconds since the last controller setpoint (−1: none yet); ``failsafe``: ``""``, ``hold`` or
    ``land`` when the gateway acted on its own; ``autopilot``: the vehicle's firmware and version as it
    reports them (``PX4 v1.16.0 6ea3539``; ``""`` until known); ``status_text``: the vehicle's newest own
    message (STATUSTEXT), its severity first (``WARNING: Arming denied: …``)."""

    TYPE: ClassVar[str] = "telemetry"
    stamp_s: float = f(_STAMP)
    connected: bool = f(_flag)
    armed: bool = f(_flag)
    in_air: bool = f(_flag)
    flight_mode: str = f(_text(max_len=32))
    roll_rad: float = f(_ANGLE)
    pitch_rad: float = f(_ANGLE)
    yaw_rad: float = f(_ANGLE)
    pos_enu_m: tuple = f(_POS)
    vel_enu_mps: tuple = f(_VEL)
    battery_v: float = f(_number(0.0, 100.0))
    battery_remaining: float = f(_number(-1.0, 1.0))
    hover_thrust_norm: float = f(_number(0.0, 1.0))
    setpoint_age_s: float = f(_number(-1.0))
    failsafe: str = f(_text(("", "hold", "land")))
    autopilot: str = f(_text(max_len=64), default="")
    status_text: str = f(_text(max_len=160), default="")


@dataclass(frozen=True, slots=True)
class RecordingMsg(Message):
    """The recorder's state, 1 Hz and on every change. ``flight``: flight id (empty when idle);
    ``segment``: 0 for a flight's first file, +1 for each restart of the recorder within it;
    ``path``: the ``.rrd`` being written; ``dropped``: messages not written (queue full)."""

    TYPE: ClassVar[str] = "recording"
    stamp_s: float = f(_STAMP)
    recording: bool = f(_flag)
    flight: str = f(_text())
    segment: int = f(_SEQ)
    path: str = f(_text(max_len=1024))
    duration_s: float = f(_number(0.0))
    size_bytes: int = f(_SEQ)
    dropped: int = f(_SEQ)


@dataclass(frozen=True, slots=True)
class NetworkMsg(Message):
    """The estimator's networks, 1 Hz and on every change. ``active``/``candidate``/``previous``:
    maps with at least ``id``; ``active`` also ``source`` (where it came from: file, registry,
    scaled), ``feature_set``, ``lipschitz_norm`` and ``lipschitz_phys`` (certified, normalised and
    (m/s²)/unit z); ``candidate`` is empty when there is none and else carries ``state``
    (``shadow``), the gate's findings, its ``certificate`` and the trainer's ``predicted`` closed-loop
    RMSE. ``shadow_error_rms_mps2``: the candidate's RMS error against f̂ over the shadow window
    (−1: no candidate). ``certificate``: the estimator's verdict for what flies
    (:meth:`neso.certificate.FlightCertificate.to_dict` plus ``pathway``); ``canary``: ``armed``,
    ``last`` (its last verdict), ``window_samples``, ``margin``."""

    TYPE: ClassVar[str] = "network"
    stamp_s: float = f(_STAMP)
    seq: int = f(_SEQ)
    active: dict = f(_mapping)
    candidate: dict = f(_mapping)
    previous: dict = f(_mapping)
    shadow_error_rms_mps2: float = f(_number(-1.0))
    certificate: dict = f(_mapping, default_factory=dict)
    canary: dict = f(_mapping, default_factory=dict)


@dataclass(frozen=True, slots=True)
class ReplayMsg(Message):
    """A recorded flight being published again (``neso replay --to-bus``): at the start, once a
    second and at the end (``playing`` false), so a watcher labels the vehicle's samples as a
    replay and says where they came from. ``file``: the recording; ``origin``: what it records
    (a flight of this system, or a PX4 log imported, with its version and hardware);
    ``t_s``/``duration_s``: flight time replayed so far / in all; ``speed``: the pace factor."""

    TYPE: ClassVar[str] = "replay"
    stamp_s: float = f(_STAMP)
    file: str = f(_text(max_len=1024))
    origin: str = f(_text(max_len=1024))
    t_s: float = f(_number(0.0))
    duration_s: float = f(_number(0.0))
    speed: float = f(_number(0.0))
    playing: bool = f(_flag)


PREFLIGHT_VERDICTS = ("go", "no-go", "warning")


def _preflight_items(x: Any) -> dict:
    """``{item: [verdict, what was found, the fix]}`` (the fix empty when it is fine), at most 64 items."""
    items = _mapping(x)
    if len(items) > 64:
        raise SchemaError(f"{len(items)} preflight items, at most 64")
    for name, entry in items.items():
        if (not isinstance(entry, list) or len(entry) != 3 or entry[0] not in PREFLIGHT_VERDICTS
                or not all(isinstance(v, str) and len(v) <= 512 for v in entry)):
            raise SchemaError(f"preflight item {name!r}: expected [verdict, found, fix] texts, verdict one of "
                              f"{PREFLIGHT_VERDICTS}")
    return items


@dataclass(frozen=True, slots=True)
class PreflightMsg(Message):
    """The px4_gateway's verdict on whether the vehicle may arm (:mod:`flight.preflight`), published after every
    check and at 1 Hz: ``go`` (no item no-go), ``items`` (one per check, in order: ``[verdict, found, fix]``),
    ``checked_s`` the monotonic time of the check, ``override``: why an operator armed on a no-go ("" none)."""

    TYPE: ClassVar[str] = "preflight"
    stamp_s: float = f(_STAMP)
    checked_s: float = f(_STAMP)
    go: bool = f(_flag)
    items: dict = f(_preflight_items)
    override: str = f(_text(max_len=512), default="")


OFFER_COMMANDS = ("offer",)  # commands that travel on the ``offer`` key, not ``cmd``


# -- keys -----------------------------------------------------------------------------------------
# Stream topics: name → message type. The per-service keys (event, health, alive, param,
# params, cmd) exist for every service and are built by Keys.
TOPICS: dict[str, type[Message]] = {
    "state": StateMsg,
    "truth": TruthMsg,
    "estimate": EstimateMsg,
    "setpoint": SetpointMsg,
    "reference": ReferenceMsg,
    "telemetry": TelemetryMsg,
    "recording": RecordingMsg,
    "network": NetworkMsg,
    "replay": ReplayMsg,
    "preflight": PreflightMsg,
}
# The control loop's streams (source → estimator → controller → source/vehicle): with the bus's
# priorities on (runtime.bus.BusConfig.priorities) they travel at Zenoh's real-time priority.
LOOP_TOPICS: tuple[str, ...] = ("state", "estimate", "setpoint")


@dataclass(frozen=True)
class Keys:
    """Every key expression of one vehicle."""

    vehicle: str

    def __post_init__(self) -> None:
        valid_name(self.vehicle, "vehicle")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.vehicle}"

    def topic(self, name: str) -> str:
        if name not in TOPICS:
            raise KeyError(f"unknown topic {name!r}; known: {sorted(TOPICS)}")
        return f"{self.prefix}/{name}"

    def _per_service(self, kind: str, service: str) -> str:
        return f"{self.prefix}/{kind}/{valid_name(service, 'service')}"

    def event(self, service: str) -> str:
        return self._per_service("event", service)

    def health(self, service: str) -> str:
        return self._per_service("health", service)

    def alive(self, service: str) -> str:
        return self._per_service("alive", service)

    def param(self, service: str) -> str:
        return self._per_service("param", service)

    def params(self, service: str) -> str:
        return self._per_service("params", service)

    def cmd(self, service: str) -> str:
        return self._per_service("cmd", service)

    def offer(self, service: str) -> str:
        return self._per_service("offer", service)

    def every(self, kind: str) -> str:
        """All services' keys of one kind (``event``, ``health``, ``alive``, ``params``)."""
        return f"{self.prefix}/{kind}/*"


def any_vehicle(suffix: str) -> str:
    """A key expression matching ``suffix`` (e.g. ``state``, ``health/*``) of every vehicle."""
    return f"{ROOT}/*/{suffix}"


def vehicle_of(key: str) -> str:
    """The vehicle name in a key expression ``neso/<v>/...`` (ValueError if it is not one)."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise ValueError(f"{key!r} is not a key under {ROOT}/<vehicle>/")
    return valid_name(parts[1], "vehicle")


def state_measurement(msg: StateMsg):
    """The ``neso`` measurement a state message carries (arrays of shape (3,))."""
    return StateMeasurement(t_s=msg.t_s, pos_enu_m=np.array(msg.pos_enu_m), vel_enu_mps=np.array(msg.vel_enu_mps),
                            roll_rad=msg.roll_rad, pitch_rad=msg.pitch_rad, yaw_rad=msg.yaw_rad)


def vec(x) -> tuple[float, ...]:
    """A numpy vector (or any sequence of numbers) as the tuple of floats a message field holds."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64:
        return tuple(x.tolist())  # the same floats, without a Python loop
    return tuple(float(v) for v in x)
