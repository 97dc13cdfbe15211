"""Every message round-trips bit-exactly; malformed, unknown-version and out-of-range payloads are refused."""
from __future__ import annotations

import dataclasses
import math
import random

import msgpack
import pytest

from neso.estimator import PATHWAYS as METHOD_PATHWAYS
from runtime import schema
from runtime.schema import (PATHWAYS, SCHEMA_VERSION, EstimateMsg, Keys, Message, ParamRequest, SchemaError,
                            SetpointMsg, StateMsg, any_vehicle, vehicle_of)
from tests.helpers import EXAMPLES


def all_message_classes():
    return {cls for cls in vars(schema).values()
            if isinstance(cls, type) and issubclass(cls, Message) and cls is not Message}


def test_fields_added_later_have_defaults_so_older_payloads_still_decode():
    """estimate_stamp_s and counters came after the first recordings and peers: a payload without them decodes."""
    import msgpack

    for msg, name, default in ((EXAMPLES[3], "estimate_stamp_s", 0.0), (EXAMPLES[6], "counters", {})):
        body = msgpack.unpackb(msg.to_bytes())
        del body[name]
        assert getattr(type(msg).from_bytes(msgpack.packb(body)), name) == default


def test_every_message_class_has_an_example():
    assert {type(m) for m in EXAMPLES} == all_message_classes()


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_round_trip_is_exact(msg):
    back = type(msg).from_bytes(msg.to_bytes())
    assert back == msg
    assert type(msg).from_bytes(back.to_bytes()) == back


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda m: type(m).__name__)
def test_malformed_variants_are_refused(msg):
    body = msgpack.unpackb(msg.to_bytes())
    bad = [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb([1, 2]), msg.to_bytes()[:-1],
           msgpack.packb({**body, "v": SCHEMA_VERSION + 1}), msgpack.packb({**body, "type": "other"}),
           msgpack.packb({**body, "surprise": 1})]
    for fld in dataclasses.fields(msg):
        required = fld.default is dataclasses.MISSING and fld.default_factory is dataclasses.MISSING
        if required:
            bad.append(msgpack.packb({k: v for k, v in body.items() if k != fld.name}))
        bad.append(msgpack.packb({**body, fld.name: [None, {"x": b"\x00"}]}))
    for data in bad:
        with pytest.raises(SchemaError):
            type(msg).from_bytes(data)


@pytest.mark.parametrize("field,value", [
    ("pos_enu_m", [0.0, 0.0]), ("pos_enu_m", [0.0, math.nan, 0.0]), ("pos_enu_m", [0.0, 0.0, math.inf]),
    ("pos_enu_m", [0.0, 0.0, 1e9]), ("roll_rad", 7.0), ("seq", -1), ("seq", 1.5), ("seq", True),
    ("source", "camera"), ("t_s", "now"),
])
def test_out_of_range_state_fields_are_refused(field, value):
    body = msgpack.unpackb(EXAMPLES[0].to_bytes())
    with pytest.raises(SchemaError, match=field):
        StateMsg.from_bytes(msgpack.packb({**body, field: value}))


def test_setpoint_thrust_outside_0_1_is_refused():
    body = msgpack.unpackb(EXAMPLES[3].to_bytes())
    for value in (-0.01, 1.01, math.nan):
        with pytest.raises(SchemaError, match="thrust_norm"):
            SetpointMsg.from_bytes(msgpack.packb({**body, "thrust_norm": value}))


def test_random_bytes_are_refused_with_schema_error_and_nothing_else():
    rng = random.Random(0)
    for _ in range(3000):
        data = bytes(rng.getrandbits(8) for _ in range(rng.randrange(0, 200)))
        for cls in (StateMsg, SetpointMsg, EstimateMsg, ParamRequest):
            with pytest.raises(SchemaError):  # any other exception fails the test as it is
                cls.from_bytes(data)


def test_schema_pathways_mirror_the_method():
    assert PATHWAYS == METHOD_PATHWAYS


def test_keys_are_built_in_one_place_and_names_are_checked():
    k = Keys("uav1")
    assert k.topic("state") == "neso/uav1/state"
    assert k.param("estimator") == "neso/uav1/param/estimator"
    assert k.alive("controller") == "neso/uav1/alive/controller"
    for bad in ("", "a/b", "*", "uav 1", "-x"):
        with pytest.raises(ValueError):
            Keys(bad)
    with pytest.raises(KeyError):
        k.topic("nonsense")


def test_any_vehicle_keys_and_the_vehicle_a_key_belongs_to():
    assert any_vehicle("state") == "neso/*/state"
    assert vehicle_of(Keys("uav2").topic("state")) == "uav2"
    assert vehicle_of(Keys("uav2").health("estimator")) == "uav2"
    with pytest.raises(ValueError):
        vehicle_of("other/uav1/state")
