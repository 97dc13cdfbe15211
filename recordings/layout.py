"""How bus messages map onto a Rerun recording, and the blueprint the stock viewer opens.

Entity paths mirror the key expressions. Each channel's messages are stored whole, bit-exact, on
the entity named by its key (``neso/uav1/state``, ``neso/uav1/health/estimator``): one
component per field, named ``<message type>.<field>`` (``state.pos_enu_m``; float64, int64,
bool, a row of float64 for vectors, text; parameter maps as JSON text; the viewer shows them
like ``AnyValues``). The
fields an operator plots are also ``Scalars`` on a child entity named by the field
(``neso/uav1/state/pos_enu_m``, ``neso/uav1/health/estimator/latency_p99_ms``): one chunk per
channel per flush plus one per plotted field, instead of one per field, keeps the live file and
the writer's cost down. Events are also ``TextLog`` on ``<key>/log``.

Timelines: ``stamp`` (every message: its ``stamp_s``, the machine's monotonic clock),
``seq`` and ``t`` (messages of a sample: the sample number and its time ``t_s``; events,
health and parameter broadcasts are put on ``t`` at the newest sample time when they arrived).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from runtime.schema import ROOT, TOPICS, EventMsg, HealthMsg, Message, ParamStateMsg

RECORDINGS_DIR = "out/recordings"  # where the recorder writes flights and everything else looks for them

APPLICATION_ID = "neso"
SAMPLED_TOPICS = ("state", "truth", "estimate", "setpoint", "reference")  # messages with seq and t_s
# per-service kinds recorded (key neso/<v>/<kind>/<service>) and their message type
SERVICE_KINDS: dict[str, type[Message]] = {"event": EventMsg, "health": HealthMsg, "params": ParamStateMsg}
KINDS = ("number", "integer", "flag", "vector", "text", "json")
TIMELINES = ("stamp", "seq", "t")
POSE_ENTITY = "pose"  # neso/<v>/state/pose: the body transform for the 3D view
REFERENCE_POINT = "point"  # neso/<v>/reference/point: the reference position in 3D (and state/point: the vehicle's)
LOOP_LATENCY = "loop_latency_ms"  # neso/<v>/setpoint/loop_latency_ms: state published → setpoint published, per sample
TRAIL_S = 10.0  # the 3D view shows the last seconds of positions as the trail and the reference path
ARENA_ENTITY = "scene/arena"  # static: the floor square the 3D view frames
ARENA_HALF_SIZE_M = 1.5
VECTOR_SERIES = ("x", "y", "z")
# (channel kind, field) also logged as Scalars for the viewer
PLOTTED = {("state", "pos_enu_m"), ("state", "vel_enu_mps"), ("reference", "pos_enu_m"), ("truth", "pos_enu_m"),
           ("truth", "disturbance_acc_enu_mps2"), ("estimate", "f_hat_mps2"), ("estimate", "f_n_mps2"),
           ("estimate", "delta_f_hat_mps2"), ("setpoint", "thrust_n"), ("setpoint", "roll_rad"),
           ("setpoint", "pitch_rad"), ("health", "latency_p50_ms"), ("health", "latency_p99_ms"), ("health", "rate_hz")}
# vector fields plotted as their z component alone (a legend listing hidden x/y series was noise; the
# whole vector is on the channel's entity): field → the series' name in a legend
Z_ONLY = {("state", "pos_enu_m"): "state z", ("reference", "pos_enu_m"): "reference z", ("truth", "pos_enu_m"): "true z",
          ("estimate", "f_hat_mps2"): "f̂ z", ("estimate", "f_n_mps2"): "f_N z", ("estimate", "delta_f_hat_mps2"): "Δf̂ z",
          ("truth", "disturbance_acc_enu_mps2"): "true disturbance z"}


@dataclass(frozen=True)
class FieldSpec:
    name: str
    kind: str  # one of KINDS


def _kind(annotation: str) -> str:
    return {"float": "number", "int": "integer", "bool": "flag", "tuple": "vector", "str": "text",
            "dict": "json"}[str(annotation)]


def fields_of(cls: type[Message]) -> tuple[FieldSpec, ...]:
    """Every recorded field of a message type, with its kind (from the schema's annotations)."""
    return tuple(FieldSpec(f.name, _kind(f.type)) for f in dataclasses.fields(cls))


def message_type(channel: str) -> type[Message]:
    """The message type of a channel: a topic (``state``) or a per-service kind (``health/estimator``)."""
    head = channel.split("/")[0]
    if "/" in channel:
        return SERVICE_KINDS[head]
    return TOPICS[head]


def channel_of(key: str) -> tuple[str, str] | None:
    """(vehicle, channel) of a key expression: ``neso/uav1/state`` → (``uav1``, ``state``),
    ``neso/uav1/health/estimator`` → (``uav1``, ``health/estimator``); None if not recorded."""
    parts = str(key).split("/")
    if len(parts) == 3 and parts[0] == ROOT and parts[2] in TOPICS:
        return parts[1], parts[2]
    if len(parts) == 4 and parts[0] == ROOT and parts[2] in SERVICE_KINDS:
        return parts[1], f"{parts[2]}/{parts[3]}"
    return None


def channel_entity(vehicle: str, channel: str) -> str:
    """The entity holding a channel's messages whole: its key expression."""
    return f"{ROOT}/{vehicle}/{channel}"


def entity(vehicle: str, channel: str, field: str) -> str:
    """The entity path of one plotted field of one channel."""
    return f"{ROOT}/{vehicle}/{channel}/{field}"


def component(cls: type[Message], field: str) -> str:
    """The ``AnyValues`` component name of one field (type-prefixed: names are global in Rerun)."""
    return f"{cls.TYPE}.{field}"


def is_plotted(channel: str, field: str) -> bool:
    return (channel.split("/")[0], field) in PLOTTED


def parse_channel_entity(path: str) -> tuple[str, str] | None:
    """(vehicle, channel) of an entity written by :func:`channel_entity`, else None."""
    return channel_of(str(path).strip("/"))


def blueprint(vehicle: str):
    """The viewer layout: the 3D scene, following the vehicle with its trail and reference path,
    beside the time series an operator looks at."""
    import rerun.blueprint as rrb

    v = f"/{ROOT}/{vehicle}"
    series = [
        ("height z (m): state, reference, truth", [f"{v}/state/pos_enu_m", f"{v}/reference/pos_enu_m", f"{v}/truth/pos_enu_m"]),
        ("disturbance z (m/s²): f̂, f_N, Δf̂, truth", [f"{v}/estimate/f_hat_mps2", f"{v}/estimate/f_n_mps2",
                                                     f"{v}/estimate/delta_f_hat_mps2", f"{v}/truth/disturbance_acc_enu_mps2"]),
        ("thrust (N)", [f"{v}/setpoint/thrust_n"]),
        ("attitude setpoint (rad)", [f"{v}/setpoint/roll_rad", f"{v}/setpoint/pitch_rad"]),
        ("loop latency state → setpoint (ms)", [f"{v}/setpoint/{LOOP_LATENCY}"]),
    ]
    views = [rrb.TimeSeriesView(name=name, origin="/", contents=[f"+ {p}" for p in paths],
                                plot_legend=rrb.PlotLegend("LeftTop")) for name, paths in series]
    trail = rrb.VisibleTimeRange("t", start=rrb.TimeRangeBoundary.cursor_relative(seconds=-TRAIL_S),
                                 end=rrb.TimeRangeBoundary.cursor_relative())
    scene = rrb.Spatial3DView(
        name="3D", origin="/",
        contents=[f"+ {v}/state/{POSE_ENTITY}/**", f"+ {v}/state/{REFERENCE_POINT}", f"+ {v}/reference/{REFERENCE_POINT}",
                  f"+ /{ARENA_ENTITY}"],
        time_ranges=[trail],
        eye_controls=rrb.EyeControls3D(position=(0.8, -1.1, 1.0), look_target=(0.0, 0.0, 0.4),
                                       tracking_entity=f"{v}/state/{POSE_ENTITY}"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(scene, rrb.TextLogView(name="events", origin=f"{v}/event"), row_shares=[3, 1]),
            rrb.Vertical(*views),
            column_shares=[2, 3],
        ),
        rrb.TimePanel(timeline="t"),
        collapse_panels=True,
    )
