"""The compiled (msgspec) decoding path accepts exactly what the Python validators accept, with the same values.

:func:`runtime.schema.decode` tries msgspec first and hands anything it refuses to
:func:`runtime.schema.decode_python` (the definition of the rules, and the reasons). So the one way it could go
wrong is msgspec accepting a payload the Python rules refuse, or giving other values: every payload here is
decoded both ways and must give the same message (compared by ``repr``: types and ``-0.0`` included) or the
same refusal.
"""
from __future__ import annotations

import dataclasses
import math
import random

import msgpack
import msgspec
import pytest

from runtime import schema
from runtime.schema import SCHEMA_VERSION, SchemaError
from tests.helpers import EXAMPLES

LOOP = (schema.StateMsg, schema.TruthMsg, schema.EstimateMsg, schema.SetpointMsg, schema.ReferenceMsg,
        schema.HealthMsg, schema.EventMsg, schema.TelemetryMsg)
COMPILED = [m for m in EXAMPLES if schema.compile_decoder(type(m)) is not None]

# values that sit on, just past or across every rule: kinds, bounds, finiteness, lengths, enums
TRICKY = [math.nan, math.inf, -math.inf, True, False, 0, 1, -1, 0.0, -0.0, 1.5, 4.0, 4.000001, -4.0, 1e4, 1e4 + 1,
          1e9, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1, -2**63, 1e308, -1e308, "", "x", "sim", "px4", "camera",
          "hold", "info", "neural_eso", "é" * 256, "é" * 257, "a" * 4097, b"bin", None, [], [1, 2], [1, 2, 3],
          [1.0, 2.0, 3.0], [0.0, math.nan, 0.0], [0.0, 0.0, 1e9], [1, 2, True], [1.0] * 16, [1.0] * 17,
          (1e6, -1e6), [1e6 + 1], {}, {"a": 1}, {"a": 1.5}, {"a": math.nan}, {"a": "b"}, {"a": True},
          {f"k{i}": 1.0 for i in range(257)}, [[1.0]], {"a": [1]}]


def outcome(decode, cls, data: bytes) -> str:
    try:
        return repr(decode(cls, data))
    except SchemaError as exc:
        return f"refused: {exc}"


def variants(msg) -> list[bytes]:
    """Payloads around ``msg``: each field set to each tricky value, dropped, an unknown field, other
    versions and types, truncations and byte flips."""
    body = msgpack.unpackb(msg.to_bytes())
    out = [msg.to_bytes()]
    for name in body:
        out.append(msgpack.packb({k: v for k, v in body.items() if k != name}))
        out += [msgpack.packb({**body, name: value}) for value in TRICKY]
        if isinstance(body[name], list):  # int elements where floats travel, and the elements' own bounds
            out.append(msgpack.packb({**body, name: [int(v) for v in body[name]]}))
            out += [msgpack.packb({**body, name: [value] + body[name][1:]}) for value in TRICKY if body[name]]
    out += [msgpack.packb({**body, "v": v}) for v in (SCHEMA_VERSION + 1, True, float(SCHEMA_VERSION), "1")]
    out += [msgpack.packb({**body, "surprise": 1}), msgpack.packb({**body, 7: 1}), msgpack.packb(list(body.values()))]
    data = msg.to_bytes()
    rng = random.Random(len(data))
    for _ in range(300):
        flipped = bytearray(data)
        for _ in range(rng.randint(1, 3)):
            flipped[rng.randrange(len(flipped))] = rng.getrandbits(8)
        out.append(bytes(flipped))
    out += [data[:n] for n in range(0, len(data), 7)] + [data + b"\x00"]
    return out


def test_the_loops_messages_decode_on_the_compiled_path():
    for cls in LOOP:
        assert schema.compile_decoder(cls) is not None, cls.__name__


@pytest.mark.parametrize("msg", COMPILED, ids=lambda m: type(m).__name__)
def test_the_compiled_path_accepts_exactly_what_the_python_rules_accept(msg):
    cls = type(msg)
    decoder = schema.compile_decoder(cls)
    accepted_by_msgspec = refused_by_msgspec = 0
    for data in variants(msg):
        assert outcome(schema.decode, cls, data) == outcome(schema.decode_python, cls, data), data
        try:
            decoder.decode(data)
            accepted_by_msgspec += 1
        except (msgspec.MsgspecError, UnicodeDecodeError):  # a bad string is msgspec's UnicodeDecodeError
            refused_by_msgspec += 1
    assert accepted_by_msgspec > 1 and refused_by_msgspec > 50  # both ways really taken


def test_a_field_added_later_gets_its_default_on_the_compiled_path():
    body = msgpack.unpackb(EXAMPLES[3].to_bytes())
    del body["estimate_stamp_s"]
    decoded = schema.compile_decoder(schema.SetpointMsg).decode(msgpack.packb(body))
    assert dataclasses.astuple(schema.SetpointMsg.from_bytes(msgpack.packb(body)))[-1] == 0.0
    assert decoded.estimate_stamp_s == 0.0


def test_a_refused_payload_names_its_reason_as_before():
    body = msgpack.unpackb(EXAMPLES[0].to_bytes())
    with pytest.raises(SchemaError, match=r"field 'roll_rad': 7.0 is outside \[-4.0, 4.0\]"):
        schema.StateMsg.from_bytes(msgpack.packb({**body, "roll_rad": 7.0}))
