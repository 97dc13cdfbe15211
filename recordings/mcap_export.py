"""A recording as MCAP with JSON messages and JSON Schemas, for Foxglove and PlotJuggler.

``neso recordings export FILE.rrd --mcap OUT.mcap``. One MCAP channel per key expression
(``neso/uav1/state``, ``neso/uav1/health/estimator`` …, the topic named exactly like the key), one
schema per message type (encoding ``jsonschema``, named ``neso.<type>``, generated from the schema
module's dataclasses: numbers, integers, booleans, vectors as arrays of numbers, text, maps), and each
message a JSON object with every field (message encoding ``json``; floats written with Python's
shortest round-trip repr, so values read back bit-exact). ``log_time`` and ``publish_time`` are the
message's ``stamp_s`` in integer nanoseconds; ``sequence`` its ``seq`` where it has one. The
recording's properties go into MCAP metadata records (``neso.<property>``, values as JSON text).
Foxglove plots ``neso/uav1/state.pos_enu_m[2]``; PlotJuggler's JSON parser flattens the arrays.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from recordings.layout import fields_of, message_type
from recordings.reader import Recording, RecordingError, read_recording
from runtime.schema import ROOT

_JSON_TYPES = {"number": {"type": "number"}, "integer": {"type": "integer"}, "flag": {"type": "boolean"},
               "text": {"type": "string"}, "json": {"type": "object"}}


def json_schema(cls) -> dict:
    """The JSON Schema of a message type (every field required, no others)."""
    props = {}
    for spec in fields_of(cls):
        if spec.kind == "vector":
            props[spec.name] = {"type": "array", "items": {"type": "number"}}
        else:
            props[spec.name] = dict(_JSON_TYPES[spec.kind])
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": f"neso.{cls.TYPE}",
            "description": (cls.__doc__ or "").strip().split("\n\n")[0], "type": "object", "properties": props,
            "required": list(props), "additionalProperties": False}


def message_json(msg) -> dict:
    """A message as a JSON-able object (vectors as lists)."""
    return {spec.name: (list(v) if isinstance(v := getattr(msg, spec.name), tuple) else v)
            for spec in fields_of(type(msg))}


@dataclass(frozen=True)
class ExportSummary:
    path: Path
    channels: dict[str, int]  # topic (key expression) → messages written

    def report(self) -> str:
        return (f"wrote {self.path}: {sum(self.channels.values())} messages on {len(self.channels)} channels "
                f"({', '.join(f'{k} {n}' for k, n in self.channels.items())})")


def export_mcap(rec: Recording | str | Path, out: str | Path) -> ExportSummary:
    """Write every channel of ``rec`` (a recording or its path) to ``out`` (written through a temporary file)."""
    from mcap.writer import Writer

    if not isinstance(rec, Recording):
        rec = read_recording(rec)
    items = []  # (log_time_ns, order, channel key, message)
    for vehicle, channels in rec.vehicles.items():
        for name, channel in channels.items():
            for msg in channel.messages():
                items.append((int(round(msg.stamp_s * 1e9)), len(items), f"{ROOT}/{vehicle}/{name}", name, msg))
    if not items:
        raise RecordingError(f"{rec.path}: nothing to export (no messages)")
    items.sort(key=lambda x: (x[0], x[1]))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.writing")
    counts: dict[str, int] = {}
    try:
        with open(tmp, "wb") as f:
            writer = Writer(f)
            writer.start(profile="", library="neso recordings export")
            schemas: dict[str, int] = {}
            channel_ids: dict[str, int] = {}
            for _, _, key, name, msg in items:
                if key not in channel_ids:
                    cls = message_type(name)
                    if cls.TYPE not in schemas:
                        schemas[cls.TYPE] = writer.register_schema(
                            name=f"neso.{cls.TYPE}", encoding="jsonschema", data=json.dumps(json_schema(cls)).encode())
                    channel_ids[key] = writer.register_channel(topic=key, message_encoding="json",
                                                               schema_id=schemas[cls.TYPE])
                    counts[key] = 0
                ns = int(round(msg.stamp_s * 1e9))
                writer.add_message(channel_ids[key], log_time=ns, publish_time=ns, sequence=getattr(msg, "seq", counts[key]),
                                   data=json.dumps(message_json(msg), separators=(",", ":")).encode())
                counts[key] += 1
            for prop, values in rec.properties.items():
                if isinstance(values, dict):
                    writer.add_metadata(f"neso.{prop}", {str(k): json.dumps(v, default=str) for k, v in values.items()})
            writer.finish()
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return ExportSummary(out, dict(sorted(counts.items())))
