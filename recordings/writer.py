"""Messages in, one ``.rrd`` file out: a Rerun recording stream with a file sink, written in columns.

:class:`FlightWriter` buffers messages per channel and, on :meth:`FlightWriter.flush`, sends
each field as one column (``send_columns``: ~10 ms for 60 s of a flight, where row-by-row
logging costs ~50 µs a call) and flushes the stream to the file. Call ``flush`` every
0.1 s and a crash loses at most what arrived since the last one.

A flight is one recording (``recording_id`` = flight id); a recorder restarted during a flight
writes the next *segment* of the same flight into a new file, with the same recording id.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from recordings.layout import (APPLICATION_ID, ARENA_ENTITY, ARENA_HALF_SIZE_M, LOOP_LATENCY, POSE_ENTITY,
                               REFERENCE_POINT, SAMPLED_TOPICS, VECTOR_SERIES, Z_ONLY, blueprint, channel_entity,
                               component, entity, fields_of, is_plotted, message_type)
from runtime.schema import EventMsg, Message, ROOT

_TEXT_LEVEL = {"info": "INFO", "warning": "WARN", "error": "ERROR"}


def segment_path(directory: str | Path, flight: str, segment: int) -> Path:
    """Where segment ``segment`` of flight ``flight`` is written."""
    return Path(directory) / f"{flight}.seg{segment}.rrd"


@dataclass
class WriterStats:
    messages: int = 0
    flushes: int = 0
    first_stamp_s: float | None = None
    last_stamp_s: float | None = None
    first_t_s: float | None = None
    last_t_s: float | None = None
    flush_s: list[float] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        if self.first_t_s is not None and self.last_t_s is not None:
            return max(0.0, self.last_t_s - self.first_t_s)
        if self.first_stamp_s is None or self.last_stamp_s is None:
            return 0.0
        return max(0.0, self.last_stamp_s - self.first_stamp_s)


class _Arrow:
    """A ready Arrow array as a Rerun component batch (``rr.ComponentBatchLike``): building the
    columns straight from numpy costs a fraction of ``rr.AnyValues`` (which inspects each value)."""

    def __init__(self, array) -> None:
        self._array = array

    def as_arrow_array(self):
        return self._array


def _field_column(name: str, kind: str, values: list):
    """One field of a batch of messages as a column of one-row (vectors: k-row) components."""
    import pyarrow as pa
    import rerun as rr

    if kind == "vector":  # rows may differ in length (an estimate's z when the network's inputs change)
        rows = [np.asarray(v, dtype=float).reshape(-1) for v in values]
        return rr.ComponentColumn(name, _Arrow(pa.array(np.concatenate(rows))), lengths=[len(r) for r in rows])
    if kind == "number":
        data = pa.array(np.array(values, dtype=float))
    elif kind == "integer":
        data = pa.array(np.array(values, dtype=np.int64))
    elif kind == "flag":
        data = pa.array(np.array(values, dtype=bool))
    elif kind == "text":
        data = pa.array([str(v) for v in values], type=pa.string())
    else:
        data = pa.array([json.dumps(v, sort_keys=True) for v in values], type=pa.string())
    return rr.ComponentColumn(name, _Arrow(data))


class FlightWriter:
    """One segment of one flight of one vehicle into ``path``.

    ``properties``: name → map of plain values, stored as recording properties (flight,
    vehicle, segment, config, scenario…; maps and lists become JSON text)."""

    def __init__(self, path: str | Path, *, vehicle: str, flight: str, segment: int = 0,
                 properties: dict[str, dict] | None = None) -> None:
        import rerun as rr

        self._rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.vehicle, self.flight, self.segment = vehicle, flight, segment
        self.stats = WriterStats()
        self._buffers: dict[str, list[Message]] = {}
        self._t_at_add: dict[str, list[float | None]] = {}
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=flight, send_properties=True)
        self.rec.save(str(self.path), default_blueprint=blueprint(vehicle))
        self.rec.send_recording_name(f"{flight} segment {segment}")
        self.set_properties({"flight": {"flight": flight, "vehicle": vehicle, "segment": segment,
                                        "started_unix_s": time.time()}})
        if properties:
            self.set_properties(properties)
        self._static_scene()
        self.closed = False

    def set_properties(self, properties: dict[str, dict]) -> None:
        for name, values in properties.items():
            plain = {k: (json.dumps(v, default=str) if isinstance(v, (dict, list, tuple)) else v)
                     for k, v in values.items() if v is not None}
            if plain:
                self.rec.send_property(name, self._rr.AnyValues(**plain))

    def _static_scene(self) -> None:
        rr = self._rr
        pose = f"{ROOT}/{self.vehicle}/state/{POSE_ENTITY}"
        # the vehicle at its real size (0.37 m across the rotors): body, two arms, four rotor discs
        rr.log(f"{pose}/body", rr.Boxes3D(centers=[[0, 0, 0], [0, 0, 0], [0, 0, 0]],
                                          half_sizes=[[0.08, 0.08, 0.025], [0.185, 0.01, 0.006], [0.185, 0.01, 0.006]],
                                          rotation_axis_angles=[rr.RotationAxisAngle([0, 0, 1], 0.0),
                                                                rr.RotationAxisAngle([0, 0, 1], 0.785398),
                                                                rr.RotationAxisAngle([0, 0, 1], -0.785398)],
                                          colors=[[40, 60, 90]] * 3, fill_mode="solid"),
               static=True, recording=self.rec)
        rotors = [[0.13, 0.13, 0.02], [-0.13, 0.13, 0.02], [-0.13, -0.13, 0.02], [0.13, -0.13, 0.02]]
        rr.log(f"{pose}/rotors", rr.Cylinders3D(lengths=[0.012] * 4, radii=[0.065] * 4, centers=rotors,
                                                colors=[[210, 70, 50], [80, 80, 80], [80, 80, 80], [210, 70, 50]],
                                                fill_mode="solid"), static=True, recording=self.rec)
        h = ARENA_HALF_SIZE_M
        rr.log(ARENA_ENTITY, rr.LineStrips3D([[[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0], [-h, -h, 0]]],
                                             colors=[[160, 160, 160]]), static=True, recording=self.rec)
        for topic in SAMPLED_TOPICS:  # name the plotted series; vectors where z is what matters: z alone
            for spec in fields_of(message_type(topic)):
                if spec.kind == "vector" and is_plotted(topic, spec.name):
                    names = [Z_ONLY[(topic, spec.name)]] if (topic, spec.name) in Z_ONLY else \
                        [f"{topic} {spec.name} {c}" for c in VECTOR_SERIES]
                    rr.log(entity(self.vehicle, topic, spec.name), rr.SeriesLines(names=names), static=True,
                           recording=self.rec)
        rr.log(entity(self.vehicle, "setpoint", LOOP_LATENCY), rr.SeriesLines(names=["state → setpoint"]), static=True,
               recording=self.rec)
        rr.log(f"{ROOT}/{self.vehicle}/state/{REFERENCE_POINT}", rr.Points3D.from_fields(colors=[[30, 110, 220]],
                                                                                       radii=[0.012]),
               static=True, recording=self.rec)
        rr.log(f"{ROOT}/{self.vehicle}/reference/{REFERENCE_POINT}", rr.Points3D.from_fields(colors=[[240, 140, 20]],
                                                                                           radii=[0.01]),
               static=True, recording=self.rec)

    # -- messages -----------------------------------------------------------------------
    def add(self, channel: str, msg: Message) -> None:
        """Buffer one message of ``channel`` (a topic, or ``health/<service>`` etc.)."""
        self._buffers.setdefault(channel, []).append(msg)
        self._t_at_add.setdefault(channel, []).append(self.stats.last_t_s)
        s = self.stats
        s.messages += 1
        stamp = getattr(msg, "stamp_s", None)
        if stamp is not None:
            s.first_stamp_s = stamp if s.first_stamp_s is None else s.first_stamp_s
            s.last_stamp_s = stamp
        t = getattr(msg, "t_s", None)
        if channel == "state" and t is not None:
            s.first_t_s = t if s.first_t_s is None else s.first_t_s
            s.last_t_s = t

    def flush(self) -> int:
        """Write what was buffered and flush the file; the number of messages written."""
        started = time.perf_counter()
        buffers, self._buffers = self._buffers, {}
        t_at_add, self._t_at_add = self._t_at_add, {}
        n = 0
        for channel, msgs in buffers.items():
            self._send(channel, msgs, t_at_add[channel])
            n += len(msgs)
        self.rec.flush()
        self.stats.flushes += 1
        self.stats.flush_s.append(time.perf_counter() - started)
        del self.stats.flush_s[:-1000]
        return n

    def close(self) -> None:
        if self.closed:
            return
        self.flush()
        self.rec.disconnect()
        self.closed = True

    # -- columns ------------------------------------------------------------------------
    def _send(self, channel: str, msgs: list[Message], t_at_add: list[float | None]) -> None:
        rr = self._rr
        cls = message_type(channel)
        topic = channel.split("/")[0]
        stamps = np.array([m.stamp_s for m in msgs], dtype=float)
        indexes = [rr.TimeColumn("stamp", duration=stamps)]
        if topic in SAMPLED_TOPICS:
            indexes += [rr.TimeColumn("seq", sequence=np.array([m.seq for m in msgs], dtype=np.int64)),
                        rr.TimeColumn("t", duration=np.array([m.t_s for m in msgs], dtype=float))]
        elif all(t is not None for t in t_at_add):  # events, health, params: at the flight time they arrived
            indexes.append(rr.TimeColumn("t", duration=np.array(t_at_add, dtype=float)))
        columns = []
        for spec in fields_of(cls):
            values = [getattr(m, spec.name) for m in msgs]
            columns.append(_field_column(component(cls, spec.name), spec.kind, values))
            if is_plotted(channel, spec.name):
                arr = np.array(values, dtype=float)
                if (topic, spec.name) in Z_ONLY:
                    arr = arr[:, 2]
                scalars = rr.Scalars.columns(scalars=arr.reshape(-1))
                if arr.ndim == 2:
                    scalars = scalars.partition([arr.shape[1]] * len(msgs))
                rr.send_columns(entity(self.vehicle, channel, spec.name), indexes=indexes, columns=scalars,
                                recording=self.rec)
        if topic == "setpoint":
            latency_ms = (stamps - np.array([m.state_stamp_s for m in msgs], dtype=float)) * 1e3
            rr.send_columns(entity(self.vehicle, channel, LOOP_LATENCY), indexes=indexes,
                            columns=rr.Scalars.columns(scalars=latency_ms), recording=self.rec)
        rr.send_columns(channel_entity(self.vehicle, channel), indexes=indexes, columns=columns, recording=self.rec)
        if isinstance(msgs[0], EventMsg):
            rr.send_columns(f"{ROOT}/{self.vehicle}/{channel}/log", indexes=indexes,
                            columns=rr.TextLog.columns(text=[m.text for m in msgs],
                                                       level=[_TEXT_LEVEL.get(m.level, "INFO") for m in msgs]),
                            recording=self.rec)
        if topic == "state":
            self._send_pose(msgs, indexes)
            rr.send_columns(f"{ROOT}/{self.vehicle}/state/{REFERENCE_POINT}", indexes=indexes,
                            columns=rr.Points3D.columns(positions=np.array([m.pos_enu_m for m in msgs])),
                            recording=self.rec)
        elif topic == "reference":
            rr.send_columns(f"{ROOT}/{self.vehicle}/reference/{REFERENCE_POINT}", indexes=indexes,
                            columns=rr.Points3D.columns(positions=np.array([m.pos_enu_m for m in msgs])),
                            recording=self.rec)

    def _send_pose(self, msgs, indexes) -> None:
        from neso.rotations import world_from_body_zyx

        rr = self._rr
        mats = np.array([world_from_body_zyx(m.roll_rad, m.pitch_rad, m.yaw_rad) for m in msgs])
        rr.send_columns(f"{ROOT}/{self.vehicle}/state/{POSE_ENTITY}", indexes=indexes,
                        columns=rr.Transform3D.columns(translation=np.array([m.pos_enu_m for m in msgs]), mat3x3=mats),
                        recording=self.rec)
